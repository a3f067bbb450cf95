"""Plans with unseen space: closed doors and robots confined to chosen rooms."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from shapely.ops import unary_union

from swarmmap.services.world.simulation import robot_paths
from swarmmap.shared.run.config import RunConfig, WorldSettings
from swarmmap.shared.world.floorplan import PlanError
from swarmmap.shared.world.paths import path_length, plan_paths, point_along
from swarmmap.shared.world.plans import load_floorplan
from tests.conftest import KIT_DATA

CUBICASA = KIT_DATA / "cubicasa5k" / "353" / "model.svg"


def along(path: np.ndarray, n: int = 400) -> np.ndarray:
    return np.array([point_along(path, s)[0] for s in np.linspace(0, path_length(path), n)])


def test_a_closed_door_is_wall_and_its_number_is_kept():
    open_plan = load_floorplan("procedural", WorldSettings(rooms_x=3, rooms_y=3), seed=4)
    door = open_plan.doors[2].centroid
    closed = load_floorplan("procedural", WorldSettings(rooms_x=3, rooms_y=3, closed_doors=[2]), seed=4)
    assert closed.closed == [2] and len(closed.doors) == len(open_plan.doors) - 1
    grid_open, grid_closed = open_plan.occupancy(0.05), closed.occupancy(0.05)
    assert not grid_open.occupied(np.array([[door.x, door.y]]))[0]
    assert grid_closed.occupied(np.array([[door.x, door.y]]))[0]
    assert closed.mesh(2.5).is_watertight
    with pytest.raises(PlanError, match=r"door\(s\) \[99\] do not exist"):
        load_floorplan("procedural", WorldSettings(closed_doors=[99]), seed=4)


def test_closing_a_share_of_the_doors_is_seeded_and_leaves_rooms_unreachable():
    settings = WorldSettings(rooms_x=3, rooms_y=3, closed_door_fraction=0.5)
    a, b = (load_floorplan("procedural", settings, seed=s) for s in (1, 1))
    assert a.closed == b.closed and len(a.closed) >= 2  # the same seed closes the same doors
    assert any(load_floorplan("procedural", settings, seed=s).closed != a.closed for s in (2, 3, 4))  # another, others
    cfg = RunConfig(robots=3, world=settings)
    grid = a.occupancy(0.05)
    paths = robot_paths(cfg, a, grid)
    driven = unary_union([shapely.LineString(p).buffer(0.05) for p in paths if len(p) > 1])
    unseen = [r for r in a.rooms if not driven.intersects(r.buffer(-0.3))]
    assert unseen, "with half the doors closed some rooms should be out of reach"


def test_robots_confined_to_chosen_rooms_never_enter_the_others():
    plan = load_floorplan("procedural", WorldSettings(rooms_x=3, rooms_y=3), seed=0)
    corridor = plan.room_names.index("corridor")
    chosen = [corridor, plan.room_names.index("room-0-0"), plan.room_names.index("room-0-2")]
    paths = plan_paths(plan, plan.occupancy(0.05), robots=2, seed=0, rooms=chosen)
    allowed = unary_union([plan.rooms[r] for r in chosen] + plan.doors).buffer(0.1)
    for path in paths:
        pts = along(path)
        assert shapely.contains_xy(allowed, pts[:, 0], pts[:, 1]).all()
    with pytest.raises(PlanError, match=r"room\(s\) \[42\] do not exist"):
        plan_paths(plan, plan.occupancy(0.05), robots=2, seed=0, rooms=[42])


def test_every_door_closed_leaves_no_path_and_says_so():
    cfg = RunConfig(robots=2, world=WorldSettings(rooms_x=2, rooms_y=1, corridor_width_m=0, closed_door_fraction=1.0))
    plan = load_floorplan("procedural", cfg.world, seed=0)
    assert not plan.doors
    with pytest.raises(PlanError, match="no usable path"):
        robot_paths(cfg, plan, plan.occupancy(0.05))


@pytest.mark.skipif(not CUBICASA.exists(), reason="kit data ../shared/data/cubicasa5k not present")
def test_cubicasa_doors_close_too():
    plan = load_floorplan(str(CUBICASA), WorldSettings(closed_door_fraction=1.0), seed=0)
    assert len(plan.closed) == 12 and not plan.doors
    assert plan.mesh(2.5).is_watertight
