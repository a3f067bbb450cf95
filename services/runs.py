"""Tools that read run directories: ``swarmmap runs``, ``swarmmap logs`` and ``swarmmap compare``.

    swarmmap runs [FOLDER]                     # every run in FOLDER (default ./runs) at a glance
    swarmmap logs RUN_DIR                      # the run's service logs, with sizes
    swarmmap logs RUN_DIR learner-1 --tail 50  # one service's log (learner: every learner's)
    swarmmap compare RUN_A RUN_B=label [--out ab.png] [--target 0.102]  # default: RUN_A/compare.png

They need no config and no network: what a run leaves is enough, also of a run that failed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from swarmmap.shared.run.config import did_you_mean
from swarmmap.shared.run.rundir import TeamCurve, is_run_dir, local_time, run_info, run_words, team_curve, unused_path


class ToolError(Exception):
    """A path or argument the tool cannot use; printed as is, exit status 2."""


def run_folders(folder: Path) -> list[Path]:
    """The run directories in ``folder`` (each holds a config.yaml), by start time; ``folder``
    itself when it is one."""
    if not folder.is_dir():
        raise ToolError(f"swarmmap runs: {folder} is not a folder" + (" (it does not exist)" if not folder.exists() else ""))
    if is_run_dir(folder):
        return [folder]
    return sorted((p for p in folder.iterdir() if p.is_dir() and is_run_dir(p)), key=lambda p: (p / "config.yaml").stat().st_mtime)


def list_runs(args: argparse.Namespace) -> int:
    """``swarmmap runs [FOLDER]``: a table of the runs, their status and final mean val_bce."""
    infos = [run_info(p) for p in run_folders(args.folder)]
    if not infos:
        print(f"no runs in {args.folder} (a run directory holds config.yaml; swarmmap up --run-dir makes one)")
        return 0
    header = ("run", "status", "robots", "rounds", "final val_bce", "started", "what")
    rows = [(i.path.name, i.status, str(i.robots or "?"), str(i.rounds or "?"),
             "n/a" if i.final_mean_val_bce is None else f"{i.final_mean_val_bce:.4f}", local_time(i.started), run_words(i.path))
            for i in infos]
    widths = [max(len(r[k]) for r in [header, *rows]) for k in range(len(header))]
    for row in [header, *rows]:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())
    return 0


def log_files(run_dir: Path) -> list[Path]:
    """The run's service logs (``logs/<service>-<id>.log``), by name."""
    if not run_dir.is_dir():
        raise ToolError(f"swarmmap logs: {run_dir} is not a run directory" + (" (it does not exist)" if not run_dir.exists() else ""))
    folder = run_dir / "logs"
    if not folder.is_dir():
        raise ToolError(f"swarmmap logs: {run_dir} has no logs/ folder (swarmmap up, compose with a log driver of "
                        "its own, or a run that never started)")
    return sorted(folder.glob("*.log"), key=lambda p: (p.stem.rsplit("-", 1)[0], int(p.stem.rsplit("-", 1)[-1])
                                                      if p.stem.rsplit("-", 1)[-1].isdigit() else 0))


def show_logs(args: argparse.Namespace) -> int:
    """``swarmmap logs RUN_DIR [SERVICE]``: the list of logs, or the chosen ones' text."""
    files = log_files(args.run_dir)
    if args.service is None:
        for f in files:
            size = f.stat().st_size
            print(f"{f.stem:<14} {size / 1024:8.1f} KiB  {local_time(f.stat().st_mtime)}  {f}")
        if not files:
            print(f"{args.run_dir / 'logs'} holds no logs")
        return 0
    names = {f.stem: f for f in files}
    chosen = [names[args.service]] if args.service in names else [f for f in files if f.stem.rsplit("-", 1)[0] == args.service]
    if not chosen:
        raise ToolError(f"swarmmap logs: no log of {args.service!r} in {args.run_dir / 'logs'}"
                        f"{did_you_mean(args.service, [*names, *{n.rsplit('-', 1)[0] for n in names}])}; "
                        f"there are: {', '.join(names) or 'none'}")
    for f in chosen:
        lines = f.read_text(errors="replace").splitlines()
        if len(chosen) > 1:
            print(f"==> {f} <==")
        print("\n".join(lines[-args.tail:] if args.tail > 0 else lines))
    return 0


def reached(curve: TeamCurve, target: float) -> tuple[int, float] | None:
    """(round, seconds) when the team's mean val_bce first reached ``target``."""
    return next(((k, t) for k, t, m in zip(curve.rounds, curve.seconds, curve.mean) if m <= target), None)


def plot_curves(curves: list[tuple[str, TeamCurve]], out: Path, target: float | None = None) -> None:
    """Mean val_bce against round and against wall time, a line per run, into ``out`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (by_round, by_time) = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True, constrained_layout=True)
    for label, c in curves:
        by_round.plot(c.rounds, c.mean, marker=".", label=label)
        by_time.plot(c.seconds, c.mean, marker=".", label=label)
    by_round.set_xlabel("round")
    by_time.set_xlabel("wall time since the run started (s)")
    by_round.set_ylabel("mean validation BCE over robots")
    for ax in (by_round, by_time):
        if target is not None:
            ax.axhline(target, color="grey", linestyle="--", linewidth=1)
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    by_round.legend(fontsize=8)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def compare(args: argparse.Namespace) -> int:
    """``swarmmap compare RUN...``: each run's final mean val_bce (and when it reached
    ``--target``), and its curves against round and wall time in ``--out``."""
    curves = []
    for spec in args.runs:
        path, _, label = spec.partition("=")
        run_dir = Path(path)
        if not is_run_dir(run_dir):
            raise ToolError(f"swarmmap compare: {run_dir} is not a run directory (no config.yaml)")
        try:
            curve = team_curve(run_dir)
        except FileNotFoundError as exc:
            raise ToolError(f"swarmmap compare: {exc}") from None
        if not curve.rounds:
            raise ToolError(f"swarmmap compare: {run_dir}: no round that every learner reported")
        curves.append((label or f"{run_dir.name} ({run_words(run_dir)})", curve))
    for label, c in curves:
        when = ""
        if args.target is not None:
            hit = reached(c, args.target)
            when = (f"reached {args.target} at round {hit[0]}, {hit[1]:.0f} s; " if hit else f"never reached {args.target}; ")
        print(f"{label}: {when}final mean val_bce {c.mean[-1]:.4f} at round {c.rounds[-1]}, {c.seconds[-1]:.0f} s "
              f"(start-up and traversal {c.startup_s:.0f} s)", flush=True)
    out = args.out or unused_path(Path(args.runs[0].partition("=")[0]) / "compare.png")
    if out.exists():
        raise ToolError(f"swarmmap compare: {out} exists; name another --out (nothing is overwritten)")
    plot_curves(curves, out, args.target)
    print(f"curves: {out}")
    return 0
