"""The world's drive of an exploring team, on a real pybullet world: legs tied to the goals that
come, a robot that never enters a wall (its LiDAR stops it, its body would touch one), the last
scan of each leg and of each robot's drive said, and exploration.csv consistent with the poses."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from swarmmap.services.world.exploring import BODY_RADIUS_M, Exploration, Goals, LatestBce, explore_starts
from swarmmap.services.world.simulation import Simulation, build_plan
from swarmmap.shared.run.config import resolve
from swarmmap.shared.wire.protocol import Goal, Tensor
from swarmmap.shared.world.explore import read_exploration


def goal(robot: int, leg: int, path=None, done: bool = False) -> Goal:
    return Goal(run="r", sender=robot, leg=leg, round=10 * leg, x=0.0, y=0.0, done=done,
                path=None if path is None else Tensor.of(np.asarray(path, np.float32)))


@pytest.fixture()
def drive(tmp_path):
    cfg = resolve({"run_id": "r", "run_dir": str(tmp_path), "robots": 2, "learner": {"rounds": 31},
                   "explore": {"policy": "frontier", "leg_s": 4.0, "distance_m": 3.0, "goal_wait_s": 0.5, "starts": "1,1;1,3.2"}},
                  preset="quickstart", environ={})
    plan = build_plan(cfg)
    grid = plan.occupancy(cfg.world.grid_resolution_m)
    starts = explore_starts(cfg, grid, None)
    sim = Simulation(plan, [s[None] for s in starts], cfg.world)
    sent: list[tuple] = []
    goals = Goals(cfg.legs())
    ex = Exploration(cfg, sim, grid, starts, None, goals, LatestBce(), lambda *scan: sent.append(scan))
    yield cfg, grid, goals, ex, sent
    sim.close()


def test_robots_drive_their_goals_legs_stop_short_of_walls_and_end_on_their_budget(drive):
    cfg, grid, goals, ex, sent = drive
    west = grid.origin[0]  # robot 0 is sent straight through the building's west wall, robot 1 to and fro
    goals.add(goal(0, 1, [[1.0, 1.0], [west - 1.0, 1.0]]))
    goals.add(goal(1, 1, [[1.0, 3.2], [2.0, 3.2]]))  # (along the corridor)
    goals.add(goal(1, 2, [[2.0, 3.2], [1.0, 3.2], [2.0, 3.2], [1.0, 3.2]]))  # (3 m: its budget ends it 2 m in)
    goals.add(goal(0, 2, done=True))  # robot 0's policy has nowhere left to go
    ex.run(threading.Event())
    by_robot = {i: [s for s in sent if s[0] == i] for i in range(2)}
    assert [s[5:] for s in by_robot[0][:1]] == [(0, True, False)]  # leg 0: one scan from the start, the leg's end
    legs = [s[5] for s in by_robot[1]]
    assert legs == sorted(legs) and set(legs) == {0, 1, 2}  # robot 1 drove two legs, then spent its 3 m (leg 3 never)
    assert by_robot[1][-1][6:] == (True, True) and sum(s[7] for s in sent) == 2  # each robot's drive ends once
    assert by_robot[0][-1][5:] == (2, True, True)  # robot 0: its done goal ends it with leg 2
    assert sum(s[6] for s in by_robot[1]) == 3  # each leg's last scan said so
    rows = read_exploration(cfg.run_dir / "exploration.csv")
    assert len(rows) == len(sent)
    clear = grid.clearance()
    for robot in (0, 1):
        xy = np.array([(r["x"], r["y"]) for r in rows if r["robot"] == robot])
        r, c, inside = grid.cells(xy)
        assert inside.all() and (clear[r, c] >= BODY_RADIUS_M).all(), "a robot inside or against a wall"
        steps = np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()
        assert steps == pytest.approx([r["distance_m"] for r in rows if r["robot"] == robot][-1], abs=1e-3)
    assert xy[0] == pytest.approx([1.0, 3.2]) and ex.drives[1].driven == pytest.approx(3.0, abs=1e-6)
    assert ex.drives[0].driven < 1.0 - west  # stopped short of the wall (by what its LiDAR showed, or by the wall itself)
    assert ex.why[1].startswith("distance budget") and "nowhere left" in ex.why[0]


def test_a_robot_whose_goal_never_comes_stays_where_it_is_and_the_team_goes_on(drive):
    cfg, grid, goals, ex, sent = drive
    for leg in (1, 2, 3):
        goals.add(goal(1, leg, [[1.0, 3.2], [1.5, 3.2]] if leg % 2 else [[1.5, 3.2], [1.0, 3.2]]))
    ex.run(threading.Event())
    zero = np.array([s[1][:2] for s in sent if s[0] == 0])
    assert np.ptp(zero, axis=0).max() < 1e-9 and 0 in ex.missed  # robot 0 never moved
    assert ex.drives[1].driven == pytest.approx(1.5, abs=1e-6)
    assert ex.why[0].startswith("the learners' last leg") and max(s[5] for s in sent) == 3  # legs 1..(31 - 1) // 10


def test_a_beam_ends_at_the_ground_truths_solid_space_not_only_at_walls():
    """A plan's outside is solid in its ground truth: a beam out of an exterior door ends there
    (the robots could never reach what it would have seen); a beam that hits a wall keeps its range."""
    from swarmmap.services.world.exploring import solid_truth
    from swarmmap.shared.world.grid import OccupancyGrid

    grid = np.zeros((40, 40), np.uint8)  # 2 m x 2 m at 0.05 m, solid beyond x = 1.5 m
    grid[:, 30:] = 1
    truth = OccupancyGrid(grid, 0.05, (0.0, 0.0))
    poses = np.array([[0.5, 1.0, 0.0]])
    angles = np.array([[0.0, np.pi]])  # east: out of the door into the solid outside; west: a wall 0.5 m away
    ranges, hit = np.array([[3.5, 0.5]]), np.array([[False, True]])
    _, r, h = solid_truth(truth, poses, angles, ranges, hit)
    assert r[0, 0] == pytest.approx(1.0, abs=0.03) and h[0, 0]
    assert r[0, 1] == 0.5 and h[0, 1]
