"""``swarmmap status``: whether a run is going, and what its services and learners are doing.

Run-book: ``swarmmap status RUN_DIR`` (or ``--config RUN_DIR/config.yaml``, or ``--run-id ID``
with the Zenoh options that reach the run). A finished run is answered from its
``summary.json`` at once ("not running; finished ok at ..."), a missing one too. Otherwise the
run is asked over Zenoh: its live services (liveliness tokens under ``alive/``) and, from the
Metrics stream (and, when the run directory is at hand, its ``metrics.csv``), each learner's
round and val_bce, with the message rates of ``--window`` seconds. Ctrl-C or SIGTERM ends it
at once (the Zenoh session works in a thread of its own).
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import threading
import time
from pathlib import Path

import zenoh

from swarmmap.shared.run.config import ConfigError, RunConfig
from swarmmap.shared.run.flags import config_from_args
from swarmmap.shared.run.progress import TeamProgress, eta_words
from swarmmap.shared.run.rundir import final_val_bce, local_time, read_metrics, read_summary, run_words, summary_outcome
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.codec import decode
from swarmmap.shared.wire.protocol import Keys, Metrics

MiB = 1024**2

# Not services of the run: the launcher, this tool and the learners' exchange readiness tokens.
NOT_SERVICES = ("status", "exchange", "up")
PROBE_CONNECT_S = 5.0  # how long to wait for the run's router before saying nothing answers


def publisher_of(keys: Keys, key: str) -> tuple[str, str, str] | None:
    """(service, id, topic) of the service that publishes ``key``."""
    tail = key[len(keys.root) + 1 :].split("/")
    if len(tail) == 3 and tail[0] == "robots":
        return ("world", "0", "scan") if tail[2] == "scan" else ("lidar", tail[1], tail[2])
    if len(tail) == 3 and tail[0] == "learners":
        return "learner", tail[1], tail[2]
    return None


class Snapshot:
    """What a live run showed during the window: its services, their traffic, the learners' Metrics."""

    def __init__(self) -> None:
        self.alive: list[tuple[str, str]] = []
        self.counts: dict[tuple[str, str], dict[str, list[float]]] = collections.defaultdict(
            lambda: collections.defaultdict(lambda: [0, 0]))
        self.metrics: dict[int, Metrics] = {}
        self.lock = threading.Lock()

    def on_sample(self, keys: Keys, sample: zenoh.Sample) -> None:
        """Count one sample by its publisher; keep a learner's newest Metrics."""
        key = str(sample.key_expr)
        who = publisher_of(keys, key)
        if who is None:
            return
        payload = sample.payload.to_bytes()
        with self.lock:
            c = self.counts[who[:2]][who[2]]
            c[0] += 1
            c[1] += len(payload)
        if who[2] == "metrics":
            try:
                m = decode(payload, Metrics, run=keys.run, sender=int(who[1]))
            except Exception:  # a refused payload is not shown  # noqa: BLE001
                return
            with self.lock:
                if m.sender not in self.metrics or m.round >= self.metrics[m.sender].round:
                    self.metrics[m.sender] = m


def collect(cfg: RunConfig, window: float, stop: threading.Event) -> Snapshot:
    """Live services and, per service, per topic [messages, bytes] seen in ``window`` s."""
    keys = Keys(cfg.key_prefix, cfg.run_id)
    snap = Snapshot()
    zenoh_settings = cfg.zenoh.model_copy(update={"connect_timeout_s": min(cfg.zenoh.connect_timeout_s, PROBE_CONNECT_S)})
    with Bus.open(zenoh_settings, keys, "status", 0) as bus:
        sub = bus.session.declare_subscriber(keys.everything(), lambda s: snap.on_sample(keys, s))
        stop.wait(window)
        sub.undeclare()
        snap.alive = sorted(((s, i) for s, i in bus.alive() if s not in NOT_SERVICES),
                            key=lambda p: (p[0], int(p[1]) if p[1].isdigit() else 0))
    return snap


