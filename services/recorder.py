"""``swarmmap recorder``: the run directory and the end of the run, whoever launched it.

Run-book: ``swarmmap recorder --config RUN_DIR/config.yaml`` (or with ``SWARMMAP_RUN_DIR`` and
the run's other settings in the environment, as compose does). Start it before the world
drives: the world waits for ``alive/recorder/0`` (``world.wait_for``). ``swarmmap up``, compose
and the SLURM job scripts all start one, so every launcher leaves the same run directory:

- ``config.yaml`` (the resolved config, when the launcher did not write it already),
  ``metrics.csv`` (every learner's ``Metrics`` as it arrives), ``groundtruth.png`` and
  ``groundtruth.npz`` (the world's map and validation set), ``summary.json`` (per learner:
  first and final val_bce, rounds, bytes; the run's outcome and why), and at the end
  ``overview.png`` (:mod:`swarmmap.shared.overview`: ground truth beside each robot's saved maps).

It also decides when the run is over, and says so on ``run/done`` (``RunDone``), on which
every other service exits: the run succeeded when every learner sent its final ``Metrics``;
it failed when a learner left before finishing (its liveliness token vanished: it crashed or
was killed), or the world or a lidar streamer left while still needed, and did not come back
within ``recorder.rejoin_timeout_s`` (``swarmmap up`` restarts crashed services), or when a
learner never came alive within ``recorder.start_timeout_s``. The recorder then waits up to
``recorder.linger_s`` for the other services to leave and exits 0 (success) or 1 (failure),
so ``docker compose up --exit-code-from recorder`` and a SLURM job end with the run's status.

Its log says what the run is doing, whoever launched it: the phases (every learner alive, the
traversal, the training), a progress line every ``PROGRESS_EVERY_S`` seconds (the scans so
far, then the slowest learner's round, the team's mean, min and max val_bce and the time
left), each learner's Metrics, and at the end the verdict and one line with each robot's final
val_bce, the team's mean, the wall time and the bytes sent.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import threading
import time
from pathlib import Path

import numpy as np

from swarmmap.shared.atomic import atomic_write_bytes, atomic_write_text, save_png
from swarmmap.shared.bus import Bus
from swarmmap.shared.config import RunConfig, fail
from swarmmap.shared.progress import PROGRESS_EVERY_S, TeamProgress, TraversalProgress, duration
from swarmmap.shared.protocol import Keys, Metrics, RunDone, Scan, WorldMap

log = logging.getLogger("recorder")

METRICS_COLUMNS = ["robot", "round", "wall_time_s", "val_bce", "consensus_error", "bytes_sent", "bytes_received",
                   "compute_s", "wait_s", "send_s", "n_points", "final"]
# Services whose tokens say nothing about the run's health (the launcher, tools, Algorithm 1 readiness).
BYSTANDERS = ("up", "status", "exchange", "router", "recorder")


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


class RunTracker:
    """Decides from final Metrics and liveliness whether the run is over, and how it ended.

    Pure bookkeeping (no network), so that the rules can be tested alone."""

    def __init__(self, robots: int, rejoin_timeout: float = 0.0):
        self.robots = robots
        self.rejoin_timeout = rejoin_timeout
        self._lock = threading.Lock()
        self.finished: set[int] = set()
        self.training: set[int] = set()  # learners that reported a round: they hold their data
        self.seen: set[tuple[str, int]] = set()
        self.away: dict[tuple[str, int], tuple[float, str]] = {}  # left while needed: since when, and what it means
        self.failure: str | None = None

    def on_metrics(self, m: Metrics) -> None:
        with self._lock:
            if m.sender < self.robots:
                self.training.add(m.sender)
                if m.final:
                    self.finished.add(m.sender)

    def on_alive(self, service: str, ident: str, alive: bool, now: float | None = None) -> None:
        """A liveliness token came (``alive``) or went. A service that leaves while still needed
        fails the run unless it is back within ``rejoin_timeout`` seconds (a launcher restarts it)."""
        if not ident.isdigit():
            return
        key = (service, int(ident))
        now = time.monotonic() if now is None else now
        with self._lock:
            if alive:
                self.seen.add(key)
                self.away.pop(key, None)
                return
            if key not in self.seen or self.failure is not None or self._all_finished():
                return
            robot = key[1]
            if service == "learner" and robot not in self.finished:
                why = f"learner {robot} left before finishing (its liveliness token vanished: it crashed, was killed or failed)"
            elif service == "lidar" and robot not in self.training:
                why = f"lidar {robot} left before learner {robot} had its training points"
            elif service == "world" and len(self.training) < self.robots:
                why = "the world left before every learner had its training points"
            else:
                return
            self.away[key] = (now, why)

    def learners_missing(self) -> list[int]:
        """Learners never seen alive."""
        with self._lock:
            return sorted(set(range(self.robots)) - {i for s, i in self.seen if s == "learner"})

    def _all_finished(self) -> bool:
        return self.finished >= set(range(self.robots))

    def outcome(self, now: float | None = None) -> tuple[bool, str] | None:
        """(ok, reason) once the run is over, else None."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if self.failure is None and self.away:
                since, why = min(self.away.values())
                if now - since >= self.rejoin_timeout:
                    back = f" and was not back within {self.rejoin_timeout:.0f} s" if self.rejoin_timeout else ""
                    self.failure = why + back
            if self.failure is not None:
                return False, self.failure
            if self._all_finished():
                return True, f"all {self.robots} learners finished"
            return None


