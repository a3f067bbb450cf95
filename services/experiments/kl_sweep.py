"""``swarmmap experiment kl-sweep``: the paper's Figure 6. One isolated agent (no communication)
whose path visits only ``--rooms`` rooms, so part of the plan stays unseen; one run per
``--kl-weights`` value; a row of mean maps over a row of std maps, the scores and a report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from swarmmap.services.experiments.common import (
    Progress,
    base_config,
    checked,
    fmt,
    maps_figure,
    model_text,
    prior_text,
    reliability_figure,
    run_up,
    unseen_text,
    write_csv,
)
from swarmmap.services.experiments.score import SCORE_KEYS, load_maps, score_run, scores_table
from swarmmap.shared.run.rundir import final_val_bce

FLAGS = {"learner.kl_weight": "--kl-weights", "world.rooms_per_robot": "--rooms", "learner.rounds": "--rounds"}


def kl_sweep(args: argparse.Namespace) -> int:
    """Run the sweep into ``--out`` and write its figures, CSV and report; every setting is
    checked before anything is created."""
    out: Path = args.out
    base = base_config(args)
    world = base.world.model_copy(update={"rooms_per_robot": args.rooms})
    learner = base.learner.model_copy(update={"algorithm": "individual"})
    base = checked(base.model_copy(update={"robots": 1, "world": world, "learner": learner}), "kl-sweep", FLAGS)
    runs = {kl: checked(base.model_copy(update={"learner": base.learner.model_copy(update={"kl_weight": kl})}),
                        f"kl-{kl:g}", FLAGS) for kl in args.kl_weights}
    out.mkdir(parents=True, exist_ok=True)
    progress = Progress(len(args.kl_weights), base.learner.rounds)
    columns, rows, scored = [], [], []
    try:
        for kl, cfg in runs.items():
            run_dir = run_up(cfg, out / "runs" / f"kl-{kl:g}", progress, f"kl_weight {kl:g}")
            scores = score_run(run_dir)[0]
            val = final_val_bce(run_dir)[0]
            columns.append((f"kl_weight = {kl:g}", load_maps(run_dir, 0)))
            rows.append([kl, val] + [scores[k] for k in SCORE_KEYS])
            scored.append((f"kl_weight {kl:g}", scores))
    finally:
        progress.close()
    maps_figure(columns, out / "kl_sweep_maps.png", base.observer.std_max)
    reliability_figure([(label, sc["reliability"]) for label, sc in scored], out / "reliability.png")
    write_csv(out / "kl_sweep.csv", ["kl_weight", "final_val_bce", *SCORE_KEYS], rows)
    lines = [f"# KL-weight sweep (the paper's Figure 6): preset {base.preset}", "",
             f"One isolated agent (no communication) whose path visits {args.rooms} room(s), so part of the plan "
             f"stays unseen{unseen_text(base)}; {base.learner.rounds} rounds of {base.learner.primal_iterations} steps, "
             f"{model_text(base)}.{prior_text(base)}",
             "", "![mean and std maps](kl_sweep_maps.png)", "",
             "| kl_weight | final val_bce |", "| --- | --- |"]
    lines += [f"| {r[0]:g} | {fmt(r[1])} |" for r in rows]
    lines += ["", "Uncertainty scores (observed = within 0.1 m of a training point):", ""] + scores_table(scored)
    lines += ["", "![reliability diagrams of the mean maps](reliability.png)"]
    lines += ["", f"Command: `{' '.join(sys.argv)}`", ""]
    (out / "report.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


