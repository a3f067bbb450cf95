"""``swarmmap experiment regularization``: the paper's Figures 7 and 8 over a grid. ``--robots``
agents (7), the strategies ``uniform-l2``, ``separate-l2``, ``separate-kl`` and ``--seeds`` seeds
each, over ``--shapes`` x ``--w-rho`` (W_rho / W_mu) x ``--kl-weights``: validation-loss curves
(a panel per cell: mean over agents and seeds, with their spread), a table of final losses with
the percentage difference of separate-kl against each other strategy and the seeds on which it
is lower, a verdict per cell, and the mean/std maps of the best run."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from swarmmap.services.experiments.common import (
    Progress,
    _plt,
    base_config,
    checked,
    fmt,
    maps_figure,
    mean_over_agents,
    prior_text,
    run_up,
    stack_curves,
    unseen_text,
    write_csv,
)
from swarmmap.services.experiments.score import SCORE_KEYS, load_maps, mean_scores, score_run, scores_table
from swarmmap.shared.run.config import ConfigError, RunConfig
from swarmmap.shared.run.config import parse_shape as parse_model_shape
from swarmmap.shared.run.rundir import final_val_bce, read_metrics

RegCell = tuple[tuple[int, ...], float, float]  # (model shape, W_rho / W_mu, kl_weight)


def parse_shape(text: str) -> tuple[int, ...]:
    """A BNN's model shape as ``--set learner.model_shape`` takes it: ``2,256,64,64,1`` or ``[2, 256, 64, 64, 1]``."""
    try:
        shape = tuple(parse_model_shape(text))
    except ValueError as exc:
        raise ConfigError(f"config error:\n  --shapes: {exc}") from None
    if len(shape) < 4 or shape[0] != 2 or shape[-1] != 1 or min(shape) < 1:
        raise ConfigError(f"config error:\n  --shapes: {text!r}: a BNN shape is 2, the sine layer, at least one "
                          f"Bayesian layer, then 1")
    return shape


def regularization_cells(args: argparse.Namespace, base: RunConfig) -> list[RegCell]:
    """The grid: every model shape x W_rho/W_mu ratio x kl_weight (each the base's when not given)."""
    shapes = [parse_shape(t) for t in args.shapes] if args.shapes else [tuple(base.learner.model_shape)]
    ratios = args.w_rho or [base.learner.w_rho / max(base.learner.w_mu, 1e-12)]
    kls = args.kl_weights or [base.learner.kl_weight]
    return list(dict.fromkeys((sh, r, k) for sh in shapes for r in ratios for k in kls))


def widths(shape: tuple[int, ...]) -> str:
    """A model shape's hidden widths, ``256x64x64``."""
    return "x".join(map(str, shape[1:-1]))


def cell_label(cell: RegCell) -> str:
    """A cell of the grid in words, for figures and reports."""
    shape, ratio, kl = cell
    return f"model {widths(shape)}, W_rho/W_mu {ratio:g}, kl_weight {kl:g}"


def run_key(strategy: str, cell: RegCell) -> tuple:
    """Which run of the grid gives ``strategy`` at ``cell``: uniform-l2 has no W_rho, so one
    run per shape and kl_weight serves every ratio."""
    shape, ratio, kl = cell
    return strategy, shape, None if strategy == "uniform-l2" else ratio, kl


FLAGS = {"learner.kl_weight": "--kl-weights", "learner.w_rho": "--w-rho", "learner.model_shape": "--shapes",
         "learner.rounds": "--rounds", "robots": "--robots"}


def regularization_plan(args: argparse.Namespace, base: RunConfig,
                        plan: dict[tuple, tuple[str, RegCell]]) -> list[tuple[int, tuple, str, RunConfig]]:
    """(seed, run key, run name, config) of every run, each config checked before any runs."""
    grid = len({cell for _, cell in plan.values()}) > 1
    runs = []
    for seed in args.seeds:
        for key, (strategy, (shape, ratio, kl)) in plan.items():
            learner = base.learner.model_copy(update={
                "regularization": strategy, "model_shape": list(shape), "kl_weight": kl,
                "w_rho": base.learner.w_mu * (1.0 if strategy == "uniform-l2" else ratio)})
            name = f"{strategy}-seed{seed}" if not grid else (
                f"{strategy}-{widths(shape)}-kl{kl:g}" + ("" if strategy == "uniform-l2" else f"-wrho{ratio:g}") + f"-seed{seed}")
            runs.append((seed, key, name, checked(base.model_copy(update={"seed": seed, "learner": learner}), name, FLAGS)))
    return runs


