"""``swarmmap recorder``: the run directory and the end of the run, whoever launched it.

Run-book: ``swarmmap recorder --config RUN_DIR/config.yaml`` (or with ``SWARMMAP_RUN_DIR`` and
the run's other settings in the environment, as compose does). Start it before the world
drives: the world waits for ``alive/recorder/0`` (``world.wait_for``). ``swarmmap up``, compose
and the SLURM job scripts all start one, so every launcher leaves the same run directory:

- ``config.yaml`` (the resolved config, when the launcher did not write it already),
  ``metrics.csv`` (every learner's ``Metrics`` as it arrives), ``groundtruth.png`` and
  ``groundtruth.npz`` (the world's map and validation set), ``summary.json`` (per learner:
  first and final val_bce, rounds, bytes; the run's outcome and why), and at the end
  ``overview.png`` (:mod:`swarmmap.shared.run.overview`: ground truth beside each robot's saved maps).

It also decides when the run is over, and says so on ``run/done`` (``RunDone``), on which
every other service exits: the run succeeded when every learner sent its final ``Metrics``;
it failed when a learner left before finishing (its liveliness token vanished: it crashed or
was killed), or the world or a lidar streamer left while still needed, and did not come back
within ``recorder.rejoin_timeout_s`` (``swarmmap up`` restarts crashed services), when a
learner never came alive within ``recorder.start_timeout_s``, when, once every learner is
alive, the run made no progress (no new Metrics, no scans) for ``recorder.stall_timeout_s``
(the reason names the learners that hold it up), or when the recorder cannot write the run directory (a full disk, one made
read-only: the reason names the file and the disk). The recorder then waits up to
``recorder.linger_s`` for the other services to leave and exits 0 (success) or 1 (failure),
so ``docker compose up --exit-code-from recorder`` and a SLURM job end with the run's status.
It refuses to start (status 2) on a run directory it cannot write or that holds a finished run.

A resumed run (``swarmmap up --resume``) goes on in the same files: rows of ``metrics.csv``
already there are not written again (a learner that resumes from its checkpoint reports some
rounds twice), ``summary.json`` keeps the first attempt's start and ``first_val_bce`` and adds
up the attempts' wall time.

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

from swarmmap.shared.run.atomic import atomic_write_bytes, atomic_write_text, save_png
from swarmmap.shared.run.config import RunConfig, fail
from swarmmap.shared.run.disk import disk_words, is_full, write_problem
from swarmmap.shared.run.progress import PROGRESS_EVERY_S, TeamProgress, TraversalProgress, duration
from swarmmap.shared.run.rundir import read_summary, run_state
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.protocol import Keys, Metrics, ProtocolError, RunDone, Scan, WorldMap

log = logging.getLogger("recorder")

METRICS_COLUMNS = ["robot", "round", "wall_time_s", "val_bce", "consensus_error", "bytes_sent", "bytes_received",
                   "compute_s", "wait_s", "send_s", "n_points", "final"]
# Services whose tokens say nothing about the run's health (the launcher, tools, Algorithm 1 readiness).
BYSTANDERS = ("up", "status", "exchange", "router", "recorder")
DISK_CHECK_S = 2.0  # how often the recorder looks at the run directory's free space


def cannot_write(path: Path, exc: OSError) -> str:
    """A write that failed, in words: the file, the system's reason and the disk."""
    return f"the recorder cannot write {path}: {exc.strerror or exc} ({disk_words(path.parent)})"


