"""Reading a run directory (what ``swarmmap up``, compose and SLURM leave): its metrics, its
summary and the team's curve. The experiments, the run tools (``status``, ``runs``,
``compare``) and ``bench/time_to_quality.py`` read runs through these functions only.

    rows = read_metrics(run_dir)          # {robot: [(round, val_bce), ...]}
    curve = team_curve(run_dir)           # rounds, seconds since the run started, mean val_bce
    info = run_info(run_dir)              # status, robots, rounds, final mean val_bce, start time
    state = run_state(run_dir)            # new, finished or interrupted (what a new run may do there)
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import json
import os
import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path


def read_metrics(run_dir: Path, column: str = "val_bce") -> dict[int, list[tuple[int, float]]]:
    """Per robot, (round, ``column``) in round order from ``metrics.csv`` (a row still being
    written, without its line end, is left out)."""
    out: dict[int, dict[int, float]] = {}
    for row in metric_rows(run_dir):
        out.setdefault(int(row["robot"]), {})[int(row["round"])] = float(row[column])
    return {r: sorted(v.items()) for r, v in sorted(out.items())}


def metric_rows(run_dir: Path) -> list[dict[str, str]]:
    """The complete rows of ``metrics.csv`` as dicts; [] when there is none yet."""
    try:
        text = (run_dir / "metrics.csv").read_text()
    except OSError:
        return []
    lines = text.splitlines(keepends=True)
    return list(csv.DictReader([line for line in lines if line.endswith("\n")]))


def final_val_bce(run_dir: Path) -> dict[int, float]:
    """Each robot's last reported val_bce."""
    return {r: rows[-1][1] for r, rows in read_metrics(run_dir).items()}


def read_summary(run_dir: Path) -> dict | None:
    """``summary.json`` (the recorder's, completed by ``up``), or None when there is none or it
    cannot be read."""
    try:
        doc = json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


@dataclass
class TeamCurve:
    """The team's mean val_bce at every round all its learners reported, and when."""

    rounds: list[int]
    seconds: list[float]  # since the run started (start-up and traversal included: an upper bound)
    mean: list[float]
    startup_s: float  # start-up and traversal before the learners' clocks started


def team_curve(run_dir: Path) -> TeamCurve:
    """Mean val_bce over the robots at every evaluated round (a round counts once every robot
    that reports from round 0 has reported it), placed at the latest robot's ``wall_time_s``
    plus the run's start-up and traversal (``summary.json``'s wall time less the learners' last:
    an upper bound, as it also holds the shut-down)."""
    rows = metric_rows(run_dir)
    if not rows:
        raise FileNotFoundError(f"{run_dir / 'metrics.csv'}: no metrics (the run did not get to train?)")
    by_round: dict[int, list[dict]] = defaultdict(list)
    for r in rows:
        by_round[int(r["round"])].append(r)
    # The learners that report from the first round (a centralized run has one; its copies report only at the end).
    learners = {r["robot"] for r in by_round[min(by_round)]}
    summary = read_summary(run_dir) or {}
    last = max(float(r["wall_time_s"]) for r in rows)
    startup = max(0.0, float(summary.get("wall_time_s", last)) - last)
    curve = TeamCurve([], [], [], startup)
    for k in sorted(by_round):
        mine = {r["robot"]: r for r in by_round[k] if r["robot"] in learners}
        if len(mine) != len(learners):
            continue
        curve.rounds.append(k)
        curve.seconds.append(startup + max(float(r["wall_time_s"]) for r in mine.values()))
        curve.mean.append(sum(float(r["val_bce"]) for r in mine.values()) / len(learners))
    return curve


@dataclass
class RunInfo:
    """One run directory at a glance (``swarmmap runs``)."""

    path: Path
    status: str  # ok, failed, interrupted, no summary (running, or stopped without one)
    robots: int | None
    rounds: int | None
    final_mean_val_bce: float | None
    started: float | None  # epoch seconds
    reason: str = ""


def run_started(run_dir: Path, summary: dict | None) -> float | None:
    """When the run started (epoch seconds): the summary's ``started`` or, for a run that has
    none, its config.yaml's modification time."""
    if summary and isinstance(summary.get("started"), (int, float)):
        return float(summary["started"])
    try:
        return (run_dir / "config.yaml").stat().st_mtime
    except OSError:
        return None


def summary_outcome(summary: dict | None) -> str:
    """ok, failed or interrupted from a summary (``up`` adds its exit status); no summary: None."""
    if summary is None:
        return "no summary"
    if summary.get("ok"):
        return "ok"
    return "interrupted" if summary.get("status") == 130 else "failed"


def run_info(run_dir: Path) -> RunInfo:
    """Status, robots, rounds, final mean val_bce and start time of ``run_dir``."""
    summary = read_summary(run_dir)
    finals = final_val_bce(run_dir)
    mean = sum(finals.values()) / len(finals) if finals else None
    robots = summary.get("robots") if summary else None
    rounds = summary.get("rounds") if summary else None
    if summary is None:
        robots, rounds = config_numbers(run_dir)
    return RunInfo(run_dir, summary_outcome(summary), robots, rounds, mean, run_started(run_dir, summary),
                   (summary or {}).get("reason", ""))