class PhaseLog:
    """The run's phases (services alive, traversal, training) and, every ``every`` seconds, a
    progress line, in the recorder's log: what compose, SLURM and ``up`` runs say as they go."""

    def __init__(self, robots: int, rounds: int, every: float = PROGRESS_EVERY_S):
        self.robots = robots
        self.team = TeamProgress(robots, rounds)
        self.traversal = TraversalProgress(robots)
        self.every = every
        self.phase = "waiting"
        self._last = -float("inf")

    def tick(self, tracker: RunTracker, now: float | None = None) -> None:
        """Log a phase that began since the last call, and the progress line when one is due."""
        now = time.monotonic() if now is None else now
        if self.phase == "waiting" and not tracker.learners_missing():
            log.info("every learner is alive (%d); waiting for the world to drive", self.robots)
            self.phase = "ready"
        if self.traversal.started and self.phase in ("waiting", "ready"):
            log.info("traversal: the robots drive their paths")
            self.phase, self._last = "traversal", -float("inf")
        if self.team.started and self.phase != "training":
            if self.traversal.started:
                log.info("%s", self.traversal.line(now))
            log.info("training: the learners have their points")
            self.phase, self._last = "training", -float("inf")
        if now - self._last >= self.every:
            line = self.team.line(now) if self.phase == "training" else self.traversal.line(now)
            if line is not None:
                log.info("%s", line)
                self._last = now


def closing_line(doc: dict) -> str:
    """A finished run in one line: each robot's final val_bce, the team's mean, time and bytes."""
    finals = {r: v["final_val_bce"] for r, v in doc["learners"].items() if v.get("final_val_bce") is not None}
    sent = sum(v.get("bytes_sent") or 0 for v in doc["learners"].values())
    per_robot = ", ".join(f"robot {r} {v:.4f}" for r, v in finals.items()) or "none reported"
    mean = f"; team mean {sum(finals.values()) / len(finals):.4f}" if finals else ""
    return f"final val_bce: {per_robot}{mean}; {duration(doc['wall_time_s'])}; {sent / 1e6:.1f} MB sent by the learners"


def save_ground_truth(run_dir: Path, world: WorldMap) -> None:
    """``groundtruth.png`` and ``groundtruth.npz`` (grid, resolution, origin, validation set)."""
    grid = world.grid.numpy()
    save_png(run_dir / "groundtruth.png", np.where(grid == 2, 0.5, grid.astype(float)))  # unknown (ROS maps): grey
    buf = io.BytesIO()
    np.savez_compressed(buf, grid=world.grid.numpy(), resolution=world.resolution, origin=np.asarray(world.origin),
                        val_points=world.val_points.numpy(), val_labels=world.val_labels.numpy())
    atomic_write_bytes(run_dir / "groundtruth.npz", buf.getvalue())


def summary(cfg: RunConfig, metrics: MetricsRecorder, ok: bool, reason: str, wall: float, started: float | None = None) -> dict:
    """What ``summary.json`` holds: the run's outcome and, per learner, its first and last metrics."""
    learners = {}
    for robot in range(cfg.robots):
        first, last = metrics.first.get(robot), metrics.final.get(robot) or metrics.latest.get(robot)
        learners[str(robot)] = {
            "finished": robot in metrics.final,
            "rounds": last.round if last else 0,
            "first_val_bce": first.val_bce if first else None,
            "final_val_bce": last.val_bce if last else None,
            "wall_time_s": last.wall_time_s if last else None,
            "reported_pid": last.pid if last else None,
            "bytes_sent": last.bytes_sent if last else None,
            "bytes_received": last.bytes_received if last else None,
            "refused": last.refused if last else None,
        }
    return {"run_id": cfg.run_id, "preset": cfg.preset, "robots": cfg.robots, "rounds": cfg.rounds(),
            "transport": cfg.transport(), "ok": ok, "reason": reason, "wall_time_s": round(wall, 3),
            "started": round(time.time() - wall if started is None else started, 3), "finished": round(time.time(), 3),
            "learners": learners}