class MetricsRecorder:
    """Appends every Metrics message to metrics.csv and keeps the first and last per robot.

    On a resumed run it goes on after the rows already there (a half-written last row, left by
    a recorder killed while writing it, is dropped), counts them as the first and latest, and
    does not write a (robot, round, final) row that is there already. A failed write raises
    OSError."""

    def __init__(self, path: Path):
        self.path = path
        self._lock = threading.Lock()
        self.first: dict[int, Metrics] = {}
        self.final: dict[int, Metrics] = {}
        self.latest: dict[int, Metrics] = {}
        self._written: set[tuple[int, int, bool]] = set()
        resuming = path.exists() and path.stat().st_size > 0  # a resumed run keeps the rows it had
        if resuming:
            for row in self._earlier_rows():
                self._keep(row)
        self._file = path.open("a" if resuming else "w", newline="")
        self._csv = csv.writer(self._file)
        if not resuming:
            self._csv.writerow(METRICS_COLUMNS)
        self._file.flush()

    def _earlier_rows(self) -> list[Metrics]:
        """The rows already in the file, as Metrics; a last row without its line end is cut off."""
        data = self.path.read_bytes()
        whole = data.rfind(b"\n") + 1
        if whole < len(data):
            log.warning("%s: dropping a half-written last row (%r)", self.path, data[whole:][:80].decode(errors="replace"))
            with self.path.open("r+b") as f:
                f.truncate(whole)
        rows = []
        for row in csv.DictReader(io.StringIO(data[:whole].decode(errors="replace"), newline="")):
            try:
                rows.append(Metrics.model_construct(
                    run="", sender=int(row["robot"]), round=int(row["round"]), wall_time_s=float(row["wall_time_s"]),
                    val_bce=float(row["val_bce"]), consensus_error=float(row["consensus_error"]),
                    bytes_sent=int(row["bytes_sent"]), bytes_received=int(row["bytes_received"]), pid=0, refused=0,
                    final=row["final"] == "1"))
            except (KeyError, TypeError, ValueError):
                continue  # a row of an older layout: kept in the file, not counted
        return rows

    def _keep(self, m: Metrics) -> bool:
        """Count ``m``; False when its row is written already."""
        key = (m.sender, m.round, bool(m.final))
        self.first.setdefault(m.sender, m)
        self.latest[m.sender] = m
        if m.final:
            self.final[m.sender] = m
        if key in self._written:
            return False
        self._written.add(key)
        return True

    def add(self, m: Metrics) -> bool:
        """Write ``m``'s row unless it is there already; whether it was written."""
        with self._lock:
            if not self._keep(m):
                return False
            self._csv.writerow([m.sender, m.round, f"{m.wall_time_s:.3f}", f"{m.val_bce:.6f}",
                                f"{m.consensus_error:.6f}", m.bytes_sent, m.bytes_received, f"{m.compute_s:.3f}",
                                f"{m.wait_s:.3f}", f"{m.send_s:.3f}", m.n_points, int(m.final)])
            self._file.flush()
            return True

    def close(self) -> None:
        """Close the file (a flush that fails is the failure already reported)."""
        with self._lock:
            try:
                self._file.close()
            except OSError:
                pass