def config_doc(run_dir: Path) -> dict:
    """A run's config.yaml as a plain dict, without validating it (an older run's is read too); {} when unreadable."""
    import yaml

    try:
        doc = yaml.safe_load((run_dir / "config.yaml").read_text())
    except (OSError, yaml.YAMLError):
        return {}
    return doc if isinstance(doc, dict) else {}


def run_words(run_dir: Path) -> str:
    """What tells a run apart, from its config.yaml: its label, preset, model, plan or dataset and
    robots ("first try, smoke, fourier, procedural 2x2, 3 robots"); "" when unreadable."""
    doc = config_doc(run_dir)
    if not doc:
        return ""
    world, learner = doc.get("world") or {}, doc.get("learner") or {}
    if world.get("dataset"):
        names = [Path(str(p)).name for p in world["dataset"]] if isinstance(world["dataset"], list) else [str(world["dataset"])]
        plan = f"dataset {', '.join(names[:2])}{' ...' if len(names) > 2 else ''}"
    elif world.get("floorplan") not in (None, "procedural"):
        plan = f"plan {Path(str(world['floorplan'])).name}"
    else:
        plan = f"procedural {world.get('rooms_x', '?')}x{world.get('rooms_y', '?')}"
    words = [doc.get("label") or "", doc.get("preset") or "", str(learner.get("model") or ""), plan,
             f"{doc.get('robots', '?')} robots"]
    return ", ".join(w for w in words if w)


def config_numbers(run_dir: Path) -> tuple[int | None, int | None]:
    """(robots, rounds) from a run's config.yaml."""
    doc = config_doc(run_dir)
    try:
        return int(doc["robots"]), int(doc["learner"]["rounds"])
    except (ValueError, TypeError, KeyError):
        return None, None


def is_run_dir(path: Path) -> bool:
    """Whether ``path`` holds a run (its config.yaml)."""
    return (path / "config.yaml").is_file()


# What a run leaves in its directory as soon as it starts (any one of them: the run was there).
RUN_FILES = ("config.yaml", "metrics.csv", "summary.json", "checkpoints")


def run_state(run_dir: Path) -> str:
    """``new`` (no run was there), ``finished`` (its summary says every learner finished) or
    ``interrupted`` (a run began there and did not finish: it failed, was stopped, or is still going)."""
    if not any((run_dir / name).exists() for name in RUN_FILES):
        return "new"
    summary = read_summary(run_dir)
    return "finished" if summary is not None and summary.get("ok") is True else "interrupted"


def unused_path(path: Path) -> Path:
    """``path`` when nothing is there, else the first free ``<stem>-<n><suffix>`` beside it (a
    resumed run's second recording is ``recording-2.rrd``: the first attempt's is kept)."""
    n, free = 1, path
    while free.exists() and free.stat().st_size > 0:
        n += 1
        free = path.with_name(f"{path.stem}-{n}{path.suffix}")
    return free


def local_time(epoch: float | None) -> str:
    """``2025-01-31 14:05:09`` in local time; "" for None."""
    return "" if epoch is None else time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(epoch))


LOCK_FILE = ".swarmmap.lock"


class RunDirBusy(RuntimeError):
    """Another swarmmap process holds the run directory (its ``up`` or ``prepare``)."""


@contextlib.contextmanager
def hold_run_dir(run_dir: Path, what: str) -> Iterator[None]:
    """Hold ``run_dir`` for this process (``what``: ``swarmmap up``, ``swarmmap prepare``) while the
    block runs: an exclusive lock on its LOCK_FILE, taken at once or refused with
    :class:`RunDirBusy` naming the holder. Two launchers never prepare or run one directory at
    once. A directory this made and the block leaves empty (its checks refused the run) is removed;
    one that cannot be written is not held (the launcher's checks refuse it, saying why)."""
    made = [p for p in (run_dir, *run_dir.parents) if not p.exists()]  # the folders the hold makes, innermost first
    path = run_dir / LOCK_FILE
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    except OSError:  # a directory that cannot be written: the launcher's own checks refuse it, naming why
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
            raise RunDirBusy(f"{run_dir} is held by {holder}: one launcher at a time prepares or runs a run directory; "
                             "wait for it to end, or choose another --run-dir") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{what} (pid {os.getpid()})\n".encode(), 0)
        try:
            yield
        finally:
            os.ftruncate(fd, 0)  # the holder is gone: a refused launcher leaves the directory as it found it
            if made and [p.name for p in run_dir.iterdir()] == [LOCK_FILE]:
                path.unlink(missing_ok=True)
                with contextlib.suppress(OSError):
                    for folder in made:  # (one something else wrote into stays)
                        folder.rmdir()
    finally:
        os.close(fd)
