"""``swarmmap up``: the whole system as local processes on loopback, and its run directory.

Starts a router on a free port, the Rerun observer (unless ``up.observer`` is off), then N
learners and N lidar streamers (each its own OS process, all Zenoh peers connected to the
router, multicast scouting off), waits until they are alive, then starts the world. It
records every learner's ``Metrics`` into ``RUN_DIR/metrics.csv`` as they arrive, and when
every learner has finished (or on Ctrl-C, or when a service fails) stops the rest and writes
``RUN_DIR/summary.json``.

Run directory: ``config.yaml`` (the resolved config; every service reads it), ``metrics.csv``,
``summary.json``, ``groundtruth.png`` and ``groundtruth.npz`` (grid and validation set),
``models/robot-<id>.pt``, ``maps/robot-<id>-mean.png``, ``data/robot-<id>.npz`` (training
points), ``logs/<service>-<id>.log``, ``recording.rrd`` and ``observer.json`` (the observer's
Rerun recording and its time per map).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from swarmmap.shared.atomic import atomic_write_bytes, atomic_write_text, save_png
from swarmmap.shared.bus import Bus
from swarmmap.shared.config import RunConfig, ZenohSettings
from swarmmap.shared.floorplan import PlanError
from swarmmap.shared.plans import plan_reference
from swarmmap.shared.protocol import Keys, Metrics, WorldMap
from swarmmap.shared.recording import RecordingError, read_recording

log = logging.getLogger("up")

METRICS_COLUMNS = ["robot", "round", "wall_time_s", "val_bce", "consensus_error", "bytes_sent", "bytes_received",
                   "compute_s", "wait_s", "send_s", "n_points", "final"]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Child:
    """One service process."""

    service: str
    ident: int
    proc: subprocess.Popen
    log_path: Path

    @property
    def name(self) -> str:
        return f"{self.service}-{self.ident}"


class MetricsRecorder:
    """Appends every Metrics message to metrics.csv and keeps the first and last per robot."""

    def __init__(self, path: Path):
        self.path = path
        self._lock = threading.Lock()
        resuming = path.exists() and path.stat().st_size > 0  # a resumed run keeps the rows it had
        self._file = path.open("a" if resuming else "w", newline="")
        self._csv = csv.writer(self._file)
        if not resuming:
            self._csv.writerow(METRICS_COLUMNS)
        self._file.flush()
        self.first: dict[int, Metrics] = {}
        self.final: dict[int, Metrics] = {}
        self.latest: dict[int, Metrics] = {}

    def add(self, m: Metrics) -> None:
        with self._lock:
            self._csv.writerow([m.sender, m.round, f"{m.wall_time_s:.3f}", f"{m.val_bce:.6f}",
                                f"{m.consensus_error:.6f}", m.bytes_sent, m.bytes_received, f"{m.compute_s:.3f}",
                                f"{m.wait_s:.3f}", f"{m.send_s:.3f}", m.n_points, int(m.final)])
            self._file.flush()
            self.first.setdefault(m.sender, m)
            self.latest[m.sender] = m
            if m.final:
                self.final[m.sender] = m

    def close(self) -> None:
        with self._lock:
            self._file.close()


class Launcher:
    """Starts, watches and stops the services of one run."""

    def __init__(self, cfg: RunConfig, stop: threading.Event):
        self.stop = stop
        run_id = cfg.run_id if cfg.run_id != "default" else time.strftime("run-%Y%m%d-%H%M%S")
        run_dir = (cfg.run_dir or Path("runs") / run_id).resolve()
        self.router_endpoint = f"tcp/127.0.0.1:{free_port()}"
        zenoh = ZenohSettings(mode="peer", connect=[self.router_endpoint], listen=["tcp/127.0.0.1:0"],
                              multicast_scouting=False)
        cfg = cfg.model_copy(update={"run_id": run_id, "run_dir": run_dir, "zenoh": zenoh})
        if cfg.up.replay is not None:
            cfg = replay_config(cfg, cfg.up.replay)
        if cfg.up.record is not None:
            record = str(cfg.up.record.resolve() / "robot-{robot}.swrec")
            cfg = cfg.model_copy(update={"lidar": cfg.lidar.model_copy(update={"record": record})})
        if cfg.up.observer:
            obs = cfg.observer.model_copy(update={"save": cfg.observer.save or run_dir / "recording.rrd",
                                                  "spawn": cfg.observer.spawn or cfg.up.viewer})
            cfg = cfg.model_copy(update={"observer": obs})
        self.cfg = cfg
        self.run_dir = run_dir
        self.keys = Keys(self.cfg.key_prefix, run_id)
        self.children: list[Child] = []
        self.config_path = run_dir / "config.yaml"

    def spawn(self, service: str, ident: int, *extra: str) -> Child:
        """Start ``swarmmap <service>`` reading the run's config.yaml, logging to logs/."""
        log_path = self.run_dir / "logs" / f"{service}-{ident}.log"
        cmd = [sys.executable, "-m", "swarmmap.services.cli", service, "--config", str(self.config_path), *extra]
        # The config file already holds the resolved environment; children must not re-read it.
        env = {k: v for k, v in os.environ.items() if not k.startswith("SWARMMAP_")}
        env["PYTHONUNBUFFERED"] = "1"
        with log_path.open("w") as out:
            proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        child = Child(service, ident, proc, log_path)
        self.children.append(child)
        return child

    def failed(self) -> Child | None:
        for c in self.children:
            code = c.proc.poll()
            if code is not None and (code != 0 or c.service != "learner"):
                return c
        return None

    def wait_alive(self, bus: Bus, service: str, idents: set[str]) -> None:
        deadline = time.monotonic() + self.cfg.up.start_timeout_s
        while not self.stop.is_set():
            missing = idents - {i for _, i in bus.alive(service)}
            if not missing:
                return
            if (bad := self.failed()) is not None:
                raise RuntimeError(f"{bad.name} exited with status {bad.proc.returncode} while starting; "
                                   f"see {bad.log_path}:\n{tail(bad.log_path)}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"{service} {sorted(missing)} not alive after {self.cfg.up.start_timeout_s:.0f} s")
            self.stop.wait(0.1)

    def shutdown(self) -> None:
        """SIGTERM every child (world and streamers first, router last), SIGKILL after the grace time."""
        order = {"world": 0, "lidar": 1, "learner": 2, "observer": 3, "router": 4}
        for c in sorted(self.children, key=lambda c: order[c.service]):
            if c.proc.poll() is None:
                c.proc.terminate()
                grace = self.cfg.up.observer_grace_s if c.service == "observer" else self.cfg.up.stop_grace_s
                try:
                    c.proc.wait(grace)
                except subprocess.TimeoutExpired:
                    log.warning("%s did not stop within %.0f s; killing it", c.name, grace)
                    c.proc.kill()
                    c.proc.wait()

    def run(self) -> int:
        cfg = self.cfg
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / "logs").mkdir(exist_ok=True)
        atomic_write_text(self.config_path, cfg.dump_yaml())
        log.info("run %s: %d robots, %d rounds -> %s", cfg.run_id, cfg.robots, cfg.learner.rounds, self.run_dir)
        t0 = time.monotonic()
        recorder = MetricsRecorder(self.run_dir / "metrics.csv")
        status = 1
        try:
            self.spawn("router", 0, "--zenoh-mode", "router", "--zenoh-listen", self.router_endpoint,
                       "--set", "zenoh.connect=[]")
            with Bus.open(cfg.zenoh, self.keys, "up", 0) as bus:
                bus.subscribe(self.keys.metrics("*"), Metrics, lambda m: self.on_metrics(recorder, m))
                self.wait_alive(bus, "router", {"0"})
                if cfg.up.observer:  # first, so that it sees the run from the start
                    self.spawn("observer", 0)
                ids = {str(i) for i in range(cfg.robots)}
                if cfg.learner.transport == "inproc":  # one process serves every robot (DiNNO's setting)
                    self.spawn("learner", 0)
                for i in range(cfg.robots):
                    if cfg.learner.transport == "zenoh":
                        self.spawn("learner", i, "--robot", str(i))
                    self.spawn("lidar", i, "--robot", str(i))
                self.wait_alive(bus, "learner", ids)
                self.wait_alive(bus, "lidar", ids)
                self.spawn("world", 0)
                self.wait_alive(bus, "world", {"0"})
                world = bus.query(self.keys.world_map(), WorldMap, timeout=30.0, stop=self.stop)
                if world is not None:
                    save_ground_truth(self.run_dir, world)
                status = self.watch(recorder)
        except RuntimeError as exc:
            log.error("%s", exc)
            status = 1
        finally:
            self.shutdown()
            recorder.close()
            self.write_summary(recorder, time.monotonic() - t0)
        return status

    def on_metrics(self, recorder: MetricsRecorder, m: Metrics) -> None:
        recorder.add(m)
        log.info("robot %d round %4d  val_bce %.4f  consensus %.4f%s", m.sender, m.round, m.val_bce,
                 m.consensus_error, "  (final)" if m.final else "")

    def watch(self, recorder: MetricsRecorder) -> int:
        """Wait until every learner has exited; 0 if all finished cleanly."""
        learners = [c for c in self.children if c.service == "learner"]
        while not self.stop.is_set():
            if (bad := self.failed()) is not None:
                log.error("%s exited with status %s; stopping the run. Its log (%s) ends:\n%s",
                          bad.name, bad.proc.returncode, bad.log_path, tail(bad.log_path))
                return 1
            if all(c.proc.poll() is not None for c in learners):
                missing = sorted(set(range(self.cfg.robots)) - recorder.final.keys())
                if missing:
                    log.error("learners %s exited without final metrics", missing)
                    return 1
                log.info("all %d learners finished", len(learners))
                return 0
            self.stop.wait(0.2)
        log.info("interrupted; stopping every service")
        return 130

    def write_summary(self, recorder: MetricsRecorder, wall: float) -> None:
        robots = {}
        learners = {c.ident: c for c in self.children if c.service == "learner"}
        for robot in range(self.cfg.robots):
            c = learners.get(robot) or learners.get(0)  # in-process: learner-0 serves every robot
            if c is None:
                continue
            first, last = recorder.first.get(robot), recorder.final.get(robot) or recorder.latest.get(robot)
            robots[str(robot)] = {
                "pid": c.proc.pid,
                "exit_code": c.proc.returncode,
                "finished": robot in recorder.final,
                "rounds": last.round if last else 0,
                "first_val_bce": first.val_bce if first else None,
                "final_val_bce": last.val_bce if last else None,
                "wall_time_s": last.wall_time_s if last else None,
                "reported_pid": last.pid if last else None,
                "bytes_sent": last.bytes_sent if last else None,
                "bytes_received": last.bytes_received if last else None,
            }
        summary = {
            "run_id": self.cfg.run_id,
            "preset": self.cfg.preset,
            "robots": self.cfg.robots,
            "rounds": self.cfg.learner.rounds,
            "transport": self.cfg.learner.transport,
            "wall_time_s": round(wall, 3),
            "services": {c.name: {"pid": c.proc.pid, "exit_code": c.proc.returncode} for c in self.children},
            "learners": robots,
        }
        atomic_write_text(self.run_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
        log.info("summary: %s", self.run_dir / "summary.json")


def replay_config(cfg: RunConfig, folder: Path) -> RunConfig:
    """The run's config for replaying the recordings in ``folder``: robots, seed, world and
    sensor settings come from the recordings; the world only serves the map."""
    files = sorted(folder.glob("robot-*.swrec"))
    if not files:
        raise RecordingError(folder, "no robot-<i>.swrec recordings in this folder")
    recs = {}
    for f in files:
        rec = read_recording(f, allow_incomplete=cfg.lidar.replay_incomplete)
        recs[rec.robot] = rec
    if sorted(recs) != list(range(len(recs))):
        raise RecordingError(folder, f"recordings of robots {sorted(recs)}; expected robots 0..{len(recs) - 1}")
    recorded = RunConfig.model_validate(recs[0].config)
    plan = recs[0].header.get("plan", {})
    if plan.get("sha256") and plan_reference(plan["floorplan"]).get("sha256") != plan["sha256"]:
        raise RecordingError(folder, f"the recorded floor plan {plan['floorplan']} is missing or has changed since")
    world = recorded.world.model_copy(update={"drive": False})
    lidar = recorded.lidar.model_copy(update={"record": None, "robot": None, "replay": str(folder.resolve() / "robot-{robot}.swrec"),
                                              "replay_speed": cfg.lidar.replay_speed,
                                              "replay_incomplete": cfg.lidar.replay_incomplete})
    return cfg.model_copy(update={"robots": len(recs), "seed": recorded.seed, "world": world, "lidar": lidar})


def save_ground_truth(run_dir: Path, world: WorldMap) -> None:
    """``groundtruth.png`` and ``groundtruth.npz`` (grid, resolution, origin, validation set)."""
    save_png(run_dir / "groundtruth.png", world.grid.numpy().astype(float))
    buf = io.BytesIO()
    np.savez_compressed(buf, grid=world.grid.numpy(), resolution=world.resolution, origin=np.asarray(world.origin),
                        val_points=world.val_points.numpy(), val_labels=world.val_labels.numpy())
    atomic_write_bytes(run_dir / "groundtruth.npz", buf.getvalue())


def tail(path: Path, lines: int = 15) -> str:
    """The last lines of a log file."""
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


def run(cfg: RunConfig, stop: threading.Event) -> int:
    try:
        launcher = Launcher(cfg, stop)
    except (RecordingError, PlanError) as exc:
        log.error("%s", exc)
        return 2
    return launcher.run()