class RunTracker:
    """Decides from final Metrics and liveliness whether the run is over, and how it ended.

    Pure bookkeeping (no network), so that the rules can be tested alone."""

    def __init__(self, robots: int, rejoin_timeout: float = 0.0, unreachable_timeout: float = 0.0):
        self.robots = robots
        self.rejoin_timeout, self.unreachable_timeout = rejoin_timeout, unreachable_timeout
        self.hosts_away: set[int] = set()  # robots whose host's router left (a router per host): their services are unreachable
        self.host_back: dict[int, float] = {}  # when each robot's host's router came back: its services have rejoin_timeout from then
        self._lock = threading.Lock()
        self.finished: set[int] = set()
        self.training: set[int] = set()  # learners that reported a round: they hold their data
        self.seen: set[tuple[str, int]] = set()
        self.away: dict[tuple[str, int], tuple[float, str]] = {}  # left while needed: since when, and what it means
        self.failure: str | None = None
        self.t0 = time.monotonic()
        self.absences: list[dict] = []  # every learner that left while training: when, and when it was back

    def _absence(self, key: tuple[str, int], now: float, back: bool) -> None:
        """Note a learner's leaving (or its coming back) for summary.json's ``absences``."""
        if key[0] != "learner":
            return
        if not back:
            self.absences.append({"robot": key[1], "left_at_s": round(now - self.t0, 1), "back_after_s": None})
            return
        for entry in reversed(self.absences):
            if entry["robot"] == key[1] and entry["back_after_s"] is None:
                entry["back_after_s"] = round(now - self.t0 - entry["left_at_s"], 1)
                log.info("learner %d is back after %.1f s away", key[1], entry["back_after_s"])
                break

    def on_metrics(self, m: Metrics) -> None:
        with self._lock:
            if m.sender < self.robots:
                self.training.add(m.sender)
                if m.final:
                    self.finished.add(m.sender)

    def on_alive(self, service: str, ident: str, alive: bool, now: float | None = None) -> None:
        """A liveliness token came (``alive``) or went. A service that leaves while still needed
        fails the run unless it is back within ``rejoin_timeout`` seconds (a launcher restarts it),
        or, when its host's router left too (``router-r<i>``), within ``unreachable_timeout``."""
        now = time.monotonic() if now is None else now
        if service == "router" and ident[:1] == "r" and ident[1:].isdigit():
            robot = int(ident[1:])
            with self._lock:
                if alive and robot in self.hosts_away:  # its router may be back before its services' tokens are
                    self.host_back[robot] = now
                (self.hosts_away.discard if alive else self.hosts_away.add)(robot)
            return
        if not ident.isdigit():
            return
        key = (service, int(ident))
        with self._lock:
            if alive:
                self.seen.add(key)
                if self.away.pop(key, None) is not None:
                    self._absence(key, now, back=True)
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
            self._absence(key, now, back=False)

    def fail(self, why: str) -> None:
        """End the run as failed for ``why`` (the first failure is the one reported)."""
        with self._lock:
            if self.failure is None and not self._all_finished():
                self.failure = why

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
            for (_, robot), (since, why) in sorted(self.away.items(), key=lambda kv: kv[1]):
                if self.failure is not None:
                    break
                unreachable = robot in self.hosts_away
                limit = self.unreachable_timeout if unreachable else self.rejoin_timeout
                if not unreachable:
                    since = max(since, self.host_back.get(robot, since))
                if now - since >= limit:
                    host = f" (its host r{robot} unreachable: its router left too)" if unreachable else ""
                    back = f" and was not back within {limit:.0f} s" if limit else ""
                    self.failure = why + host + back
            if self.failure is not None:
                return False, self.failure
            if self._all_finished():
                return True, f"all {self.robots} learners finished"
            return None


