"""``swarmmap experiment consensus``: ``--robots`` agents, consensus rules
(``learner.consensus``) x link success (``faults.link_success`` drawn per link and round, with
``learner.round_wait_s`` below 100%) x exchange intervals (``learner.exchange_every``), then each
``--compression`` mode over perfect links; curves of val_bce against round and against bytes
sent, a table with sigma's wins per seed, and the bytes and loss of each compression against
float32."""

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
    mean_over_agents,
    prior_text,
    run_up,
    stack_curves,
    unseen_text,
    write_csv,
)
from swarmmap.services.experiments.score import SCORE_KEYS, mean_scores, score_run, scores_table
from swarmmap.shared.run.config import RunConfig, std_models
from swarmmap.shared.run.rundir import read_metrics


def cell_name(consensus: str, link: float, every: int, compression: str) -> str:
    """The name of a cell's runs, ``sigma-link0.3-every1-none``."""
    return f"{consensus}-link{link:g}-every{every}-{compression}"


def consensus_cells(args: argparse.Namespace) -> list[tuple[str, float, int, str]]:
    """(consensus, link success, exchange_every, compression) of every run of a seed: the grid of
    consensus x links x exchange intervals uncompressed, then each compression mode over perfect
    links every round for the ``--compression-consensus`` rules."""
    cells = [(c, link, every, "none") for link in args.link_success for every in args.exchange_every for c in args.consensus]
    cells += [(c, 1.0, 1, mode) for mode in args.compression if mode != "none" for c in args.compression_consensus]
    return list(dict.fromkeys(cells))


FLAGS = {"faults.link_success": "--link-success", "learner.exchange_every": "--exchange-every",
         "learner.round_wait_s": "--round-wait", "learner.rounds": "--rounds", "robots": "--robots"}


def consensus_plan(args: argparse.Namespace, base: RunConfig) -> list[tuple[int, tuple, RunConfig]]:
    """(seed, cell, config) of every run, each config checked as a whole before any runs."""
    plan = []
    for seed in args.seeds:
        for cell in consensus_cells(args):
            cons, link, every, comp = cell
            learner = base.learner.model_copy(update={
                "consensus": cons, "exchange_every": every, "compression": comp,
                "round_wait_s": args.round_wait if link < 1 else 0.0})
            faults = base.faults.model_copy(update={"link_success": link, "seed": seed, "per_round": True})
            cfg = base.model_copy(update={"seed": seed, "learner": learner, "faults": faults})
            plan.append((seed, cell, checked(cfg, f"{cell_name(*cell)}-seed{seed}", FLAGS)))
    return plan


def consensus(args: argparse.Namespace) -> int:
    """Uncertainty-weighted consensus under poor links and compressed States: the grid's runs,
    then their CSV, figures and report in ``--out``."""
    out: Path = args.out
    base = checked(base_config(args).model_copy(update={"robots": args.robots}), "consensus", FLAGS)
    cells = consensus_cells(args)
    plan = consensus_plan(args, base)
    out.mkdir(parents=True, exist_ok=True)
    progress = Progress(len(plan), base.learner.rounds)
    finals: dict[tuple, dict[int, float]] = {}
    sent: dict[tuple, dict[int, float]] = {}
    curves: dict[tuple, list] = {}
    byte_curves: dict[tuple, list] = {}
    scored: dict[tuple, list[dict[str, float]]] = {}
    rows = []
    try:
        for seed, cell, cfg in plan:
            cons, link, every, comp = cell
            run_dir = run_up(cfg, out / "runs" / f"{cell_name(*cell)}-seed{seed}", progress, f"{cell_name(*cell)} seed {seed}")
            metrics, wire = read_metrics(run_dir), read_metrics(run_dir, "bytes_sent")
            final = mean_over_agents(metrics)
            per_learner = mean_over_agents(wire)
            finals.setdefault(cell, {})[seed] = final
            sent.setdefault(cell, {})[seed] = per_learner
            curves.setdefault(cell, []).append(metrics)
            byte_curves.setdefault(cell, []).append(wire)
            sc = mean_scores(score_run(run_dir)) if base.learner.model in std_models() else {k: float("nan") for k in SCORE_KEYS}
            scored.setdefault(cell, []).append(sc)
            rows.append([cons, link, every, comp, seed, final, per_learner] + [sc[k] for k in SCORE_KEYS])
    finally:
        progress.close()
    write_csv(out / "consensus_runs.csv", ["consensus", "link_success", "exchange_every", "compression", "seed",
                                           "final_val_bce_mean_over_agents", "bytes_sent_per_learner", *SCORE_KEYS], rows)
    consensus_figures(cells, curves, byte_curves, out)
    lines = consensus_report(args, base, cells, finals, sent, scored)
    (out / "report.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


def consensus_figures(cells, curves, byte_curves, out: Path) -> None:
    """val_bce against round (a panel per link success and exchange interval, a line per
    consensus rule) and against bytes sent per learner (every run of the grid)."""
    plt = _plt()
    links = sorted({c[1] for c in cells if c[3] == "none"}, reverse=True)
    everys = sorted({c[2] for c in cells if c[3] == "none"})
    if links:
        fig, axes = plt.subplots(len(links), len(everys), figsize=(4.6 * len(everys), 3.2 * len(links)), squeeze=False,
                                 sharey=True, constrained_layout=True)
        for cell in cells:
            cons, link, every, comp = cell
            if comp != "none":
                continue
            ax = axes[links.index(link), everys.index(every)]
            rounds, values = stack_curves(curves[cell])
            if values.size:
                ax.plot(rounds, values.mean(0), label=cons)
                ax.fill_between(rounds, values.min(0), values.max(0), alpha=0.15)
            ax.set_title(f"link success {link:.0%}, exchange every {every}", fontsize=9)
            ax.set_yscale("log")
            ax.grid(alpha=0.3)
        for ax in axes[-1]:
            ax.set_xlabel("round")
        for ax in axes[:, 0]:
            ax.set_ylabel("validation BCE")
        axes[0, 0].legend()
        fig.savefig(out / "consensus_curves.png", dpi=110)
        plt.close(fig)
    fig, ax = plt.subplots(figsize=(7.5, 4.5), constrained_layout=True)
    for cell in cells:
        xs, ys = [], []
        for metrics, wire in zip(curves[cell], byte_curves[cell]):
            for robot, rows in metrics.items():
                by_round = dict(wire[robot])
                xs.append([by_round[k] / 1e6 for k, _ in rows])
                ys.append([v for _, v in rows])
        n = min(len(x) for x in xs)
        ax.plot(np.mean([x[:n] for x in xs], 0), np.mean([y[:n] for y in ys], 0), label=cell_name(*cell), lw=1)
    ax.set_xscale("symlog", linthresh=0.1)
    ax.set_yscale("log")
    ax.set_xlabel("MB sent per learner")
    ax.set_ylabel("validation BCE")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, ncol=2)
    fig.savefig(out / "consensus_bytes.png", dpi=110)
    plt.close(fig)


