"""``swarmmap experiment``: the paper's experiments as commands that make its figures.

    swarmmap experiment kl-sweep --preset demo --out results/kl        # the paper's Figure 6
    swarmmap experiment regularization --preset demo --out results/reg # its Figures 7 and 8
    swarmmap experiment consensus --preset demo --out results/cons     # consensus rules, poor links, compression
    swarmmap experiment score RUN_DIR                                  # uncertainty scores of one run

Each experiment runs the real system (``swarmmap up``, learners in one process by default,
which gives the same parameters as over Zenoh) once per setting, then writes PNG figures, the
CSV behind them and ``report.md`` into ``--out``. Every report carries the uncertainty scores
of :mod:`swarmmap.shared.uncertainty` (NLL, ECE, AUROC of the std for the map's errors, mean std
over observed and never-observed cells).

- ``kl-sweep``: one isolated agent (``--robots 1``, no communication) whose path visits only
  ``--rooms`` rooms, so part of the plan stays unseen; one run per ``--kl-weights`` value; a
  row of mean maps over a row of std maps.
- ``regularization``: ``--robots`` agents (7), the strategies ``uniform-l2``, ``separate-l2``,
  ``separate-kl`` and ``--seeds`` seeds each, over a grid of ``--shapes`` x ``--w-rho``
  (W_rho / W_mu) x ``--kl-weights``; validation-loss curves (a panel per cell: mean over
  agents and seeds, with their spread), a table of final losses with the percentage difference
  of separate-kl against each other strategy and the seeds on which it is lower, a verdict per
  cell, and the mean/std maps of the best run.
- ``consensus``: ``--robots`` agents, consensus rules (``learner.consensus``) x link success
  (``faults.link_success`` drawn per link and round, with ``learner.round_wait_s`` below 100%) x exchange intervals
  (``learner.exchange_every``), then each ``--compression`` mode over perfect links; curves of
  val_bce against round and against bytes sent, a table with sigma's wins per seed, and the
  bytes and loss of each compression against float32.
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import sys
import threading
import time
from pathlib import Path

import numpy as np
import yaml

from swarmmap.shared.compression import COMPRESSIONS
from swarmmap.shared.config import DEFAULT_PRESET, PRESETS, STD_MODELS, ConfigError, RunConfig, apply_override, resolve
from swarmmap.shared.overview import load_maps, map_extent, robot_files, show, truth_grid, truth_on
from swarmmap.shared.overview import pyplot as _plt

log = logging.getLogger("experiment")

STRATEGIES = ("uniform-l2", "separate-l2", "separate-kl")
# Rounds per run where an experiment's default differs from its preset's: at demo size a
# BNN round of 7 agents takes about 1.7 s on 2 CPU cores, so 2 seeds x 3 strategies of 300
# rounds take about an hour; the single kl-sweep agent has converged by 400.
EXPERIMENT_ROUNDS = {("demo", "kl-sweep"): 400, ("demo", "regularization"): 300}
SCORE_KEYS = ("nll", "ece", "accuracy", "auroc_error", "auroc_unobserved", "std_observed", "std_unobserved", "std_ratio")


# ----------------------------------------------------------------------------- one run


def read_metrics(run_dir: Path, column: str = "val_bce") -> dict[int, list[tuple[int, float]]]:
    """Per robot, (round, ``column``) in round order from ``metrics.csv``."""
    out: dict[int, dict[int, float]] = {}
    with (run_dir / "metrics.csv").open() as f:
        for row in csv.DictReader(f):
            out.setdefault(int(row["robot"]), {})[int(row["round"])] = float(row[column])
    return {r: sorted(v.items()) for r, v in sorted(out.items())}


def final_val_bce(run_dir: Path) -> dict[int, float]:
    """Each robot's last reported val_bce."""
    return {r: rows[-1][1] for r, rows in read_metrics(run_dir).items()}