class StallWatch:
    """When the run last made progress and, once it has made none for ``timeout`` seconds, who
    holds it up: the learners that reported nothing, else the unfinished ones whose newest round is
    the lowest. Pure bookkeeping, like RunTracker.

    Progress is the team's, so that no member can fake it: a scan of the traversal, a learner
    that finishes, or a new round reached by a majority of the learners (the round that
    ``robots // 2 + 1`` of them have reached) while none has finished. A member that reports a new
    round now and then while the others wait on it, or goes on alone after the others have
    finished, moves none of these."""

    def __init__(self, robots: int, timeout: float, now: float | None = None):
        self.robots, self.timeout = robots, timeout
        self.last = time.monotonic() if now is None else now
        self.rounds: dict[int, int] = {}  # newest round each learner reported
        self.finished: set[int] = set()
        self.scans = 0
        self._lock = threading.Lock()

    def on_metrics(self, m: Metrics, now: float | None = None) -> None:
        """A learner reported its newest round: progress when it has just finished (a finished
        learner says its final Metrics again until the run is over: no progress) or, while none
        has finished, when a majority of the learners has reached a new round."""
        with self._lock:
            if m.sender >= self.robots:
                return
            before = self._majority_round()
            self.rounds[m.sender] = max(m.round, self.rounds.get(m.sender, -1))
            newly_finished = m.final and m.sender not in self.finished
            if newly_finished or (not self.finished and self._majority_round() > before):
                self.last = time.monotonic() if now is None else now
            if m.final:
                self.finished.add(m.sender)

    def _majority_round(self) -> int:
        """The newest round that a majority of the learners (``robots // 2 + 1``) have reported."""
        reached = sorted((self.rounds.get(r, -1) for r in range(self.robots)), reverse=True)
        return reached[self.robots // 2]

    def on_scan(self, now: float | None = None) -> None:
        """A robot scanned: progress of the traversal."""
        with self._lock:
            self.last = time.monotonic() if now is None else now
            self.scans += 1

    def on_ready(self, now: float | None = None) -> None:
        """Every learner is alive: the run has begun (until then the start timeouts apply)."""
        with self._lock:
            self.last = time.monotonic() if now is None else now

    def held_up_by(self) -> list[int]:
        """The learners that hold the run up: those that reported nothing, else the unfinished
        ones at the lowest round."""
        with self._lock:
            silent = [r for r in range(self.robots) if r not in self.rounds]
            if silent:
                return silent
            behind = {r: k for r, k in self.rounds.items() if r not in self.finished}
            lowest = min(behind.values(), default=None)
            return sorted(r for r, k in behind.items() if k == lowest)

    def stalled(self, now: float | None = None) -> str | None:
        """Why the run is stalled, naming who holds it up; None while it makes progress."""
        now = time.monotonic() if now is None else now
        if now - self.last < self.timeout:
            return None
        who = self.held_up_by()
        with self._lock:
            if not self.rounds:
                held = (f"no scan came from the world and no learner reported (waiting for learner(s) {who})" if not self.scans
                        else f"learner(s) {who} reported no round after the {self.scans} scans of the traversal")
            elif who and who[0] not in self.rounds:
                held = f"learner(s) {who} reported no round; the others are at round {max(self.rounds.values())}"
            else:
                newest = max(self.rounds.values())
                held = f"learner(s) {who} are at round {self.rounds[who[0]]}, the lowest (the team's newest is {newest})"
        return f"the run made no progress (no new Metrics, no scans) for {self.timeout:.0f} s (recorder.stall_timeout_s): {held}"


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
    ref = doc.get("reference")
    ref = f" (held-out scans; the log-odds grid's {ref['val_bce']:.4f})" if ref else ""
    return f"final val_bce: {per_robot}{mean}{ref}; {duration(doc['wall_time_s'])}; {sent / 1e6:.1f} MB sent by the learners"


def save_ground_truth(run_dir: Path, world: WorldMap) -> None:
    """``groundtruth.png`` and ``groundtruth.npz`` (grid, resolution, origin, validation set; on a
    dataset, which has no ground truth, ``reference``: the log-odds grid's probabilities, whose
    trinary map is the grid)."""
    grid = world.grid.numpy()
    save_png(run_dir / "groundtruth.png", np.where(grid == 2, 0.5, grid.astype(float)), world.resolution)  # unknown: grey
    buf = io.BytesIO()
    extra = {"reference": world.reference.numpy()} if world.reference is not None else {}
    np.savez_compressed(buf, grid=world.grid.numpy(), resolution=world.resolution, origin=np.asarray(world.origin),
                        val_points=world.val_points.numpy(), val_labels=world.val_labels.numpy(), **extra)
    atomic_write_bytes(run_dir / "groundtruth.npz", buf.getvalue())


def reference_scores(world: WorldMap) -> dict:
    """The log-odds grid's scores on the held-out validation set of a run on a dataset."""
    from swarmmap.shared.world.logodds import LogOddsGrid, bce

    grid = LogOddsGrid(np.zeros(world.grid.shape, np.float32), world.resolution, tuple(world.origin))
    p = world.reference.numpy()
    index, inside = grid.cell_index(world.val_points.numpy().astype(np.float64))
    at = np.where(inside, p.ravel()[index], 0.5)
    return {"kind": "log-odds grid of the training scans", "val_bce": round(bce(at, world.val_labels.numpy()), 6)}


def summary(cfg: RunConfig, metrics: MetricsRecorder, ok: bool, reason: str, wall: float, started: float | None = None,
            earlier: dict | None = None) -> dict:
    """What ``summary.json`` holds: the run's outcome and, per learner, its first and last
    metrics; with ``earlier`` (the summary of the attempts this one resumes) its start, and the
    wall time of every attempt added up."""
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
            "repeated_samples": last.repeated_samples if last else None,
            "refused_from": {str(j): n for j, n in last.refused_from} if last else {},
        }
    started = time.time() - wall if started is None else started
    refusals: dict[str, int] = {}  # per robot: its messages its neighbours refused
    for entry in learners.values():
        for j, n in entry["refused_from"].items():
            refusals[j] = refusals.get(j, 0) + n
    doc = {"run_id": cfg.run_id, "preset": cfg.preset, "robots": cfg.robots, "rounds": cfg.rounds(),
           "transport": cfg.transport(), "ok": ok, "reason": reason, "wall_time_s": round(wall, 3),
           "started": round(started, 3), "finished": round(time.time(), 3), "learners": learners,
           "refusals": dict(sorted(refusals.items(), key=lambda kv: int(kv[0])))}
    if earlier:
        for robot, entry in learners.items():  # the first attempt's, as it was (metrics.csv rounds it)
            if (first_bce := ((earlier.get("learners") or {}).get(robot) or {}).get("first_val_bce")) is not None:
                entry["first_val_bce"] = first_bce
        before = float(earlier.get("wall_time_s") or 0.0)
        doc.update(wall_time_s=round(before + wall, 3), earlier_wall_time_s=round(before, 3),
                   started=earlier.get("started", doc["started"]), attempts=int(earlier.get("attempts", 1)) + 1)
    return doc


