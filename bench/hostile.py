"""A hostile member of the team: each named attack against two clean runs, robust consensus on (and off).

    python bench/hostile.py [--preset demo] [--robots 7] [--hostile 6] [--graph complete|ring]
                            [--rounds N] [--seed S] [--bnn] [--attacks ratchet signflip ...] [--no-robust]
                            [--out /tmp/hostile]

Two clean ``swarmmap up`` runs (Zenoh, a learner process per robot with its own credentials):
``clean``, every robot honest, and ``without``, the same robots on the same paths but with the
hostile robot cut out of the graph (it trains alone): what the honest robots can learn once that
member is left out, since its data leave with it (a room only it saw is a room the others cannot
map). Then one run per attack in which robot ``--hostile``'s learner attacks from round 0
(``faults.attack``, services/learner/attacks.py) while training honestly itself. Prints, per
attack, the honest robots' final mean val_bce against the ``without`` run's (the headline: within
10%) and the ``clean`` run's, the same on the validation points they sensed (within one grid
cell of their training points: elsewhere a network's guess swings from run to run), their
val_bce in the last quarter of the rounds against the ``without`` run's (rising after the member
is left out would show here), the messages refused, the leave-outs, whether the run ended by
itself, and its wall time. ``--bnn`` runs the paper's Bayesian network with sigma consensus (and
adds the sigma attack); ``--no-robust`` turns robust consensus off (``learner.robust=false``) to
show what the attacks do without it. Runs are kept in ``--out`` and reused when their summary is there.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: its common parts

from common import Runs, up_run  # noqa: E402

ATTACKS = ["ratchet", "signflip", "scale", "noise", "stall", "equivocate", "far-future", "repeat", "bomb",
           "metrics-flood"]


def edges(graph: str, robots: int) -> list[tuple[int, int]]:
    """The edges of the ``complete`` or ``ring`` graph of ``robots`` robots."""
    if graph == "ring":
        return sorted({tuple(sorted((i, (i + 1) % robots))) for i in range(robots)})
    return [(i, j) for i in range(robots) for j in range(i + 1, robots)]


def honest(summary: dict, hostile: int) -> tuple[float, int]:
    """The honest robots' mean final val_bce and the messages they refused."""
    rows = [v for r, v in summary["learners"].items() if int(r) != hostile]
    finals = [v["final_val_bce"] for v in rows if v["final_val_bce"] is not None]
    return (sum(finals) / len(finals) if finals else float("nan")), sum(int(v["refused"] or 0) for v in rows)