def score_run(run_dir: Path, radius_m: float = 0.1) -> dict[int, dict[str, float]]:
    """Uncertainty scores of every robot's maps in a finished bnn run; observed cells are the
    ones within ``radius_m`` of any robot's training point."""
    maps = {r: load_maps(run_dir, r) for r in robot_files(run_dir / "maps", ".npz")}
    maps = {r: m for r, m in maps.items() if "std" in m}  # (a FourierNet's maps have none)
    return dict(zip(maps, score_maps(run_dir, list(maps.values()), radius_m)))


def score_maps(run_dir: Path, maps: list[dict[str, np.ndarray]], radius_m: float = 0.1) -> list[dict[str, float]]:
    """Scores of mean/std maps (``mean``, ``std``, ``resolution``, ``origin``) against the run's
    ground truth, observed cells being those within ``radius_m`` of any robot's training point."""
    from swarmmap.shared.uncertainty import observed_mask, score_map

    grid = truth_grid(run_dir)
    files = sorted((run_dir / "data").glob("robot-*.npz"))
    points = np.concatenate([np.load(f)["points"] for f in files]) if files else np.zeros((0, 2))
    references: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # grid -> truth, observed, known
    scores = []
    for m in maps:
        res, shape, origin = float(m["resolution"]), m["mean"].shape, tuple(m["origin"])
        if (res, shape, origin) not in references:  # every robot's map shares its grid, normally
            truth, known = truth_on(grid, m)
            references[res, shape, origin] = truth, observed_mask(shape, origin, res, points, radius_m), known
        truth, observed, known = references[res, shape, origin]
        scores.append(score_map(m["mean"][known], m["std"][known], truth[known], observed[known]))
    return scores


def model_maps(run_dir: Path, std_of: str = "probability") -> dict[int, dict[str, np.ndarray]]:
    """Each robot's mean and std maps computed anew from its final model (``models/robot-<i>.pt``)
    on the run's map grid with its number of passes; ``std_of="logit"``: the std of the passes'
    logits instead of their probabilities."""
    from swarmmap.shared.bnn import predict_mean_std
    from swarmmap.shared.networks import load_model

    learner = resolve(config_file=run_dir / "config.yaml", environ={}).learner  # the maps' grid and passes
    grid = truth_grid(run_dir)
    res = learner.map_resolution_m or grid.resolution
    pts, (h, w) = grid.centres(res)
    paths = robot_files(run_dir / "models", ".pt")
    if not paths:
        raise FileNotFoundError(f"{run_dir / 'models'}: no robot-<i>.pt (the run did not finish?)")
    maps = {}
    for robot, path in paths.items():
        mean, std = predict_mean_std(load_model(path), pts.astype(np.float32), samples=learner.mc_samples, std_of=std_of)
        maps[robot] = {"mean": mean.reshape(h, w), "std": std.reshape(h, w), "resolution": np.float64(res),
                       "origin": np.asarray(grid.origin)}
    return maps


def ensemble_maps(run_dir: Path) -> dict[str, np.ndarray]:
    """The team's final models as a deep ensemble (the baseline users know): per cell, the mean
    of the models' occupancies and the spread of the mixture, sqrt(mean of each model's
    variance + variance of their means) (a deterministic model's own variance is 0)."""
    members = list(model_maps(run_dir).values())
    means = [m["mean"].astype(np.float64) for m in members]
    mean = np.mean(means, 0)
    std = np.sqrt(np.mean([np.square(m["std"], dtype=np.float64) for m in members], 0) + np.var(means, 0))
    return {"mean": mean, "std": std, "resolution": members[0]["resolution"], "origin": members[0]["origin"],
            "members": np.int64(len(members))}