def exploration_section(cfg: RunConfig) -> dict | None:
    """``summary.json``'s ``exploration`` section from the world's ``exploration.csv`` (None, logged, where it cannot be read)."""
    from swarmmap.shared.world.explore import exploration_summary, read_exploration  # (scipy: only for an exploring run)

    path = cfg.run_dir / "exploration.csv"
    try:
        doc = exploration_summary(read_exploration(path), cfg.explore.policy)
        # (ROS 2 robots have no ground truth: their coverage is of the map's extent)
        return {**doc, "coverage_of": "the map's extent" if cfg.ros2.live else "the reachable free space"}
    except (OSError, ValueError) as exc:
        log.error("no exploration section in summary.json: %s", exc)
        return None


def write_summary(run_dir: Path, doc: dict, phases: PhaseLog) -> None:
    """Log how the run ended (the verdict, the team's last progress line, the closing line) and
    write ``summary.json``."""
    stopped = doc["reason"].startswith("interrupted")
    (log.info if doc["ok"] else log.warning if stopped else log.error)(
        "run %s: %s", "succeeded" if doc["ok"] else "stopped" if stopped else "FAILED", doc["reason"])
    if phases.team.started:
        log.info("%s", phases.team.line())
    log.info("%s", closing_line(doc))
    try:
        atomic_write_text(run_dir / "summary.json", json.dumps(doc, indent=2) + "\n")
    except OSError as exc:  # the verdict still goes out on run/done
        log.error("%s", cannot_write(run_dir / "summary.json", exc))


def draw_overview(cfg: RunConfig, notes: dict[int, str]) -> None:
    """``overview.png`` of the maps the learners saved, ``notes`` under each robot's name (a
    figure that fails is logged, never the run's failure)."""
    t0 = time.perf_counter()
    from swarmmap.shared.run.overview import write_overview

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


def refuse_run_dir(run_dir: Path) -> None:
    """Stop (status 2) on a run directory that cannot be written or that holds a finished run."""
    if (why := write_problem(run_dir)) is not None:
        fail(f"config error:\n  run_dir: {why}; choose a run directory on a disk this user may write")
    if run_state(run_dir) == "finished":
        fail(f"config error:\n  run_dir: {run_dir} holds a finished run, which is never overwritten; choose another")