def learner_rows(snap: Snapshot, run_dir: Path | None) -> dict[int, tuple[int, float, bool, str]]:
    """Per learner (round, val_bce, final, where from): the Metrics heard now, else the run's
    metrics.csv (the same stream, recorded)."""
    rows: dict[int, tuple[int, float, bool, str]] = {}
    if run_dir is not None:
        for robot, series in read_metrics(run_dir).items():
            rows[robot] = (series[-1][0], series[-1][1], False, "metrics.csv")
    for robot, m in snap.metrics.items():
        if robot not in rows or m.round >= rows[robot][0]:
            rows[robot] = (m.round, m.val_bce, m.final, "live")
    return rows


def live_report(cfg: RunConfig, snap: Snapshot, window: float, run_dir: Path | None) -> str:
    """The status table of a live run: every service listed (the count is of what is listed),
    then each learner's round and val_bce."""
    what = run_words(run_dir) if run_dir is not None else ""
    lines = [f"run {cfg.run_id}{f' ({what})' if what else ''}: running; {len(snap.alive)} service(s) alive (message rates "
             f"over {window:.1f} s)"]
    for service, ident in snap.alive:
        rates = ", ".join(f"{topic} {n / window:.1f} msg/s {b / window / 1024:.1f} KiB/s"
                          for topic, (n, b) in sorted(snap.counts.get((service, ident), {}).items()))
        lines.append(f"  {service:<8} {ident:>3}  {rates or 'idle'}")
    rows = learner_rows(snap, run_dir)
    if rows:
        team = TeamProgress(cfg.robots, cfg.rounds())  # the team's pace is its slowest learner's, as up's line says
        for m in snap.metrics.values():
            team.add(m)
        eta = team.eta_s() if team.finished() < len(snap.metrics) else None
        lines.append(f"learners ({len(rows)} of {cfg.robots} reported, of {cfg.rounds()} rounds"
                     f"{'' if eta is None else '; ' + eta_words(eta)}):")
        for robot, (rnd, val, final, source) in sorted(rows.items()):
            lines.append(f"  learner {robot:>3}  round {rnd:>5}  val_bce {val:.4f}{'  (final)' if final else ''}"
                         f"{'' if source == 'live' else '  (from metrics.csv)'}")
    else:
        lines.append(f"learners: none has reported a round yet (of {cfg.robots})")
    return "\n".join(lines + budget_lines(run_dir))


def budget_lines(run_dir: Path | None, summary: dict | None = None) -> list[str]:
    """Each robot's memory and CPU against its budget (``up --budget``): live from ``budget.json``,
    which ``up`` rewrites every few seconds, or a finished run's from its summary."""
    if summary is not None:
        doc = summary.get("budget")
    else:
        try:
            doc = json.loads((run_dir / "budget.json").read_text()) if run_dir is not None else None
        except (OSError, ValueError):
            doc = None
    if not doc or not doc.get("robots"):
        return []
    lines = ["budgets (memory of the robot's services, its control group's; CPU since the start):"]
    for robot, u in sorted(doc["robots"].items(), key=lambda kv: int(kv[0])):
        limit = u.get("memory_limit_bytes") or u.get("memory_bytes") or 0
        now = f"now {u['memory_bytes_now'] / MiB:.0f} MiB, " if "memory_bytes_now" in u and summary is None else ""
        wall = doc.get("wall_s") or 0
        cpus = u.get("cpus_used", u["cpu_s"] / wall if wall else 0.0)
        lines.append(f"  robot {robot:>3}  {now}peak {u['peak_memory_bytes'] / MiB:.0f} of {limit / MiB:.0f} MiB, "
                     f"CPU {cpus:.2f} of {u.get('cpus', 0):g}"
                     + (f", {u['oom_kills']} killed at the limit" if u.get("oom_kills") else "")
                     + (f", at the limit {u['limit_hits']} time(s)" if u.get("limit_hits") else ""))
    return lines