def late_mean(run_dir: Path, hostile: int, rounds: int) -> float:
    """The honest robots' mean val_bce over the reports of the last quarter of the rounds."""
    with (run_dir / "metrics.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if int(r["robot"]) != hostile and int(r["round"]) >= 0.75 * rounds]
    return sum(float(r["val_bce"]) for r in rows) / max(len(rows), 1)


def left_out(run_dir: Path, hostile: int) -> int:
    """How many honest learners' logs say the hostile robot was left out."""
    words = (f"neighbour {hostile} ", "left out", "goes on without it")
    count = 0
    for log in (run_dir / "logs").glob("learner-*.log"):
        if log.name != f"learner-{hostile}.log":
            count += any(words[0] in line and (words[1] in line or words[2] in line) for line in log.open(errors="replace"))
    return count


def sensed_bce(run_dir: Path, honest_robots: list[int]) -> float:
    """The honest robots' mean BCE on the validation points within one grid cell of a point of
    their training data: the map they can know, whatever the others saw (the same points in every
    run of one plan and paths)."""
    import numpy as np
    import torch
    from scipy.spatial import cKDTree

    from swarmmap.services.learner.metrics import validation_bce
    from swarmmap.shared.api import open_run

    run = open_run(run_dir)
    truth = run.groundtruth()
    seen = np.concatenate([np.load(run_dir / "data" / f"robot-{r}.npz")["points"] for r in honest_robots])
    near = cKDTree(seen).query(truth["val_points"], distance_upper_bound=float(truth["resolution"]))[0] < np.inf
    x = torch.from_numpy(truth["val_points"][near].astype(np.float32))
    y = torch.from_numpy(truth["val_labels"][near].astype(np.float32))
    return float(np.mean([validation_bce(run.model(r), x, y) for r in honest_robots]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--robots", type=int, default=7)
    ap.add_argument("--hostile", type=int, default=None, help="the hostile robot (default: the last)")
    ap.add_argument("--graph", choices=["complete", "ring"], default="complete")
    ap.add_argument("--rounds", type=int, default=None)
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--bnn", action="store_true", help="the paper's Bayesian network with sigma consensus")
    ap.add_argument("--attacks", nargs="+", default=None)
    ap.add_argument("--no-robust", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("/tmp/hostile"))
    a = ap.parse_args()
    hostile_robot = a.robots - 1 if a.hostile is None else a.hostile
    args = ["--preset", a.preset, "--robots", str(a.robots), "--no-observer"] + (["--rounds", str(a.rounds)] if a.rounds else [])
    args += ["--seed", str(a.seed)] if a.seed is not None else []
    if a.bnn:
        args += ["--model", "bnn", "--set", "learner.consensus=sigma"]
    args += ["--set", f"learner.robust={'false' if a.no_robust else 'true'}"]
    a.out.mkdir(parents=True, exist_ok=True)
    graph_file = a.out / "graph.json"
    graph_file.write_text(json.dumps(edges(a.graph, a.robots)))
    without_file = a.out / "without.json"
    without_file.write_text(json.dumps([e for e in edges(a.graph, a.robots) if hostile_robot not in e]))
    args += ["--set", "learner.graph=file", "--set", f"learner.graph_file={graph_file}"]
    attacks = a.attacks or ATTACKS + (["sigma"] if a.bnn else [])
    case = (f"{a.preset}, {a.robots} robots, {a.graph} graph, {'BNN sigma' if a.bnn else 'FourierNet dinno'}, "
            f"robust {'off' if a.no_robust else 'on'}")
    runs = Runs(2 + len(attacks))
    clean = up_run(a.out / "clean", args)
    runs.ended("clean")
    without = up_run(a.out / "without", args + ["--set", f"learner.graph_file={without_file}"])
    runs.ended("without")
    rounds = int(clean["rounds"])
    reference, _ = honest(without, hostile_robot)
    everyone, _ = honest(clean, hostile_robot)
    late_ref = late_mean(a.out / "without", hostile_robot, rounds)
    honest_robots = [r for r in range(a.robots) if r != hostile_robot]
    sensed_ref, sensed_clean = sensed_bce(a.out / "without", honest_robots), sensed_bce(a.out / "clean", honest_robots)
    print(f"clean runs ({case}): honest robots' mean val_bce {everyone:.4f} with robot {hostile_robot} honest, "
          f"{reference:.4f} without it (its data never shared); on what they sensed {sensed_clean:.4f} and "
          f"{sensed_ref:.4f}", flush=True)
    worst = worst_sensed = 0.0
    for attack in attacks:
        run_dir = a.out / attack
        summary = up_run(run_dir, args + ["--set", f"faults.attack={attack}", "--set", f"faults.attackers=[{hostile_robot}]"])
        runs.ended(attack)
        mean, refused = honest(summary, hostile_robot)
        change = mean / reference - 1
        worst = max(worst, change)
        late = late_mean(run_dir, hostile_robot, rounds) / late_ref - 1
        sensed = sensed_bce(run_dir, honest_robots)
        worst_sensed = max(worst_sensed, sensed / sensed_ref - 1)
        degree = sum(hostile_robot in e for e in edges(a.graph, a.robots))
        print(f"attack {attack} ({case}, robot {hostile_robot} hostile): honest mean val_bce {mean:.4f}, "
              f"{100 * change:+.1f}% against the team without it, {100 * (mean / everyone - 1):+.1f}% against the clean "
              f"run; last quarter {100 * late:+.1f}% against the team without it; on what they sensed {sensed:.4f}, "
              f"{100 * (sensed / sensed_ref - 1):+.1f}% against the team without it, {100 * (sensed / sensed_clean - 1):+.1f}% "
              f"against the clean run; {refused} messages refused; left out "
              f"by {left_out(run_dir, hostile_robot)} of {degree} neighbours; ended by itself: {summary['ok'] or summary['reason']}; "
              f"{summary.get('wall_time_s') or 0:.0f} s", flush=True)
    print(f"hostile member ({case}): worst honest mean val_bce {100 * worst:+.1f}% against the team without it over "
          f"{len(attacks)} attacks (goal: within +10%); on what they sensed {100 * worst_sensed:+.1f}%", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
