"""Exploration's parts on a real procedural plan: team coverage judged on the ground truth, the
frontier and uncertainty policies' goals, teammates' goals passed over, and a team of kinematic
robots that covers a building by each policy."""

from __future__ import annotations

import numpy as np
import pytest

from swarmmap.shared.world.explore import (
    Claims,
    Sensor,
    TeamCoverage,
    distance_at,
    frontier_goal,
    parse_starts,
    seen_cells,
    spread_starts,
    uncertainty_goal,
)
from swarmmap.shared.world.floorplan import procedural
from swarmmap.shared.world.logodds import build_logodds
from swarmmap.shared.world.paths import path_length, point_along
from swarmmap.shared.world.sensing import beam_angles, raycast_grid

SENSOR = Sensor(beams=72, max_range=3.5)


@pytest.fixture(scope="module")
def truth():
    return procedural(2, 2, seed=4).occupancy(0.1)


def scan(truth, xy):
    angles = beam_angles(SENSOR.beams)
    ranges, hit = raycast_grid(truth, np.asarray(xy, np.float64)[None], angles[None], SENSOR.max_range)
    return angles, ranges[0], hit[0]


def test_coverage_grows_with_scans_and_counts_only_the_reachable_free_space(truth):
    start = spread_starts(truth, 1, seed=0)
    cov = TeamCoverage(truth, start)
    assert 0 < cov.total < (truth.grid == 0).sum() + 1
    assert cov.fraction() == 0.0
    angles, ranges, _ = scan(truth, start[0])
    cov.add_scan(start[0], angles, ranges)
    first = cov.fraction()
    assert 0.02 < first < 0.6
    rows, cols = np.nonzero(cov.seen)
    xy = np.stack([truth.origin[0] + (cols + 0.5) * 0.1, truth.origin[1] + (rows + 0.5) * 0.1], axis=1)
    assert np.linalg.norm(xy - start[0], axis=1).max() <= SENSOR.max_range + 0.1
    cov.add_scan(start[0], angles, ranges)
    assert cov.fraction() == first, "the same scan twice sees nothing new"


def test_spread_starts_are_clear_and_apart_and_parse_starts_refuses_nonsense(truth):
    starts = spread_starts(truth, 3, seed=1)
    assert (truth.clearance()[truth.cells(starts)[:2]] >= 0.3).all()
    assert min(np.linalg.norm(starts[i] - starts[j]) for i in range(3) for j in range(i)) > 2.0
    assert (spread_starts(truth, 3, seed=1) == starts).all()
    assert parse_starts("1,2; 3.5,4", 2) == [(1, 2), (3.5, 4)]
    for bad, why in [("1,2", "1 start"), ("1,2;x,4", "no \"x,y\" pair"), ("1,2;nan,4", "not finite")]:
        with pytest.raises(ValueError, match=why):
            parse_starts(bad, 2)


def test_seen_cells_stop_at_the_first_wall():
    occupied = np.zeros((20, 20), bool)
    occupied[:, 10] = True  # a wall at x in [1.0, 1.1)
    cells = seen_cells(occupied, (0.0, 0.0), 0.1, np.array([[0.55, 1.05]]), Sensor(beams=36, max_range=3.0))[0]
    cols = np.flatnonzero(cells) % 20
    assert cols.max() == 10 and cells.reshape(20, 20)[:, 10].any(), "the wall's own cell is seen, nothing behind it"


def test_the_frontier_goal_lies_where_known_space_ends_and_a_teammates_goal_is_passed_over(truth):
    start = spread_starts(truth, 1, seed=0)[0]
    angles, ranges, hit = scan(truth, start)
    grid = build_logodds(truth.grid.shape, truth.origin, truth.resolution, start[None], angles[None], ranges[None], hit[None])
    goal = frontier_goal(0, start, grid, Claims())
    assert goal is not None and len(goal.path) >= 2
    assert not truth.occupied(goal.path).any() and not truth.occupied(np.array([goal.xy])).any()
    r, c, _ = truth.cells(np.array([goal.xy]))
    near = grid.known()[max(0, r[0] - 4) : r[0] + 5, max(0, c[0] - 4) : c[0] + 5]
    assert not near.all(), "a frontier goal lies next to space no beam reached"
    other = frontier_goal(0, start, grid, Claims({1: goal.xy}, separation=1.0))
    assert other is not None and np.linalg.norm(np.subtract(other.xy, goal.xy)) > 1.0