class Progress:
    """Prints rounds done, current losses and time left of a running experiment every ``every`` s."""

    def __init__(self, total_runs: int, rounds: int, every: float = 15.0):
        self.total_runs, self.rounds, self.every = total_runs, rounds, every
        self.done_runs = 0
        self.t0 = time.monotonic()
        self.label = ""
        self.run_dir: Path | None = None
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def start(self, label: str, run_dir: Path) -> None:
        self.label, self.run_dir, self.run_t0 = label, run_dir, time.monotonic()

    def line(self) -> str | None:
        if self.run_dir is None or not (self.run_dir / "metrics.csv").exists():
            return None
        try:
            rows = read_metrics(self.run_dir)
        except (OSError, ValueError, KeyError):
            return None
        if not rows:
            return None
        done = min(r[-1][0] for r in rows.values())
        loss = float(np.mean([r[-1][1] for r in rows.values()]))
        frac = (self.done_runs + done / self.rounds) / self.total_runs
        elapsed = time.monotonic() - self.t0
        left = f"about {elapsed * (1 - frac) / frac / 60:.1f} min left" if frac > 0.01 else "time left not known yet"
        return (f"[{self.done_runs + 1}/{self.total_runs}] {self.label}: round {done}/{self.rounds}, "
                f"val_bce {loss:.4f}, {elapsed / 60:.1f} min elapsed, {left}")

    def _loop(self) -> None:
        while not self.stop.wait(self.every):
            if (text := self.line()) is not None:
                print(text, flush=True)

    def finished(self) -> None:
        self.done_runs += 1

    def close(self) -> None:
        self.stop.set()


SAME_RUN = ("robots", "seed", "world", "lidar", "learner")  # what makes a finished run reusable


def same_settings(run_dir: Path, cfg: RunConfig) -> bool:
    """Whether ``run_dir`` was run with the same robots, seed, world, sensor and learner settings."""
    try:
        old = yaml.safe_load((run_dir / "config.yaml").read_text())
    except (OSError, yaml.YAMLError):
        return False
    from swarmmap.services.launcher import prepare

    new = prepare(cfg.model_copy(update={"run_dir": run_dir})).model_dump(mode="json")  # as up writes it
    if not isinstance(old, dict):
        return False
    defaults = RunConfig().model_dump(mode="json")

    def as_then(k: str):
        """The run's section ``k``, with the fields added since it ran at their defaults (what it ran with)."""
        value = old.get(k)
        if isinstance(value, dict) and isinstance(new[k], dict):
            return {f: value.get(f, defaults[k].get(f)) for f in new[k]}
        return value

    return all(as_then(k) == new[k] for k in SAME_RUN)


def finished(run_dir: Path) -> bool:
    try:
        return all(r.get("finished") for r in json.loads((run_dir / "summary.json").read_text())["learners"].values())
    except (OSError, ValueError, KeyError):
        return False


def move_aside(path: Path) -> Path:
    """Rename ``path`` to ``<name>.replaced-<time>`` (kept, out of the way); returns the new path."""
    aside = path.with_name(f"{path.name}.replaced-{time.strftime('%Y%m%d-%H%M%S')}")
    path.rename(aside)
    return aside


def run_up(cfg: RunConfig, run_dir: Path, progress: Progress, label: str) -> Path:
    """One ``swarmmap up`` of ``cfg`` into ``run_dir``: reused when it finished with the same
    settings, resumed (from the learners' checkpoints) when it stopped part-way, moved aside
    when it holds other settings."""
    from swarmmap.services.launcher import Launcher

    if run_dir.exists() and same_settings(run_dir, cfg) and finished(run_dir):
        log.info("%s: finished earlier in %s with the same settings, reusing it", label, run_dir)
        progress.finished()
        return run_dir
    if run_dir.exists() and not same_settings(run_dir, cfg):  # keep it, but out of this run's way
        aside = move_aside(run_dir)
        log.warning("%s: %s holds a run with other settings; moved it to %s", label, run_dir, aside)
    progress.start(label, run_dir)
    stop = threading.Event()
    status = Launcher(cfg.model_copy(update={"run_dir": run_dir}), stop).run()
    progress.finished()
    if status != 0:
        raise RuntimeError(f"{label}: swarmmap up failed with status {status}; see {run_dir / 'logs'}")
    return run_dir


# ----------------------------------------------------------------------------- figures


