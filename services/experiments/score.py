"""``swarmmap experiment score RUN_DIR``: the uncertainty scores of a finished run's maps (NLL,
ECE, AUROC of the std for the map's errors and for unobserved cells, mean std over observed and
never-observed cells; :mod:`swarmmap.shared.learning.uncertainty`), with reliability diagrams; and the
scoring every experiment's report uses."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from swarmmap.services.experiments.common import fmt, json_ready, move_aside, reliability_figure, write_csv
from swarmmap.shared.run.config import resolve
from swarmmap.shared.run.overview import load_maps, robot_files, truth_grid, truth_on
from swarmmap.shared.run.rundir import final_val_bce

SCORE_KEYS = ("nll", "ece", "accuracy", "auroc_error", "auroc_unobserved", "std_observed", "std_unobserved", "std_ratio")


def score_run(run_dir: Path, radius_m: float = 0.1) -> dict[int, dict[str, float]]:
    """Uncertainty scores of every robot's maps in a finished bnn run; observed cells are the
    ones within ``radius_m`` of any robot's training point."""
    maps = {r: load_maps(run_dir, r) for r in robot_files(run_dir / "maps", ".npz")}
    maps = {r: m for r, m in maps.items() if "std" in m}  # (a FourierNet's maps have none)
    return dict(zip(maps, score_maps(run_dir, list(maps.values()), radius_m)))


def score_maps(run_dir: Path, maps: list[dict[str, np.ndarray]], radius_m: float = 0.1) -> list[dict[str, float]]:
    """Scores of mean/std maps (``mean``, ``std``, ``resolution``, ``origin``) against the run's
    ground truth, observed cells being those within ``radius_m`` of any robot's training point."""
    from swarmmap.shared.learning.uncertainty import observed_mask, score_map

    grid = truth_grid(run_dir)
    files = sorted((run_dir / "data").glob("robot-*.npz"))
    points = np.concatenate([np.load(f)["points"] for f in files]) if files else np.zeros((0, 2))
    with np.load(run_dir / "groundtruth.npz") as gt:
        if "reference" in gt.files:  # a dataset: no ground truth, the held-out beams are scored
            return [held_out_scores(m, gt["val_points"], gt["val_labels"], points, radius_m) for m in maps]
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


def held_out_scores(maps: dict[str, np.ndarray], val_points: np.ndarray, val_labels: np.ndarray, points: np.ndarray,
                    radius_m: float) -> dict[str, float]:
    """Scores of a map on a dataset's held-out beams: its mean and std at each validation point's
    cell against the point's label (a run on real logs has no ground-truth grid)."""
    from swarmmap.shared.learning.uncertainty import observed_mask, score_map
    from swarmmap.shared.world.grid import OccupancyGrid

    res, shape, origin = float(maps["resolution"]), maps["mean"].shape, tuple(maps["origin"])
    rows, cols, inside = OccupancyGrid(np.zeros(shape, np.uint8), res, origin).cells(val_points)
    observed = observed_mask(shape, origin, res, points, radius_m)
    keep = inside
    r, c = rows[keep], cols[keep]
    return score_map(maps["mean"][r, c], maps["std"][r, c], val_labels[keep] > 0.5, observed[r, c])


def reference_row(run_dir: Path) -> dict[str, float] | None:
    """The log-odds grid's scores on a dataset's held-out beams (no std: those scores are NaN),
    or None for a run with a ground truth."""
    from swarmmap.shared.learning.uncertainty import score_map

    with np.load(run_dir / "groundtruth.npz") as gt:
        if "reference" not in gt.files:
            return None
        maps = {"mean": gt["reference"], "resolution": gt["resolution"], "origin": gt["origin"]}
        points, labels = gt["val_points"], gt["val_labels"]
    from swarmmap.shared.world.grid import OccupancyGrid

    rows, cols, inside = OccupancyGrid(np.zeros(maps["mean"].shape, np.uint8), float(maps["resolution"]),
                                       tuple(maps["origin"])).cells(points)
    mean = np.where(inside, maps["mean"][rows, cols], 0.5)
    out = score_map(mean, np.zeros_like(mean), labels > 0.5, np.ones(len(mean), bool))
    return out | {k: float("nan") for k in ("auroc_error", "auroc_unobserved", "std_observed", "std_unobserved", "std_ratio")}


def model_maps(run_dir: Path, std_of: str = "probability") -> dict[int, dict[str, np.ndarray]]:
    """Each robot's mean and std maps computed anew from its final model (``models/robot-<i>.pt``)
    on the run's map grid with its number of passes; ``std_of="logit"``: the std of the passes'
    logits instead of their probabilities."""
    from swarmmap.shared.learning.bnn import predict_mean_std
    from swarmmap.shared.learning.networks import load_model

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


def scores_table(rows: list[tuple[str, dict[str, float]]]) -> list[str]:
    """A Markdown table of (name, scores) rows."""
    lines = ["| run | " + " | ".join(SCORE_KEYS) + " |", "| --- |" + " --- |" * len(SCORE_KEYS)]
    lines += [f"| {name} | " + " | ".join(fmt(s[k]) for k in SCORE_KEYS) + " |" for name, s in rows]
    return lines


def mean_scores(per_robot: dict[int, dict[str, float]]) -> dict[str, float]:
    """Each score's mean over the robots (NaNs left out)."""
    return {k: float(np.nanmean([s[k] for s in per_robot.values()])) for k in SCORE_KEYS}



def run_dir_problem(run_dir: Path) -> str | None:
    """Why ``run_dir`` cannot be scored (not a folder, no ground truth), or None."""
    if not run_dir.exists():
        return f"{run_dir} does not exist"
    if not run_dir.is_dir():
        return f"{run_dir} is a file, not a run directory (give the folder that holds config.yaml and groundtruth.npz)"
    if not (run_dir / "groundtruth.npz").is_file():
        return f"{run_dir} holds no groundtruth.npz: not a run directory, or a run that never got its map"
    return None


def score(args: argparse.Namespace) -> int:
    """Print the scores of a finished run's maps and write them, with reliability diagrams, to
    ``--out`` (default RUN_DIR/scores; an earlier scores folder is moved aside, not overwritten)."""
    if (why := run_dir_problem(args.run_dir)) is not None:
        print(f"experiment score: {why}", file=sys.stderr)
        return 2
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
    if (reference := reference_row(args.run_dir)) is not None:
        rows.append(("log-odds grid of the training scans (held-out beams)", reference))
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
    if reference is not None:
        doc["reference"] = {"kind": "log-odds grid of the training scans", **reference}
    (out / "scores.json").write_text(json.dumps(json_ready(doc), indent=1))
    reliability_figure([(f"robot {r}", s["reliability"]) for r, s in per_robot.items()]
                       + ([("ensemble", ensemble[1]["reliability"])] if ensemble else []), out / "reliability.png")
    print(f"wrote {out / 'scores.csv'}, {out / 'scores.json'} and {out / 'reliability.png'}")
    return 0


