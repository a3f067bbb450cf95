"""``swarmmap up``'s console: its phases, one progress line and the closing block.

On a terminal the progress line updates in place (a log line first clears it); elsewhere (a
pipe, a file, a CI log) a plain progress line is logged every ``PROGRESS_EVERY_S`` seconds.
Once the run is over, :func:`closing_block` says how it ended, the final val_bce of every robot
and the team's mean, the wall time and bytes sent, where everything went, and the next
commands to copy.
"""

from __future__ import annotations

import logging
import shlex
import sys
import threading
import time
from pathlib import Path
from typing import TextIO

from swarmmap.shared.run.config import std_models
from swarmmap.shared.run.progress import PROGRESS_EVERY_S, duration
from swarmmap.shared.run.rundir import config_doc, read_summary

log = logging.getLogger("up")

CLEAR = "\r\x1b[K"  # carriage return, erase to the end of the line
TTY_EVERY_S = 0.5


class Console:
    """Draws the progress line: in place on a terminal, as a periodic log line otherwise."""

    def __init__(self, stream: TextIO | None = None, tty: bool | None = None, every_s: float = PROGRESS_EVERY_S):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty() if tty is None else tty
        self.every_s = every_s
        self._lock = threading.Lock()
        self._shown = False
        self._last_text: str | None = None
        self._last_at = -float("inf")
        if self.tty:  # a log line first clears the progress line, which the next update draws again
            for handler in logging.getLogger().handlers:
                handler.addFilter(self._clear_for_log)

    def _clear_for_log(self, record: logging.LogRecord) -> bool:
        self.clear()
        return True

    def clear(self) -> None:
        """Erase the progress line (before other output)."""
        with self._lock:
            if self._shown:
                self.stream.write(CLEAR)
                self.stream.flush()
                self._shown = False

    def progress(self, text: str | None, now: float | None = None, force: bool = False) -> None:
        """Show ``text`` as the progress line (None: nothing to show yet)."""
        if text is None:
            return
        now = time.monotonic() if now is None else now
        with self._lock:
            due = force or now - self._last_at >= (TTY_EVERY_S if self.tty else self.every_s)
            if not due or (text == self._last_text and not self.tty):
                return
            self._last_text, self._last_at = text, now
            if self.tty:
                self.stream.write(CLEAR + text)
                self.stream.flush()
                self._shown = True
                return
        log.info("%s", text)

    def close(self) -> None:
        """Leave the terminal on a fresh line, and stop clearing for log lines."""
        self.clear()
        for handler in logging.getLogger().handlers:
            handler.removeFilter(self._clear_for_log)


def closing_block(run_dir: Path, max_robots: int = 16) -> str:
    """What the run left, from its summary: outcome, per-robot and team val_bce, wall time, MB
    sent, where everything went and what to run next."""
    summary = read_summary(run_dir) or {}
    learners = summary.get("learners") or {}
    finals = {int(r): v.get("final_val_bce") for r, v in learners.items() if v.get("final_val_bce") is not None}
    outcome = "ok" if summary.get("ok") else "INTERRUPTED" if summary.get("status") == 130 else "FAILED"
    wall = summary.get("wall_time_s")
    lines = ["", f"run {summary.get('run_id', run_dir.name)}: {outcome} ({summary.get('reason', 'no summary was written')})"
                 + (f" in {duration(wall)}" if wall else "")]
    if finals:
        shown = sorted(finals.items())[:max_robots]
        lines.append("  final val_bce  " + "  ".join(f"robot {r} {v:.4f}" for r, v in shown)
                     + ("  ..." if len(finals) > max_robots else ""))
        lines.append(f"  team mean      {sum(finals.values()) / len(finals):.4f} over {len(finals)} robot(s)")
        if (ref := summary.get("reference")) is not None:  # a run on a dataset: val_bce on its held-out scans
            lines.append(f"  reference      {ref['val_bce']:.4f}, the {ref['kind']} (val_bce on the same held-out scans)")
    if (ex := summary.get("exploration")) is not None:
        lines += exploration_lines(ex, max_robots)
    sent = sum(v.get("bytes_sent") or 0 for v in learners.values())
    if sent:
        lines.append(f"  sent           {sent / 1e6:.1f} MB by the learners")
    lines.append(f"  run directory  {run_dir}")
    outputs = [name for name in ("overview.png", "maps/", "recording.rrd", "models/", "metrics.csv", "exploration.csv", "goals.csv",
                                 "summary.json", "logs/")
               if (run_dir / name.rstrip("/")).exists()]
    if outputs:
        lines.append(f"  in it          {', '.join(outputs)}")
    lines += ["next:"] + next_commands(run_dir, summary)
    return "\n".join(lines)


def exploration_lines(ex: dict, max_robots: int) -> list[str]:
    """The closing block's lines of an exploring team: coverage, distances, the distance to each coverage level."""
    driven = sorted(((int(r), d) for r, d in (ex.get("robot_distance_m") or {}).items()))[:max_robots]
    at = ", ".join(f"{float(level):.0%} at {d:.1f} m" if d is not None else f"{float(level):.0%} never"
                   for level, d in (ex.get("team_distance_at_coverage") or {}).items())
    return [f"  explored       {ex.get('policy')}: {ex.get('final_coverage', 0.0):.1%} of "
            f"{ex.get('coverage_of', 'the reachable free space')}, "
            f"team distance {ex.get('team_distance_m', 0.0):.1f} m (coverage {at})",
            "  driven         " + "  ".join(f"robot {r} {d:.1f} m" for r, d in driven)]


def next_commands(run_dir: Path, summary: dict) -> list[str]:
    """The commands to copy after a run: view, score, compare (or, after a failure, its logs)."""
    where = shlex.quote(str(run_dir))
    cmds = []
    if summary.get("status") == 130:
        cmds.append((f"swarmmap up --run-dir {where} --resume", "go on from the learners' last checkpoints"))
    if not summary.get("ok"):
        cmds.append((f"swarmmap logs {where}", "the services' logs (swarmmap logs RUN SERVICE prints one)"))
    if (run_dir / "recording.rrd").exists():
        cmds.append((f"rerun {shlex.quote(str(run_dir / 'recording.rrd'))}", "the maps, robots and curves in Rerun"))
    if (run_dir / "models").is_dir():
        if (config_doc(run_dir).get("learner") or {}).get("model") in std_models():
            cmds.append((f"swarmmap experiment score {where}", "uncertainty scores of its std maps"))
        else:  # a FourierNet has no std of its own: the team's models as an ensemble have one
            cmds.append((f"swarmmap experiment score {where} --ensemble", "uncertainty scores of the robots' models "
                                                                          "as one ensemble"))
    if (run_dir / "metrics.csv").exists():
        cmds.append((f"swarmmap compare {where} OTHER_RUN_DIR", "its val_bce curves beside another run's"))
    width = max((len(c) for c, _ in cmds), default=0)
    return [f"  {c:<{width}}  # {why}" for c, why in cmds]