class Recorder:
    """One run's recording: what arrives goes into the run directory, and the rules of the end
    (RunTracker, StallWatch, the disk) decide when the run is over."""

    def __init__(self, cfg: RunConfig):
        self.cfg, self.run_dir, self.s = cfg, cfg.run_dir, cfg.recorder
        self.t0, self.started = time.monotonic(), time.time()
        self.earlier = read_summary(self.run_dir)  # the attempts this one resumes, if any
        self.tracker = RunTracker(cfg.robots, self.s.rejoin_timeout_s, self.s.unreachable_timeout_s)
        self.stall = StallWatch(cfg.robots, self.s.stall_timeout_s)
        self.phases = PhaseLog(cfg.robots, cfg.rounds())
        self.metrics = MetricsRecorder(self.run_dir / "metrics.csv")
        self._disk_checked = -float("inf")
        self._ready = False  # every learner came alive
        self.world: WorldMap | None = None

    def on_metrics(self, m: Metrics) -> None:
        """A learner's Metrics: into metrics.csv (a failed write fails the run), the rules and the log."""
        new = True
        try:
            new = self.metrics.add(m)
        except OSError as exc:
            self.tracker.fail(cannot_write(self.metrics.path, exc))
        self.tracker.on_metrics(m)
        self.stall.on_metrics(m)
        self.phases.team.add(m)
        if new:  # (a finished learner says its final Metrics again until the run is over)
                log.info("robot %d round %4d  val_bce %.4f  consensus %.4f%s", m.sender, m.round, m.val_bce,
                     m.consensus_error, "  (final)" if m.final else "")

    def check_metrics(self, m: Metrics) -> None:
        """Refuse (ProtocolError, counted by the bus) Metrics that no learner of this run sends: of
        a robot the run does not have, of a round beyond ``learner.rounds``, final before the last
        round, or of an earlier round than its process reported already (a restarted learner, a
        new pid, reports some rounds again). With them a learner writes at most two rows a round."""
        rounds = self.cfg.rounds()
        if m.sender >= self.cfg.robots:
            raise ProtocolError("unknown-sender", f"Metrics of robot {m.sender}; the run has {self.cfg.robots}")
        if m.round > rounds or (m.final and m.round != rounds):
            raise ProtocolError("beyond-rounds", f"{'final ' if m.final else ''}Metrics of round {m.round} from learner "
                                                 f"{m.sender}; the run has {rounds} rounds")
        last = self.metrics.latest.get(m.sender)
        if last is not None and last.pid == m.pid and m.round < last.round:
            raise ProtocolError("out-of-order", f"Metrics of round {m.round} from learner {m.sender} after its round "
                                                f"{last.round}")

    def on_scan(self, scan: Scan) -> None:
        """A robot's scan: progress, and the traversal's line."""
        self.stall.on_scan()
        self.phases.traversal.add(scan)

    def fetch_ground_truth(self, bus: Bus, stop: threading.Event) -> None:
        """Ask the world for its map and write the ground truth (a failed write fails the run)."""
        world = bus.world(self.cfg.world_wait_s(), stop)
        if world is not None:
            self.world = world
            try:
                save_ground_truth(self.run_dir, world)
            except OSError as exc:
                self.tracker.fail(cannot_write(self.run_dir / "groundtruth.npz", exc))

    def outcome(self) -> tuple[bool, str] | None:
        """(ok, reason) once the run is over, else None."""
        now = time.monotonic()
        if now - self._disk_checked >= DISK_CHECK_S:
            self._disk_checked = now
            if is_full(self.run_dir):
                self.tracker.fail(f"the disk of the run directory is full ({disk_words(self.run_dir)})")
        if (verdict := self.tracker.outcome(now)) is not None:
            return verdict
        missing = self.tracker.learners_missing()
        if missing and now - self.t0 > self.s.start_timeout_s:
            return False, f"learner(s) {missing} never came alive within {self.s.start_timeout_s:.0f} s"
        if not missing and not self._ready:
            self._ready = True
            self.stall.on_ready(now)
        if (why := self.stall.stalled(now)) is not None:
            self.tracker.fail(why)
            return self.tracker.outcome(now)
        return None

    def summary(self, ok: bool, reason: str) -> dict:
        """summary.json's content for this outcome (with who held a stalled run up)."""
        doc = summary(self.cfg, self.metrics, ok, reason, time.monotonic() - self.t0, self.started, self.earlier)
        if self.world is not None and self.world.reference is not None:
            doc["reference"] = reference_scores(self.world)
        if not ok and reason.startswith("the run made no progress"):
            doc["held_up_by"] = self.stall.held_up_by()
        if self.tracker.absences:  # learners that left while training (a lost host, a cut link) and came back, or not
            doc["absences"] = self.tracker.absences
        if self.cfg.explore.active and (section := exploration_section(self.cfg)) is not None:
            doc["exploration"] = section
        return doc


