"""What every experiment shares: its base config, one ``swarmmap up`` per setting (reused when
it finished with the same settings), its progress lines, figures and report text."""

from __future__ import annotations

import argparse
import csv
import logging
import math
import threading
import time
from pathlib import Path

import numpy as np
import yaml

from swarmmap.shared.run.config import ConfigError, RunConfig, apply_override, format_validation_error, resolve
from swarmmap.shared.run.overview import map_extent, show
from swarmmap.shared.run.overview import pyplot as _plt
from swarmmap.shared.run.progress import duration, eta_words, time_left
from swarmmap.shared.run.rundir import read_metrics, read_summary

log = logging.getLogger("experiment")

# Rounds per run where an experiment's default differs from its preset's: at demo size a
# BNN round of 7 agents takes about 1.7 s on 2 CPU cores, so 2 seeds x 3 strategies of 300
# rounds take about an hour; the single kl-sweep agent has converged by 400.
EXPERIMENT_ROUNDS = {("demo", "kl-sweep"): 400, ("demo", "regularization"): 300}


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
        """A run of the experiment begins in ``run_dir``."""
        self.label, self.run_dir, self.run_t0 = label, run_dir, time.monotonic()

    def line(self) -> str | None:
        """The progress line from the current run's metrics.csv, or None before it has any."""
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
        runs_done = self.done_runs + done / self.rounds
        elapsed = time.monotonic() - self.t0
        left = eta_words(time_left(runs_done, self.total_runs, elapsed, at_least=0.01 * self.total_runs))
        return (f"[{self.done_runs + 1}/{self.total_runs}] {self.label}: round {done}/{self.rounds}, "
                f"val_bce {loss:.4f}, {duration(elapsed)} elapsed, {left}")

    def _loop(self) -> None:
        while not self.stop.wait(self.every):
            if (text := self.line()) is not None:
                print(text, flush=True)

    def finished(self) -> None:
        """The current run is done (or was reused)."""
        self.done_runs += 1

    def close(self) -> None:
        """Stop printing."""
        self.stop.set()


SAME_RUN = ("robots", "seed", "world", "lidar", "learner")  # what makes a finished run reusable


def same_settings(run_dir: Path, cfg: RunConfig) -> bool:
    """Whether ``run_dir`` was run with the same robots, seed, world, sensor and learner settings."""
    try:
        old = yaml.safe_load((run_dir / "config.yaml").read_text())
    except (OSError, yaml.YAMLError):
        return False
    from swarmmap.services.up import prepare

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
    """Whether every learner of the run in ``run_dir`` finished (its summary says so)."""
    summary = read_summary(run_dir)
    try:
        return all(r.get("finished") for r in summary["learners"].values())
    except (TypeError, KeyError, AttributeError):
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
    from swarmmap.services.up import Launcher

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
    """``rows`` under ``header`` as a CSV file."""
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def fmt(x: float, digits: int = 4) -> str:
    """A number for a report; n/a for None or NaN."""
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"



# ----------------------------------------------------------------------------- settings and report text


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
    """The experiment's config before its grid: the preset, a BNN, the transport, its --set items."""
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



def checked(cfg: RunConfig, label: str, flags: dict[str, str] | None = None) -> RunConfig:
    """``cfg`` validated as a whole (``model_copy`` does not validate): a setting of the grid
    that the config refuses stops the experiment before anything is created, naming the run
    and, where ``flags`` maps the field to one, the flag that set it."""
    from pydantic import ValidationError

    try:
        return RunConfig.model_validate(cfg.model_dump())
    except ValidationError as exc:
        lines = format_validation_error(exc).splitlines()[1:]
        for path, flag in (flags or {}).items():
            lines = [line.replace(f"  {path}:", f"  {flag} ({path}):", 1) for line in lines]
        raise ConfigError(f"config error in the run {label}:\n" + "\n".join(lines)) from None


def mean_over_agents(metrics: dict[int, list[tuple[int, float]]]) -> float:
    """The final value of each agent's curve, averaged over the agents."""
    return float(np.mean([rows[-1][1] for rows in metrics.values()]))