def regularization(args: argparse.Namespace) -> int:
    """The paper's Figures 7 and 8 over a grid (model shapes x W_rho/W_mu x kl_weight x seeds):
    where does Algorithm 2's KL regularisation beat the L2 strategies, and by how much?"""
    out: Path = args.out
    base = checked(base_config(args).model_copy(update={"robots": args.robots}), "regularization", FLAGS)
    strategies = args.strategies
    cells = regularization_cells(args, base)
    plan: dict[tuple, tuple[str, RegCell]] = {}
    for cell in cells:
        for strategy in strategies:
            plan.setdefault(run_key(strategy, cell), (strategy, cell))
    runs = regularization_plan(args, base, plan)
    out.mkdir(parents=True, exist_ok=True)
    progress = Progress(len(runs), base.learner.rounds)
    done: dict[tuple, dict[int, tuple[float, dict, dict, Path]]] = {key: {} for key in plan}
    rows = []
    try:
        for seed, key, name, cfg in runs:
            strategy, (shape, ratio, kl) = plan[key]
            run_dir = run_up(cfg, out / "runs" / name, progress, f"{strategy} {cell_label((shape, ratio, kl))} seed {seed}")
            metrics = read_metrics(run_dir)
            final = mean_over_agents(metrics)
            sc = mean_scores(score_run(run_dir))
            done[key][seed] = (final, metrics, sc, run_dir)
            rows.append([strategy, "x".join(map(str, shape)), "" if strategy == "uniform-l2" else ratio, kl, seed, final]
                        + [sc[k] for k in SCORE_KEYS])
    finally:
        progress.close()

    def result(strategy: str, cell: RegCell) -> dict[int, tuple[float, dict, dict, Path]]:
        return done[run_key(strategy, cell)]

    write_csv(out / "regularization_runs.csv", ["strategy", "model_shape", "w_rho_over_w_mu", "kl_weight", "seed",
                                                 "final_val_bce_mean_over_agents", *SCORE_KEYS], rows)
    curve_rows = []
    for cell in cells:
        for strategy in strategies:
            rounds, values = stack_curves([r[1] for r in result(strategy, cell).values()])
            for i, k in enumerate(rounds):
                curve_rows.append([strategy, "x".join(map(str, cell[0])), cell[1], cell[2], int(k), values[:, i].mean(),
                                   values[:, i].min(), values[:, i].max()])
    write_csv(out / "regularization_curves.csv", ["strategy", "model_shape", "w_rho_over_w_mu", "kl_weight", "round",
                                                   "val_bce_mean", "val_bce_min", "val_bce_max"], curve_rows)
    regularization_figure(cells, strategies, result, out / "regularization_curves.png")
    runs = [(r[0], strategy, seed, r[3]) for key, (strategy, _) in plan.items() for seed, r in done[key].items()]
    best = min(runs)
    best_maps = [(f"robot {r}", load_maps(best[3], r)) for r in sorted(final_val_bce(best[3]))[:4]]
    maps_figure(best_maps, out / "best_run_maps.png", base.observer.std_max)
    lines = regularization_report(args, base, cells, strategies, result, best)
    (out / "report.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


def regularization_figure(cells: list[RegCell], strategies, result, path: Path) -> None:
    """Validation BCE against round, a panel per cell of the grid, a line per strategy (mean
    over agents and seeds, min-max band)."""
    plt = _plt()
    cols = min(len(cells), 3)
    rows = -(-len(cells) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(max(7.0, 4.6 * cols), 3.4 * rows + 0.8), squeeze=False,
                             constrained_layout=True)
    for n, cell in enumerate(cells):
        ax = axes[n // cols, n % cols]
        for strategy in strategies:
            rounds, values = stack_curves([r[1] for r in result(strategy, cell).values()])
            if values.size:
                ax.plot(rounds, values.mean(0), label=strategy)
                ax.fill_between(rounds, values.min(0), values.max(0), alpha=0.2)
        if len(cells) > 1:
            ax.set_title(cell_label(cell), fontsize=8)
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.set_xlabel("round")
        ax.set_ylabel("validation BCE")
    for n in range(len(cells), rows * cols):
        axes[n // cols, n % cols].set_visible(False)
    axes[0, 0].legend()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def regularization_report(args, base: RunConfig, cells: list[RegCell], strategies, result, best) -> list[str]:
    """report.md's lines: the setting, the table of final losses, the verdicts, the scores, the best run."""
    seeds = args.seeds
    lines = [f"# Regularisation strategies (the paper's Figures 7 and 8): preset {base.preset}", "",
             f"{base.robots} agents, DiNNO over a {base.learner.graph} graph, {base.learner.rounds} rounds, "
             f"seeds {', '.join(map(str, seeds))}, transport {base.learner.transport}, device {base.learner.device}; "
             f"W_mu {base.learner.w_mu:g} x rho. Grid: {len(cells)} cell(s) of model shape x W_rho/W_mu x kl_weight "
             f"(uniform-l2 has no W_rho: one run serves every ratio).{unseen_text(base)}{prior_text(base)}", "",
             "![validation loss](regularization_curves.png)", "",
             "| model | W_rho/W_mu | kl_weight | strategy | final val_bce (mean over agents, then seeds) | spread over seeds "
             "| separate-kl against it | seeds where separate-kl is lower |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    verdicts = []
    for cell in cells:
        finals = {st: {seed: r[0] for seed, r in result(st, cell).items()} for st in strategies}
        mean = {st: float(np.mean(list(v.values()))) for st, v in finals.items()}
        shape, ratio, kl = cell
        lower_all, diffs = True, []
        for st in strategies:
            v = list(finals[st].values())
            vs = ""
            wins = ""
            if "separate-kl" in strategies and st != "separate-kl":
                diff = 100 * (mean["separate-kl"] - mean[st]) / mean[st]
                diffs.append(diff)
                won = sum(finals["separate-kl"][s] < finals[st][s] for s in seeds)
                lower_all &= won == len(seeds)
                vs, wins = f"{diff:+.1f}%", f"{won} of {len(seeds)}"
            lines.append(f"| {widths(shape)} | {'-' if st == 'uniform-l2' else f'{ratio:g}'} | {kl:g} "
                         f"| {st} | {fmt(mean[st])} | {fmt(min(v))} to {fmt(max(v))} | {vs} | {wins} |")
        if diffs:
            verdicts.append((cell, lower_all, max(diffs), min(diffs)))
    if verdicts:
        lines += ["", "Where separate-kl (Algorithm 2) stands against the L2 strategies (the paper reports 12-30% "
                      "lower validation loss):", ""]
        for cell, lower_all, worst, bestd in verdicts:
            if lower_all:
                lines.append(f"- {cell_label(cell)}: lower on every seed against every L2 strategy, by "
                             f"{-worst:.1f}% to {-bestd:.1f}% of the mean")
            else:
                lines.append(f"- {cell_label(cell)}: not lower on every seed (separate-kl {bestd:+.1f}% to {worst:+.1f}% "
                             f"against the L2 strategies' means)")
    lines += ["", "Uncertainty scores, mean over agents and seeds (observed = within 0.1 m of any robot's "
                  "training point):", ""]
    lines += scores_table([(f"{st}, {cell_label(cell)}" if len(cells) > 1 else st,
                            {k: float(np.nanmean([r[2][k] for r in result(st, cell).values()])) for k in SCORE_KEYS})
                           for cell in cells for st in strategies])
    lines += ["", f"Best run: {best[1]} seed {best[2]} (val_bce {fmt(best[0])}, {best[3].name}), its first agents' maps:",
              "", "![best run maps](best_run_maps.png)", "", f"Command: `{' '.join(sys.argv)}`", ""]
    return lines