def write_summary(run_dir: Path, doc: dict, phases: PhaseLog) -> None:
    """Log how the run ended (the verdict, the team's last progress line, the closing line) and
    write ``summary.json``."""
    (log.info if doc["ok"] else log.error)("run %s: %s", "succeeded" if doc["ok"] else "FAILED", doc["reason"])
    if phases.team.started:
        log.info("%s", phases.team.line())
    log.info("%s", closing_line(doc))
    atomic_write_text(run_dir / "summary.json", json.dumps(doc, indent=2) + "\n")


def draw_overview(cfg: RunConfig, notes: dict[int, str]) -> None:
    """``overview.png`` of the maps the learners saved, ``notes`` under each robot's name (a
    figure that fails is logged, never the run's failure)."""
    t0 = time.perf_counter()
    from swarmmap.shared.overview import write_overview

    try:
        path = write_overview(cfg.run_dir, cfg.std_max(), notes)
    except Exception:
        log.exception("could not draw %s", cfg.run_dir / "overview.png")
        return
    if path is not None:
        log.info("overview of the maps: %s (drawn in %.1f s)", path, time.perf_counter() - t0)


def others_alive(bus: Bus) -> set[tuple[str, str]]:
    """The run's services still alive, bystanders left out."""
    return {(s, i) for s, i in bus.alive() if s not in BYSTANDERS}


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """Record the run until it is over; returns 0 when every learner finished, else 1."""
    if cfg.run_dir is None:
        fail("config error:\n  run_dir: the recorder needs a run directory (--run-dir or SWARMMAP_RUN_DIR)")
    run_dir, s = cfg.run_dir, cfg.recorder
    run_dir.mkdir(parents=True, exist_ok=True)
    if not (run_dir / "config.yaml").exists():  # `up` and the SLURM script wrote it already
        atomic_write_text(run_dir / "config.yaml", cfg.dump_yaml())
    t0, started = time.monotonic(), time.time()
    metrics = MetricsRecorder(run_dir / "metrics.csv")
    tracker = RunTracker(cfg.robots, s.rejoin_timeout_s)
    phases = PhaseLog(cfg.robots, cfg.rounds())
    keys = Keys(cfg.key_prefix, cfg.run_id)

    def on_metrics(m: Metrics) -> None:
        metrics.add(m)
        tracker.on_metrics(m)
        phases.team.add(m)
        log.info("robot %d round %4d  val_bce %.4f  consensus %.4f%s", m.sender, m.round, m.val_bce,
                 m.consensus_error, "  (final)" if m.final else "")

    def fetch_ground_truth() -> None:
        world = bus.query(keys.world_map(), WorldMap, timeout=cfg.world_wait_s(), stop=stop)
        if world is not None:
            save_ground_truth(run_dir, world)

    with Bus.open(cfg.zenoh, keys, "recorder", 0) as bus:
        bus.subscribe(keys.metrics("*"), Metrics, on_metrics)
        bus.subscribe(keys.scan("*"), Scan, phases.traversal.add)
        for service in ("learner", "lidar", "world"):
            bus.watch_alive(service, lambda ident, alive, service=service: tracker.on_alive(service, ident, alive))
        done = bus.publisher(keys.run_done())
        bus.announce()
        threading.Thread(target=fetch_ground_truth, name="ground-truth", daemon=True).start()
        log.info("recording run %s (%d robots, %d rounds) into %s; waiting for %d learner(s), %d lidar streamer(s) and the world",
                 cfg.run_id, cfg.robots, cfg.rounds(), run_dir, cfg.robots, cfg.robots)
        outcome = None
        while outcome is None and not stop.is_set():
            phases.tick(tracker)
            outcome = tracker.outcome()
            if outcome is None and time.monotonic() - t0 > s.start_timeout_s and (missing := tracker.learners_missing()):
                outcome = False, f"learner(s) {missing} never came alive within {s.start_timeout_s:.0f} s"
            stop.wait(0.2)
        interrupted = outcome is None
        if interrupted:
            outcome = False, f"the recorder was stopped before the run was over (finished: {sorted(tracker.finished)})"
        ok, reason = outcome
        msg = RunDone(run=cfg.run_id, sender=0, ok=ok, reason=reason, finished=sorted(tracker.finished))
        write_summary(run_dir, summary(cfg, metrics, ok, reason, time.monotonic() - t0, started), phases)
        # Say it until every other service has left (a late subscriber still hears it), bounded.
        deadline = time.monotonic() + (0 if interrupted else s.linger_s)
        done.put(msg)
        notes = {r: f"val_bce {m.val_bce:.4f}" for r, m in dict(metrics.final).items()}
        drawing = threading.Thread(target=draw_overview, args=(cfg, notes), name="overview")
        if not interrupted:  # the learners wrote their maps before their final Metrics
            drawing.start()
        while time.monotonic() < deadline and others_alive(bus):
            time.sleep(0.5)
            done.put(msg)
        if drawing.ident is not None:
            drawing.join()
    metrics.close()
    log.info("summary: %s", run_dir / "summary.json")
    return 0 if ok else 1