def run(cfg: RunConfig, stop: threading.Event) -> int:
    """Record the run until it is over; returns 0 when every learner finished, else 1."""
    if cfg.run_dir is None:
        fail("config error:\n  run_dir: the recorder needs a run directory (--run-dir or SWARMMAP_RUN_DIR)")
    run_dir = cfg.run_dir
    refuse_run_dir(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    if not (run_dir / "config.yaml").exists():  # `up` and the SLURM script wrote it already
        atomic_write_text(run_dir / "config.yaml", cfg.dump_yaml())
    rec = Recorder(cfg)
    keys = Keys(cfg.key_prefix, cfg.run_id)
    with Bus.open(cfg.zenoh, keys, "recorder", 0) as bus:
        bus.subscribe(keys.metrics("*"), Metrics, rec.on_metrics, check=rec.check_metrics)
        bus.subscribe(keys.scan("*"), Scan, rec.on_scan)
        for service in ("learner", "lidar", "world", "router"):  # a robot host's router: is its host reachable?
            bus.watch_alive(service, lambda ident, alive, service=service: rec.tracker.on_alive(service, ident, alive))
        done = bus.publisher(keys.run_done())
        bus.announce()
        threading.Thread(target=rec.fetch_ground_truth, args=(bus, stop), name="ground-truth", daemon=True).start()
        log.info("recording run %s (%d robots, %d rounds) into %s; waiting for %d learner(s), %d lidar streamer(s) and the world",
                 cfg.run_id, cfg.robots, cfg.rounds(), run_dir, cfg.robots, cfg.robots)
        outcome = None
        while outcome is None and not stop.is_set():
            rec.phases.tick(rec.tracker)
            outcome = rec.outcome()
            stop.wait(0.2)
        ok = end_run(cfg, rec, bus, done, outcome)
    rec.metrics.close()
    log.info("summary: %s", run_dir / "summary.json")
    return 0 if ok else 1


def end_run(cfg: RunConfig, rec: Recorder, bus: Bus, done, outcome: tuple[bool, str] | None) -> bool:
    """Write the summary, say the verdict on ``run/done`` until every other service has left
    (bounded by ``recorder.linger_s``), draw the overview; whether the run succeeded."""
    interrupted = outcome is None
    if interrupted:
        outcome = False, f"interrupted: the recorder was stopped before the run was over (finished: {sorted(rec.tracker.finished)})"
    ok, reason = outcome
    msg = RunDone(run=cfg.run_id, sender=0, ok=ok, reason=reason, finished=sorted(rec.tracker.finished))
    write_summary(cfg.run_dir, rec.summary(ok, reason), rec.phases)  # a disk that cannot take it is logged
    done.put(msg)
    # Say it until every other service has left (a late subscriber still hears it), bounded.
    deadline = time.monotonic() + (0 if interrupted else cfg.recorder.linger_s)
    notes = {r: f"val_bce {m.val_bce:.4f}" for r, m in dict(rec.metrics.final).items()}
    drawing = threading.Thread(target=draw_overview, args=(cfg, notes), name="overview")
    if not interrupted:  # the learners wrote their maps before their final Metrics
        drawing.start()
    while time.monotonic() < deadline and others_alive(bus):
        time.sleep(0.5)
        done.put(msg)
    if drawing.ident is not None:
        drawing.join()
    return ok