def consensus_report(args, base: RunConfig, cells, finals, sent, scored) -> list[str]:
    """report.md's lines: the setting, the table per cell, sigma against the others, compression, scores."""
    seeds = args.seeds

    def mean(cell):
        return float(np.mean([finals[cell][s] for s in seeds]))

    lines = [f"# Consensus under poor links, and compressed States: preset {base.preset}", "",
             f"{base.robots} agents, model {base.learner.model} {base.learner.model_shape}, DiNNO over a "
             f"{base.learner.graph} graph, {base.learner.rounds} rounds, seeds {', '.join(map(str, seeds))}, transport "
             f"{base.learner.transport}. Poor links: each link is up for a round, both ways, with the link success "
             f"probability (drawn per link and round: the messages of a round that is down are lost, resends "
             f"included); below 100% a round waits at most {args.round_wait:g} s for messages."
             f"{unseen_text(base)}{prior_text(base)}", "",
             "![val_bce against round](consensus_curves.png)", "", "![val_bce against bytes sent](consensus_bytes.png)", "",
             "| consensus | link success | exchange every | compression | final val_bce (mean over agents, then seeds) "
             "| spread over seeds | MB sent per learner |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for cell in cells:
        v = [finals[cell][s] for s in seeds]
        lines.append(f"| {cell[0]} | {cell[1]:.0%} | {cell[2]} | {cell[3]} | {fmt(mean(cell))} | {fmt(min(v))} to "
                     f"{fmt(max(v))} | {np.mean([sent[cell][s] for s in seeds]) / 1e6:.2f} |")
    comparisons = []
    for cell in cells:
        cons, link, every, comp = cell
        if cons != "sigma" or comp != "none":
            continue
        for other in ("dinno", "ramen"):
            ref = (other, link, every, comp)
            if ref in finals:
                wins = sum(finals[cell][s] < finals[ref][s] for s in seeds)
                diff = 100 * (mean(cell) - mean(ref)) / mean(ref)
                comparisons.append(f"- link {link:.0%}, every {every}: sigma against {other}: {diff:+.1f}% "
                                   f"(lower on {wins} of {len(seeds)} seeds)")
    if comparisons:
        lines += ["", "sigma's final val_bce against the other rules (negative: lower):", ""] + comparisons
    packed = [c for c in cells if c[3] != "none" and (c[0], 1.0, 1, "none") in finals]
    if packed:
        lines += ["", "| compression | consensus | bytes against float32 | final val_bce against float32 |",
                  "| --- | --- | --- | --- |"]
        for cell in packed:
            ref = (cell[0], 1.0, 1, "none")
            ratio = np.mean([sent[ref][s] for s in seeds]) / np.mean([sent[cell][s] for s in seeds])
            lines.append(f"| {cell[3]} | {cell[0]} | {ratio:.1f}x fewer | {100 * (mean(cell) - mean(ref)) / mean(ref):+.1f}% |")
    if base.learner.model in std_models():
        lines += ["", "Uncertainty scores, mean over agents and seeds:", ""]
        lines += scores_table([(cell_name(*c), {k: float(np.nanmean([x[k] for x in scored[c]])) for k in SCORE_KEYS})
                               for c in cells])
    lines += ["", f"Command: `{' '.join(sys.argv)}`", ""]
    return lines