def maps_figure(columns: list[tuple[str, dict[str, np.ndarray]]], path: Path, std_max: float = 0.25) -> None:
    """A row of mean maps over a row of std maps, one column per (title, maps)."""
    plt = _plt()
    n = len(columns)
    fig, axes = plt.subplots(2, n, figsize=(3.2 * n + 0.8, 6.2), squeeze=False, constrained_layout=True)
    for j, (title, maps) in enumerate(columns):
        ext = map_extent(maps)
        show(axes[0, j], maps["mean"], ext, "occupancy")
        axes[0, j].set_title(title, fontsize=9)
        im = show(axes[1, j], maps["std"], ext, "std", std_max)
        for ax in axes[:, j]:
            ax.set_xticks([])
            ax.set_yticks([])
    axes[0, 0].set_ylabel("mean")
    axes[1, 0].set_ylabel("standard deviation")
    fig.colorbar(im, ax=axes[1, :].tolist(), shrink=0.8, label="std of occupancy")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def reliability_figure(diagrams: list[tuple[str, dict[str, list]]], path: Path) -> None:
    """Reliability diagrams (predicted occupancy against true frequency, one line per map) over
    the diagonal of perfect calibration, with the cells per bin below."""
    plt = _plt()
    fig, (ax, bars) = plt.subplots(2, 1, figsize=(5.2, 6.2), height_ratios=[3, 1], sharex=True, constrained_layout=True)
    ax.plot([0, 1], [0, 1], color="gray", lw=1, ls="--", label="calibrated")
    width = 1.0 / max(len(diagrams[0][1]["cells"]), 1) if diagrams else 0.1
    for k, (label, rel) in enumerate(diagrams):
        pts = [(p, f) for p, f in zip(rel["predicted"], rel["frequency"]) if p is not None]
        if pts:
            ax.plot(*zip(*pts), marker="o", ms=3, label=label)
        centres = (np.arange(len(rel["cells"])) + 0.5) * width
        bars.bar(centres + (k - len(diagrams) / 2) * width / max(len(diagrams), 1), rel["cells"],
                 width=width / max(len(diagrams), 1), label=label)
    ax.set_ylabel("true frequency of occupied cells")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    bars.set_yscale("log")
    bars.set_xlabel("predicted occupancy (mean map)")
    bars.set_ylabel("cells")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def stack_curves(runs: list[dict[int, list[tuple[int, float]]]]) -> tuple[np.ndarray, np.ndarray]:
    """Rounds common to every agent of every run, and the (agents x runs, rounds) losses."""
    series = [dict(rows) for run in runs for rows in run.values()]
    if not series:
        return np.zeros(0), np.zeros((0, 0))
    rounds = sorted(set.intersection(*(set(s) for s in series)))
    return np.array(rounds), np.array([[s[k] for k in rounds] for s in series])