def finished_report(run_dir: Path, summary: dict) -> str:
    """A finished run, from its summary: how and when it ended, and each learner's final val_bce."""
    ended = summary.get("finished") or (run_dir / "summary.json").stat().st_mtime
    status = summary_outcome(summary)
    what = run_words(run_dir)
    lines = [f"run {summary.get('run_id', run_dir.name)}{f' ({what})' if what else ''}: not running; finished {status} at "
             f"{local_time(ended)} ({summary.get('reason', '')})"]
    finals = final_val_bce(run_dir)
    for robot, v in sorted((summary.get("learners") or {}).items(), key=lambda kv: int(kv[0])):
        val = v.get("final_val_bce", finals.get(int(robot)))
        lines.append(f"  learner {robot:>3}  rounds {v.get('rounds', 0):>5}  final val_bce "
                     f"{'n/a' if val is None else f'{val:.4f}'}{'' if v.get('finished') else '  (did not finish)'}")
    return "\n".join(lines + budget_lines(run_dir, summary))


def newer_than_summary(run_dir: Path) -> bool:
    """Whether the run directory changed after its summary: a run started again in it (``up``
    rewrites config.yaml, the recorder appends to metrics.csv)."""
    try:
        written = (run_dir / "summary.json").stat().st_mtime
    except OSError:
        return True
    return any((run_dir / name).exists() and (run_dir / name).stat().st_mtime > written + 1.0
               for name in ("config.yaml", "metrics.csv"))


def run_status(args: argparse.Namespace, stop: threading.Event) -> int:
    """``swarmmap status``: 0 when it could say, 1 when the run directory holds no run, 2 for
    a refused config, 130 when interrupted."""
    run_dir: Path | None = args.run_dir or (args.config.parent if args.config else None)
    if args.run_dir is not None:
        if not (args.run_dir / "config.yaml").is_file():
            print(f"not running: {args.run_dir} holds no run (no config.yaml)")
            return 1
        args.config = args.config or args.run_dir / "config.yaml"
    summary = read_summary(run_dir) if run_dir is not None else None
    if summary is not None and not newer_than_summary(run_dir):
        print(finished_report(run_dir, summary))
        return 0
    try:
        cfg = config_from_args(args)
    except ConfigError as exc:
        print(exc.message)
        return 2
    return probe(cfg, args.window, run_dir, stop)


def probe(cfg: RunConfig, window: float, run_dir: Path | None, stop: threading.Event) -> int:
    """Ask the run over Zenoh, in a thread, so that Ctrl-C and SIGTERM end the command at once."""
    result: dict[str, object] = {}
    print(f"run {cfg.run_id}: no summary yet; asking its services over Zenoh ({window:g} s)...", file=sys.stderr, flush=True)

    def work() -> None:
        """Collect the snapshot, or the reason there is none."""
        try:
            result["snap"] = collect(cfg, window, stop)
        except ConfigError:  # Bus.open: no session within PROBE_CONNECT_S (a run whose router is gone), or refused settings
            where = ", ".join(cfg.zenoh.connect) or "the configured endpoints"
            result["error"] = f"no Zenoh session to the run's router at {where} within {PROBE_CONNECT_S:.0f} s"
        except Exception as exc:  # noqa: BLE001 - the reason is printed, not a traceback
            result["error"] = f"could not ask the run: {exc}"

    thread = threading.Thread(target=work, name="status", daemon=True)
    thread.start()
    deadline = time.monotonic() + window + PROBE_CONNECT_S + 10.0
    while thread.is_alive() and not stop.is_set() and time.monotonic() < deadline:
        thread.join(0.1)
    if stop.is_set():
        print("interrupted")
        return 130
    if "error" in result:
        print(f"run {cfg.run_id}: not running, or not reachable from here: {result['error']}")
        return 1
    snap = result.get("snap")
    if not isinstance(snap, Snapshot) or not snap.alive:
        where = f"; {run_dir} has no summary.json: it stopped before the recorder wrote one" if run_dir else ""
        print(f"run {cfg.run_id}: not running (no service answers){where}")
        return 0
    print(live_report(cfg, snap, window, run_dir))
    return 0
