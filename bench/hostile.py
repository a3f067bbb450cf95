"""A hostile member of the team: each named attack against a clean run, robust consensus on (and off).

    python bench/hostile.py [--preset demo] [--robots 7] [--hostile 6] [--rounds N] [--bnn]
                            [--attacks ratchet signflip ...] [--no-robust] [--out /tmp/hostile]

One clean ``swarmmap up`` run (Zenoh, a learner process per robot with its own credentials),
then one run per attack in which robot ``--hostile``'s learner lies to its neighbours
(``faults.attack``, services/learner/attacks.py) while training honestly itself. Prints, per
attack, the honest robots' final mean val_bce against the clean run's (the headline: within 10%),
the lies refused, whether the run ended by itself, and its wall time. ``--bnn`` runs the
paper's Bayesian network with sigma consensus (and adds the sigma attack); ``--no-robust`` turns
robust consensus off (``learner.robust=false``) to show what the attacks do without it. Runs are
kept in ``--out`` and reused when their summary is there.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: its common parts

from common import Runs, up_run  # noqa: E402

ATTACKS = ["ratchet", "signflip", "scale", "noise", "stall", "equivocate"]


def run(run_dir: Path, args: list[str]) -> tuple[dict, float]:
    """The run's summary (running it unless it is there already) and its wall time."""
    summary = up_run(run_dir, args)
    return summary, float(summary.get("wall_time_s") or 0.0)


def honest(summary: dict, hostile: int) -> tuple[float, int]:
    """The honest robots' mean final val_bce and the States they refused."""
    rows = [v for r, v in summary["learners"].items() if int(r) != hostile]
    finals = [v["final_val_bce"] for v in rows if v["final_val_bce"] is not None]
    return (sum(finals) / len(finals) if finals else float("nan")), sum(int(v["refused"] or 0) for v in rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--robots", type=int, default=7)
    ap.add_argument("--hostile", type=int, default=6)
    ap.add_argument("--rounds", type=int, default=None)
    ap.add_argument("--bnn", action="store_true", help="the paper's Bayesian network with sigma consensus")
    ap.add_argument("--attacks", nargs="+", default=None)
    ap.add_argument("--no-robust", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("/tmp/hostile"))
    a = ap.parse_args()
    args = ["--preset", a.preset, "--robots", str(a.robots), "--no-observer"] + (["--rounds", str(a.rounds)] if a.rounds else [])
    if a.bnn:
        args += ["--model", "bnn", "--set", "learner.consensus=sigma"]
    args += ["--set", f"learner.robust={'false' if a.no_robust else 'true'}"]
    attacks = a.attacks or ATTACKS + (["sigma"] if a.bnn else [])
    case = f"{a.preset}, {a.robots} robots, {'BNN sigma' if a.bnn else 'FourierNet dinno'}, robust {'off' if a.no_robust else 'on'}"
    a.out.mkdir(parents=True, exist_ok=True)
    runs = Runs(1 + len(attacks))
    clean, clean_s = run(a.out / "clean", args)
    runs.ended("clean")
    reference, _ = honest(clean, a.hostile)
    print(f"clean run ({case}): honest robots' mean val_bce {reference:.4f}, {clean_s:.0f} s, ok {clean['ok']}", flush=True)
    worst = 0.0
    for attack in attacks:
        summary, wall = run(a.out / attack, args + ["--set", f"faults.attack={attack}", "--set", f"faults.attackers=[{a.hostile}]"])
        runs.ended(attack)
        mean, refused = honest(summary, a.hostile)
        change = mean / reference - 1
        worst = max(worst, change)
        print(f"attack {attack} ({case}, robot {a.hostile} hostile): honest mean val_bce {mean:.4f} against the clean run's "
              f"{reference:.4f}: {100 * change:+.1f}%; {refused} States refused; ended by itself: {summary['ok'] or summary['reason']}; "
              f"{wall:.0f} s", flush=True)
    print(f"hostile member ({case}): worst honest mean val_bce {100 * worst:+.1f}% against a clean run over "
          f"{len(attacks)} attacks (goal: within +10%)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