def json_ready(x):
    """``x`` with every NaN float as None (JSON has no NaN)."""
    if isinstance(x, dict):
        return {k: json_ready(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_ready(v) for v in x]
    return None if isinstance(x, float) and x != x else x


def write_csv(path: Path, header: list[str], rows: list[list]) -> None:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def fmt(x: float, digits: int = 4) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def scores_table(rows: list[tuple[str, dict[str, float]]]) -> list[str]:
    lines = ["| run | " + " | ".join(SCORE_KEYS) + " |", "| --- |" + " --- |" * len(SCORE_KEYS)]
    lines += [f"| {name} | " + " | ".join(fmt(s[k]) for k in SCORE_KEYS) + " |" for name, s in rows]
    return lines


def mean_scores(per_robot: dict[int, dict[str, float]]) -> dict[str, float]:
    return {k: float(np.nanmean([s[k] for s in per_robot.values()])) for k in SCORE_KEYS}


# ----------------------------------------------------------------------------- experiments


def unseen_text(cfg: RunConfig) -> str:
    """How the run keeps rooms unseen beyond the path, for a report ("" when it does not)."""
    w = cfg.world
    parts = ([f"doors {w.closed_doors} closed"] if w.closed_doors else []) + (
        [f"{w.closed_door_fraction:.0%} of the doors closed"] if w.closed_door_fraction else []) + (
        [f"paths confined to rooms {w.rooms}"] if w.rooms else [])
    return f" ({', '.join(parts)})" if parts else ""


def model_text(cfg: RunConfig) -> str:
    """The run's network and its uncertainty settings, for a report."""
    s = cfg.learner
    if s.model == "bnn":
        return (f"BNN {s.model_shape}, prior sigma {s.prior_sigma:g}, rho init {s.bnn_rho_init:g}"
                f"{', local reparameterisation' if s.bnn_local_reparam else ''}")
    if s.model == "dropout":
        return f"FourierNet {s.model_shape} with MC dropout p {s.dropout_p:g} (kl_weight has no effect)"
    return f"FourierNet {s.model_shape} (deterministic: no std)"


def prior_text(cfg: RunConfig) -> str:
    """The noise-contrastive prior on unseen space, for a report ("" when off)."""
    s = cfg.learner
    if s.model != "bnn" or s.unseen_weight <= 0:
        return ""
    return (f" Noise-contrastive prior on unseen space: weight {s.unseen_weight:g}, margin {s.unseen_margin_m:g} m, "
            f"logit prior std {s.unseen_prior_std:g}{', coverage shared' if s.share_coverage else ''}.")


def base_config(args: argparse.Namespace) -> RunConfig:
    overrides: dict = {"learner": {"model": "bnn", "transport": args.transport}, "up": {"observer": args.observer},
                       "log_level": "warning"}
    rounds = args.rounds or EXPERIMENT_ROUNDS.get((args.preset, args.experiment))
    if rounds:
        overrides["learner"]["rounds"] = rounds
    if getattr(args, "device", None):
        overrides["learner"]["device"] = args.device
    for item in args.set or []:
        apply_override(overrides, item)
    return resolve(overrides, preset=args.preset, environ={})


def kl_sweep(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    base = base_config(args)
    world = base.world.model_copy(update={"rooms_per_robot": args.rooms})
    learner = base.learner.model_copy(update={"algorithm": "individual"})
    base = base.model_copy(update={"robots": 1, "world": world, "learner": learner})
    progress = Progress(len(args.kl_weights), base.learner.rounds)
    columns, rows, scored = [], [], []
    try:
        for kl in args.kl_weights:
            cfg = base.model_copy(update={"learner": base.learner.model_copy(update={"kl_weight": kl})})
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


RegCell = tuple[tuple[int, ...], float, float]  # (model shape, W_rho / W_mu, kl_weight)


def parse_shape(text: str) -> tuple[int, ...]:
    """A model shape from ``2,256,64,64,1`` (or a JSON list)."""
    try:
        shape = tuple(int(x) for x in text.strip("[] ").split(","))
    except ValueError:
        raise ConfigError(f"config error:\n  --shapes: {text!r} is not a list of layer widths like 2,256,64,64,1") from None
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
    shape, ratio, kl = cell
    return f"model {widths(shape)}, W_rho/W_mu {ratio:g}, kl_weight {kl:g}"


def run_key(strategy: str, cell: RegCell) -> tuple:
    """Which run of the grid gives ``strategy`` at ``cell``: uniform-l2 has no W_rho, so one
    run per shape and kl_weight serves every ratio."""
    shape, ratio, kl = cell
    return strategy, shape, None if strategy == "uniform-l2" else ratio, kl


def regularization(args: argparse.Namespace) -> int:
    """The paper's Figures 7 and 8 over a grid (model shapes x W_rho/W_mu x kl_weight x seeds):
    where does Algorithm 2's KL regularisation beat the L2 strategies, and by how much?"""
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    base = base_config(args)
    base = base.model_copy(update={"robots": args.robots})
    strategies = args.strategies
    cells = regularization_cells(args, base)
    grid = len(cells) > 1
    plan: dict[tuple, tuple[str, RegCell]] = {}
    for cell in cells:
        for strategy in strategies:
            plan.setdefault(run_key(strategy, cell), (strategy, cell))
    progress = Progress(len(plan) * len(args.seeds), base.learner.rounds)
    done: dict[tuple, dict[int, tuple[float, dict, dict, Path]]] = {key: {} for key in plan}
    rows = []
    try:
        for seed in args.seeds:
            for key, (strategy, (shape, ratio, kl)) in plan.items():
                learner = base.learner.model_copy(update={
                    "regularization": strategy, "model_shape": list(shape), "kl_weight": kl,
                    "w_rho": base.learner.w_mu * (1.0 if strategy == "uniform-l2" else ratio)})
                cfg = base.model_copy(update={"seed": seed, "learner": learner})
                name = f"{strategy}-seed{seed}" if not grid else (
                    f"{strategy}-{widths(shape)}-kl{kl:g}"
                    + ("" if strategy == "uniform-l2" else f"-wrho{ratio:g}") + f"-seed{seed}")
                run_dir = run_up(cfg, out / "runs" / name, progress, f"{strategy} {cell_label((shape, ratio, kl))} seed {seed}")
                metrics = read_metrics(run_dir)
                final = float(np.mean([rows_[-1][1] for rows_ in metrics.values()]))
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


CONSENSUS = ("dinno", "ramen", "sigma")


def cell_name(consensus: str, link: float, every: int, compression: str) -> str:
    return f"{consensus}-link{link:g}-every{every}-{compression}"


def consensus_cells(args: argparse.Namespace) -> list[tuple[str, float, int, str]]:
    """(consensus, link success, exchange_every, compression) of every run of a seed: the grid of
    consensus x links x exchange intervals uncompressed, then each compression mode over perfect
    links every round for the ``--compression-consensus`` rules."""
    cells = [(c, link, every, "none") for link in args.link_success for every in args.exchange_every for c in args.consensus]
    cells += [(c, 1.0, 1, mode) for mode in args.compression if mode != "none" for c in args.compression_consensus]
    return list(dict.fromkeys(cells))


def consensus(args: argparse.Namespace) -> int:
    """Uncertainty-weighted consensus under poor links and compressed States (issue 13's grid)."""
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    base = base_config(args).model_copy(update={"robots": args.robots})
    cells = consensus_cells(args)
    progress = Progress(len(cells) * len(args.seeds), base.learner.rounds)
    finals: dict[tuple, dict[int, float]] = {}
    sent: dict[tuple, dict[int, float]] = {}
    curves: dict[tuple, list] = {}
    byte_curves: dict[tuple, list] = {}
    scored: dict[tuple, list[dict[str, float]]] = {}
    rows = []
    try:
        for seed in args.seeds:
            for cell in cells:
                cons, link, every, comp = cell
                learner = base.learner.model_copy(update={
                    "consensus": cons, "exchange_every": every, "compression": comp,
                    "round_wait_s": args.round_wait if link < 1 else 0.0})
                faults = base.faults.model_copy(update={"link_success": link, "seed": seed, "per_round": True})
                cfg = base.model_copy(update={"seed": seed, "learner": learner, "faults": faults})
                try:
                    cfg = RunConfig.model_validate(cfg.model_dump())  # the cell's settings, checked together
                except Exception as exc:
                    raise ConfigError(f"{cell_name(*cell)}: {exc}") from None
                run_dir = run_up(cfg, out / "runs" / f"{cell_name(*cell)}-seed{seed}", progress, f"{cell_name(*cell)} seed {seed}")
                metrics, wire = read_metrics(run_dir), read_metrics(run_dir, "bytes_sent")
                final = float(np.mean([m[-1][1] for m in metrics.values()]))
                per_learner = float(np.mean([b[-1][1] for b in wire.values()]))
                finals.setdefault(cell, {})[seed] = final
                sent.setdefault(cell, {})[seed] = per_learner
                curves.setdefault(cell, []).append(metrics)
                byte_curves.setdefault(cell, []).append(wire)
                sc = mean_scores(score_run(run_dir)) if base.learner.model in STD_MODELS else {k: float("nan") for k in SCORE_KEYS}
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
    if base.learner.model in STD_MODELS:
        lines += ["", "Uncertainty scores, mean over agents and seeds:", ""]
        lines += scores_table([(cell_name(*c), {k: float(np.nanmean([x[k] for x in scored[c]])) for k in SCORE_KEYS})
                               for c in cells])
    lines += ["", f"Command: `{' '.join(sys.argv)}`", ""]
    return lines


def score(args: argparse.Namespace) -> int:
    """Print the scores of a finished run's maps and write them, with reliability diagrams, to
    ``--out`` (default RUN_DIR/scores; an earlier scores folder is moved aside, not overwritten)."""
    if args.std_of == "logit":
        if args.ensemble:
            print("--std-of logit scores each robot's model; the ensemble's spread is of probabilities: "
                  "give one of --ensemble and --std-of logit", file=sys.stderr)
            return 2
        maps = model_maps(args.run_dir, "logit")
        per_robot = dict(zip(maps, score_maps(args.run_dir, list(maps.values()), args.radius)))
    else:
        per_robot = score_run(args.run_dir, args.radius)
    ensemble = None
    if args.ensemble:
        maps = ensemble_maps(args.run_dir)
        ensemble = (int(maps["members"]), score_maps(args.run_dir, [maps], args.radius)[0])
    if not per_robot and ensemble is None:
        print(f"{args.run_dir}: no std maps in maps/robot-<i>.npz (only a bnn or dropout run has them; --ensemble scores any "
              f"run's models together)", file=sys.stderr)
        return 2
    vals = final_val_bce(args.run_dir)
    rows = [(f"robot {r} (val_bce {fmt(vals.get(r))})", s) for r, s in per_robot.items()]
    if ensemble is not None:
        rows.append((f"ensemble of {ensemble[0]} robot model(s)", ensemble[1]))
    print("\n".join(scores_table(rows)))
    out = args.out or args.run_dir / "scores"
    if out.exists() and any(out.iterdir()):
        aside = move_aside(out)
        print(f"{out} held earlier scores; moved them to {aside}", file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "scores.csv", ["robot", "final_val_bce", *SCORE_KEYS],
              [[r, vals.get(r), *(s[k] for k in SCORE_KEYS)] for r, s in per_robot.items()]
              + ([["ensemble", None, *(ensemble[1][k] for k in SCORE_KEYS)]] if ensemble else []))
    doc = {"run_dir": str(args.run_dir), "radius_m": args.radius, "std_of": args.std_of,
           "mean": mean_scores(per_robot) if per_robot else None,
           "robots": {str(r): {"final_val_bce": vals.get(r), **s} for r, s in per_robot.items()}}
    if ensemble is not None:
        doc["ensemble"] = {"members": ensemble[0], **ensemble[1]}
    (out / "scores.json").write_text(json.dumps(json_ready(doc), indent=1))
    reliability_figure([(f"robot {r}", s["reliability"]) for r, s in per_robot.items()]
                       + ([("ensemble", ensemble[1]["reliability"])] if ensemble else []), out / "reliability.png")
    print(f"wrote {out / 'scores.csv'}, {out / 'scores.json'} and {out / 'reliability.png'}")
    return 0


def add_parser(sub) -> None:
    """The ``experiment`` subcommand and its three experiments."""
    p = sub.add_parser("experiment", help="The paper's experiments: kl-sweep, regularization; score a run.",
                       description=__doc__.split("\n\n")[0])
    exp = p.add_subparsers(dest="experiment", required=True, metavar="EXPERIMENT")
    for name, text in (("kl-sweep", "One isolated agent, one run per kl_weight (the paper's Figure 6)."),
                       ("regularization", "7 agents, the three regularisation strategies (the paper's Figures 7 and 8)."),
                       ("consensus", "7 agents: consensus rules x link success x exchange interval, and compressed States.")):
        e = exp.add_parser(name, help=text, description=text, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
        e.add_argument("--out", type=Path, required=True, help="directory for the runs, figures, CSV and report.md")
        e.add_argument("--preset", choices=list(PRESETS), default=DEFAULT_PRESET, help="size: smoke, demo, paper (GPU)")
        e.add_argument("--rounds", type=int, default=0,
                       help="rounds per run (0: the preset's; for demo, 400 in kl-sweep and 300 in regularization)")
        e.add_argument("--transport", choices=["inproc", "zenoh"], default="inproc",
                       help="learners in one process (same result, faster) or one process per robot over Zenoh")
        e.add_argument("--observer", action="store_true", help="also record each run in Rerun (RUN_DIR/recording.rrd)")
        e.add_argument("--set", action="append", metavar="KEY=VALUE", help="any config field, e.g. learner.prior_sigma=0.1")
        e.add_argument("--device", default=None, help="torch device of the learners (learner.device): cpu, cuda, cuda:1; "
                                                      "default: the config's (auto: a GPU when there is one)")
        if name == "kl-sweep":
            e.add_argument("--kl-weights", type=float, nargs="+", default=[1e-4, 5e-3, 5e-1], help="kl_weight values")
            e.add_argument("--rooms", type=int, default=2, help="rooms the agent's path visits (the rest stays unseen)")
        else:
            e.add_argument("--robots", type=int, default=7, help="agents")
            e.add_argument("--seeds", type=int, nargs="+", default=[0, 1] if name == "regularization" else [0, 1, 2],
                           help="seeds (plan, paths, initialisation and lost messages)")
        if name == "regularization":
            e.add_argument("--strategies", nargs="+", choices=STRATEGIES, default=list(STRATEGIES), help="strategies to run")
            e.add_argument("--shapes", nargs="+", metavar="SHAPE", default=None,
                           help="model shapes of the grid, e.g. 2,256,64,64,64,1 2,256,256,256,256,256,1 (the paper's); "
                                "default: the preset's")
            e.add_argument("--w-rho", type=float, nargs="+", default=None, metavar="RATIO",
                           help="W_rho / W_mu ratios of the grid (1: separate-l2 equals uniform-l2); default: the config's")
            e.add_argument("--kl-weights", type=float, nargs="+", default=None,
                           help="kl_weight values of the grid; default: the config's")
        if name == "consensus":
            e.add_argument("--consensus", nargs="+", choices=CONSENSUS, default=list(CONSENSUS), help="consensus rules")
            e.add_argument("--link-success", type=float, nargs="+", default=[1.0, 0.3, 0.05],
                           help="probabilities that a message reaches a neighbour")
            e.add_argument("--exchange-every", type=int, nargs="+", default=[1, 10], help="exchange intervals (rounds)")
            e.add_argument("--compression", nargs="+", choices=COMPRESSIONS,
                           default=[c for c in COMPRESSIONS if c != "lowrank"],  # (fails under Adam: README)
                           help="State encodings, each run over perfect links exchanging every round")
            e.add_argument("--compression-consensus", nargs="+", choices=CONSENSUS, default=["dinno"],
                           help="consensus rules the compression runs use")
            e.add_argument("--round-wait", type=float, default=0.3,
                           help="below 100%% link success, the most a round waits for messages (learner.round_wait_s)")
    s = exp.add_parser("score", help="Uncertainty scores of a finished bnn run's maps.",
                       description="Uncertainty scores of a finished bnn run's maps.")
    s.add_argument("run_dir", type=Path, help="the run directory")
    s.add_argument("--radius", type=float, default=0.1, help="cells within this distance (m) of a training point are observed")
    s.add_argument("--ensemble", action="store_true", help="also score the robots' final models as one deep ensemble "
                                                           "(any model: a FourierNet run too)")
    s.add_argument("--std-of", choices=("probability", "logit"), default="probability",
                   help="the spread scored: of the passes' occupancy probabilities (the saved maps), or of their "
                        "logits (maps computed anew from the robots' final models)")
    s.add_argument("--out", type=Path, default=None, help="folder for scores.csv, scores.json, reliability.png "
                                                          "(default RUN_DIR/scores)")


def main(args: argparse.Namespace) -> int:
    try:
        if args.experiment == "kl-sweep":
            return kl_sweep(args)
        if args.experiment == "regularization":
            return regularization(args)
        if args.experiment == "consensus":
            return consensus(args)
        return score(args)
    except ConfigError as exc:
        print(exc.message, file=sys.stderr)
        return 2
    except (RuntimeError, FileNotFoundError) as exc:
        print(f"experiment failed: {exc}", file=sys.stderr)
        return 1
