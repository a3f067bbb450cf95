"""Exploration policies from the same starts: team distance to 0.9 coverage, final coverage, val_bce at equal distance.

    python bench/explore.py [--plans procedural cubicasa dinno] [--robots 3 5] [--seed 1] [--out /tmp/bench/explore]

On each plan (a procedural one, the kit's CubiCasa5K plan, DiNNO's floor plan) and team size, one
``swarmmap up`` (Zenoh, a learner process per robot) per policy, every policy from the same starts
(spread over the plan by the seed, given as ``--starts``): ``planned`` (the paths planned before the
run, driven in legs while the learners train), ``frontier`` (nearest frontier of a log-odds grid of
the robot's and its neighbours' scans), ``uncertainty`` with the quickstart's Bayesian network, and
``uncertainty`` with an MC-dropout network (without the prior on unseen space, which shapes a
Bayesian network's weight draws only). Prints per run the team distance at which coverage of
the reachable free space first reached 0.9 (from exploration.csv), the final coverage, the team's
mean val_bce at the team distance where ``planned`` ended its paths (each robot's newest val_bce
in exploration.csv at the first scan where the team had driven that far; a policy whose drive
ended sooner: at its end), the final mean val_bce and the wall time; then one headline line per
plan and team: uncertainty's distance to 0.9 against frontier's, and its val_bce at planned's
distance against planned's. Runs are kept in ``--out`` and reused when their summary is there (an
exploring run is never resumed: an unfinished one is run again).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: its common parts

from common import Runs, up_run  # noqa: E402

from swarmmap.shared.run.config import resolve  # noqa: E402
from swarmmap.shared.run.rundir import run_state  # noqa: E402
from swarmmap.shared.world.explore import read_exploration, spread_starts  # noqa: E402
from swarmmap.shared.world.plans import load_floorplan  # noqa: E402

KIT = Path(__file__).resolve().parents[2] / "shared" / "data"
PLANS = {  # name: (extra up arguments, rounds: enough legs to cover the plan)
    "procedural": (["--set", "world.rooms_x=3", "--set", "world.rooms_y=2"], 200),
    "cubicasa": (["--floorplan", str(KIT / "cubicasa5k" / "353" / "model.svg")], 200),
    "dinno": (["--floorplan", str(KIT / "dinno-floorplan-32" / "floor_img.png")], 300),
}
POLICIES = {  # name: up arguments
    "planned": ["--explore", "planned"],
    "frontier": ["--explore", "frontier"],
    "uncertainty": ["--explore", "uncertainty"],
    "uncertainty-dropout": ["--explore", "uncertainty", "--model", "dropout", "--set", "learner.unseen_weight=0"],
}


def starts_of(plan_args: list[str], robots: int, seed: int) -> str:
    """The starts every policy is given: spread over the plan's free space by the seed."""
    cli: dict = {"robots": robots, "seed": seed}
    if "--floorplan" in plan_args:
        cli["world"] = {"floorplan": plan_args[plan_args.index("--floorplan") + 1]}
    else:
        cli["world"] = {k.split("=")[0].split(".")[1]: int(k.split("=")[1]) for k in plan_args[1::2]}
    cfg = resolve(cli, preset="quickstart", environ={})
    grid = load_floorplan(cfg.world.floorplan, cfg.world, seed).occupancy(cfg.world.grid_resolution_m)
    return ";".join(f"{x:.2f},{y:.2f}" for x, y in spread_starts(grid, robots, seed, clearance=0.3))


def drive_figures(run_dir: Path, at_distance: float | None) -> dict:
    """Distance to 0.9 coverage, the final coverage and the team's mean val_bce at ``at_distance``."""
    rows = read_exploration(run_dir / "exploration.csv")
    driven: dict[int, float] = {}
    bce: dict[int, float] = {}
    at_bce = None
    for row in rows:
        r = int(row["robot"])
        driven[r] = row["distance_m"]
        if not np.isnan(row["val_bce"]):
            bce[r] = row["val_bce"]
        if at_distance is not None and at_bce is None and sum(driven.values()) >= at_distance - 1e-6 and bce:
            at_bce = float(np.mean(list(bce.values())))
    if at_bce is None and bce:
        at_bce = float(np.mean(list(bce.values())))  # (its drive ended sooner: at its end)
    return {"at_bce": at_bce, "team_m": sum(driven.values())}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--plans", nargs="+", default=list(PLANS), choices=list(PLANS))
    p.add_argument("--robots", nargs="+", type=int, default=[3, 5])
    p.add_argument("--policies", nargs="+", default=list(POLICIES), choices=list(POLICIES))
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path("/tmp/bench/explore"))
    a = p.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    runs = Runs(len(a.plans) * len(a.robots) * len(a.policies))
    table = []
    for plan in a.plans:
        plan_args, rounds = PLANS[plan]
        for robots in a.robots:
            starts = starts_of(plan_args, robots, a.seed)
            done: dict[str, dict] = {}
            for policy in a.policies:
                run_dir = a.out / f"{plan}-{robots}-{policy}"
                if run_dir.exists() and run_state(run_dir) != "finished":
                    shutil.rmtree(run_dir)  # (an exploring run is never resumed)
                done[policy] = up_run(run_dir, ["--preset", "quickstart", "--robots", str(robots), "--rounds", str(rounds),
                                                "--seed", str(a.seed), f"--starts={starts}", "--set", "up.observer=false",
                                                *plan_args, *POLICIES[policy]])
                runs.ended(run_dir.name)
            planned_m = done["planned"]["exploration"]["team_distance_m"] if "planned" in done else None
            for policy, summary in done.items():
                ex = summary["exploration"]
                figures = drive_figures(a.out / f"{plan}-{robots}-{policy}", planned_m)
                finals = [v["final_val_bce"] for v in summary["learners"].values()]
                table.append((plan, robots, policy, ex["team_distance_at_coverage"]["0.9"], ex["final_coverage"],
                              ex["team_distance_m"], figures["at_bce"], float(np.mean(finals)), summary["wall_time_s"]))
    print("\n| plan | robots | policy | team m to 0.9 coverage | final coverage | team m | val_bce at planned's team m "
          "| final val_bce | wall s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for plan, robots, policy, to90, cov, team, at_bce, final, wall in table:
        print(f"| {plan} | {robots} | {policy} | {'never' if to90 is None else f'{to90:.1f}'} | {cov:.3f} | {team:.1f} | "
              f"{'-' if at_bce is None else f'{at_bce:.4f}'} | {final:.4f} | {wall:.0f} |")
    print()
    rows = {(plan, robots, policy): (to90, at_bce) for plan, robots, policy, to90, _, _, at_bce, _, _ in table}
    for plan in a.plans:
        for robots in a.robots:
            unc, fr, pl = (rows.get((plan, robots, k)) for k in ("uncertainty", "frontier", "planned"))
            if unc is None or fr is None or pl is None:
                continue
            ratio = "n/a (never reached 0.9)" if unc[0] is None or fr[0] is None else f"{unc[0] / fr[0]:.2f}x frontier's"
            print(f"exploration, {plan} plan, {robots} robots: uncertainty team distance to 0.9 coverage "
                  f"{'never' if unc[0] is None else f'{unc[0]:.1f} m'}, {ratio} "
                  f"({'never' if fr[0] is None else f'{fr[0]:.1f} m'}); val_bce at planned's team distance "
                  f"{unc[1]:.4f} vs planned {pl[1]:.4f} ({unc[1] / pl[1]:.2f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