def test_the_uncertainty_goal_goes_where_the_model_is_unsure(truth):
    """A model sure of the west half and unsure of the east half (std 0.5 there) sends the robot
    east, on a path that stays in believed free space; a teammate's goal is passed over."""
    mean = np.where(truth.grid == 1, 0.95, 0.05).astype(np.float32)
    std = np.zeros_like(mean)
    x = truth.origin[0] + (np.arange(truth.grid.shape[1]) + 0.5) * truth.resolution
    mid = (x.min() + x.max()) / 2
    std[:, x > mid] = 0.5
    start = spread_starts(truth, 1, seed=0)[0]
    goal = uncertainty_goal(0, start, mean, std, truth.origin, truth.resolution, Claims(), sensor=SENSOR)
    assert goal is not None and goal.xy[0] > mid - SENSOR.max_range / 2
    assert not truth.occupied(goal.path).any()
    other = uncertainty_goal(0, start, mean, std, truth.origin, truth.resolution, Claims({3: goal.xy}), sensor=SENSOR)
    assert other is not None and np.linalg.norm(np.subtract(other.xy, goal.xy)) > 1.5
    flat = uncertainty_goal(0, start, mean, None, truth.origin, truth.resolution, Claims(), sensor=SENSOR, kind="entropy")
    assert flat is not None  # (no std: the entropy of the mean)


def explore(truth, policy: str, robots: int, seed: int, budget_m: float = 60.0, step: float = 0.25):
    """Kinematic robots on the ground truth: each drives its path in steps, scanning at each,
    and asks ``policy`` for a new goal when it arrives (or none is left). Returns the coverage
    and the team's distance after each step, and whether any robot stood in a wall."""
    starts = spread_starts(truth, robots, seed)
    cov = TeamCoverage(truth, starts)
    poses, angles = list(starts), beam_angles(SENSOR.beams)
    scans: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    paths: list[np.ndarray | None] = [None] * robots
    done, driven, claims = [False] * robots, [0.0] * robots, Claims()
    history, in_wall = [], False

    def look(i):
        _, ranges, hit = scan(truth, poses[i])
        scans.append((poses[i].copy(), ranges, hit))
        cov.add_scan(poses[i], angles, ranges)

    for i in range(robots):
        look(i)
    while not all(done) and sum(driven) < budget_m * robots:
        for i in range(robots):
            if done[i]:
                continue
            if paths[i] is None:
                pos = np.array([s[0] for s in scans])
                grid = build_logodds(truth.grid.shape, truth.origin, truth.resolution, pos, np.tile(angles, (len(pos), 1)),
                                     np.array([s[1] for s in scans]), np.array([s[2] for s in scans]))
                if policy == "frontier":
                    goal = frontier_goal(i, poses[i], grid, claims)
                else:
                    # (a model's stand-in: the log-odds grid's belief, unsure where no beam reached)
                    std = np.where(grid.known(), 0.0, 0.5).astype(np.float32)
                    goal = uncertainty_goal(i, poses[i], grid.probability(), std, truth.origin, truth.resolution, claims,
                                            sensor=SENSOR, min_gain=2.0)
                if goal is None:
                    done[i] = True
                    claims.held.pop(i, None)
                    continue
                claims.held[i], paths[i] = goal.xy, goal.path
            length = path_length(paths[i])
            nxt, _ = point_along(paths[i], min(step, length))
            driven[i] += float(np.linalg.norm(nxt - poses[i]))
            poses[i] = nxt
            in_wall |= bool(truth.occupied(poses[i][None]).any())
            look(i)
            paths[i] = None if length <= step else np.vstack([nxt[None], rest_of(paths[i], step)])
        history.append((cov.fraction(), sum(driven)))
    return history, in_wall


def rest_of(path: np.ndarray, s: float) -> np.ndarray:
    """The waypoints of ``path`` beyond arc length ``s``."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    return path[1:][np.cumsum(seg) > s]


@pytest.mark.parametrize("policy", ["frontier", "uncertainty"])
def test_a_team_of_three_covers_the_building_by_either_policy(truth, policy):
    history, in_wall = explore(truth, policy, robots=3, seed=2)
    coverage, distance = np.array(history).T
    assert not in_wall
    assert coverage[-1] >= 0.9, f"{policy}: coverage {coverage[-1]:.2f} after {distance[-1]:.0f} m"
    assert (np.diff(coverage) >= 0).all()
    reached = distance_at(coverage, distance)
    assert reached["0.5"] is not None and reached["0.5"] <= reached["0.9"]


def test_the_exploration_log_appends_survives_a_torn_line_and_sums_up(tmp_path):
    from swarmmap.shared.world.explore import RowLog, exploration_summary, read_exploration

    path = tmp_path / "exploration.csv"
    log = RowLog(path)
    log.row(0, 0.0, 1.0, 2.0, 0.0, 0.10, None)
    log.row(1, 0.0, 5.0, 2.0, 0.0, 0.20, 0.7)
    log.close()
    log = RowLog(path)  # (a resumed run appends)
    log.row(0, 1.0, 2.0, 2.0, 1.0, 0.55, 0.5)
    log.row(1, 1.0, 5.0, 4.0, 2.0, 0.85, 0.4)
    log.close()
    with path.open("a") as f:
        f.write("0,2.0,3.0")  # a crash mid-row
    rows = read_exploration(path)
    assert len(rows) == 4 and np.isnan(rows[0]["val_bce"]) and rows[3]["val_bce"] == 0.4
    s = exploration_summary(rows, "frontier")
    assert s["robot_distance_m"] == {"0": 1.0, "1": 2.0} and s["team_distance_m"] == 3.0
    assert s["final_coverage"] == 0.85
    assert s["team_distance_at_coverage"] == {"0.5": 1.0, "0.8": 3.0, "0.9": None, "0.95": None}
    assert path.read_text().count("robot,sim_time_s") == 1


def test_a_drive_follows_its_path_and_stops_before_a_wall_its_map_missed():
    from swarmmap.shared.world.explore import Drive

    d = Drive(np.array([0.0, 0.0]), speed=0.5)
    d.follow(np.array([[1.0, 0.0], [1.0, 1.0]]))
    d.step(1.0, np.zeros((0, 2)))
    assert np.allclose(d.pose, [0.5, 0.0]) and d.driven == pytest.approx(0.5)
    d.step(3.0, np.zeros((0, 2)))  # (1.5 m left, 1.5 m of drive: it arrives)
    assert d.arrived and np.allclose(d.pose, [1.0, 1.0]) and d.driven == pytest.approx(2.0)
    d.follow(np.array([[3.0, 1.0]]))
    wall = np.stack([np.full(11, 1.4), np.linspace(0.5, 1.5, 11)], axis=1)  # a wall 0.4 m ahead, across the path
    d.step(1.0, wall)
    assert d.blocked and np.allclose(d.pose, [1.0, 1.0]), "it stops rather than drive into the wall"
    d.step(1.0, wall)
    assert np.allclose(d.pose, [1.0, 1.0]) and d.driven == pytest.approx(2.0)


def test_a_log_odds_grid_of_two_batches_of_scans_is_the_sum_of_theirs():
    """The frontier policy keeps counts, not scans: the grid of scans A and B is A's plus B's."""
    from swarmmap.shared.world.logodds import build_logodds

    rng = np.random.default_rng(3)
    pos, ang = rng.uniform(1, 3, (6, 2)), rng.uniform(-np.pi, np.pi, (6, 40))
    rng_, hit = rng.uniform(0.2, 2.0, (6, 40)), rng.uniform(size=(6, 40)) < 0.7
    grid = lambda s: build_logodds((40, 40), (0.0, 0.0), 0.1, pos[s], ang[s], rng_[s], hit[s])  # noqa: E731
    both, summed = grid(slice(None)), grid(slice(0, 2)).plus(grid(slice(2, 6)))
    assert (both.hits == summed.hits).all() and (both.misses == summed.misses).all()
    assert np.array_equal(both.logodds, summed.logodds) and both.known().any()
