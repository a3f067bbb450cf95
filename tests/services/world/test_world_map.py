"""The world's map over Zenoh: a validation set sent as its recipe, drawn by each receiver and
checked against the world's own draw; the points themselves when a receiver's draw differs."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from pydantic import ValidationError

from swarmmap.services.world.simulation import build_plan, map_replies, world_map_message
from swarmmap.shared.run.config import resolve
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.codec import encode
from swarmmap.shared.wire.protocol import Keys, Tensor, ValidationRecipe, WorldMap
from swarmmap.shared.world.sensing import validation_set


@pytest.fixture(scope="module")
def world():
    cfg = resolve({"world": {"val_scans": 40}}, preset="smoke", environ={})
    grid = build_plan(cfg).occupancy(cfg.world.grid_resolution_m)
    w, beams = cfg.world, cfg.labelling()
    points, labels = validation_set(grid, w.val_scans, w.val_beams, w.lidar_max_range_m, beams.samples_per_beam,
                                     cfg.seed, beams.occupied_depth_m)
    return cfg, grid, points, labels


def asked(zenoh_pair, run_id, reply) -> WorldMap | None:
    """What a learner's ``Bus.world`` makes of a world answering ``reply(parameters)``."""
    keys = Keys("swarmmap", run_id)
    with Bus.open(zenoh_pair[0], keys, "world", 0) as world, Bus.open(zenoh_pair[1], keys, "learner", 0) as learner:
        world.serve(keys.world_map(), reply)
        return learner.world(15.0)


@pytest.mark.integration
def test_a_receiver_draws_the_worlds_validation_set_from_a_recipe(zenoh_pair, run_id, world):
    cfg, grid, points, labels = world
    reply = map_replies(cfg.model_copy(update={"run_id": run_id}), grid, None)
    assert len(reply("")) < grid.grid.nbytes + 1024 < len(reply("points"))  # the grid and a few hundred bytes
    got = asked(zenoh_pair, run_id, reply)
    assert got is not None and got.validation is None
    np.testing.assert_array_equal(got.val_points.numpy(), points)
    np.testing.assert_array_equal(got.val_labels.numpy(), labels)


@pytest.mark.integration
def test_a_draw_unlike_the_worlds_asks_for_the_points(zenoh_pair, run_id, world, caplog):
    cfg, grid, points, labels = world
    cfg = cfg.model_copy(update={"run_id": run_id})
    honest = world_map_message(cfg, grid, points=False)
    off = honest.model_copy(update={"validation": honest.validation.model_copy(update={"count": honest.validation.count + 50})})
    asks: list[str] = []

    def reply(parameters: str) -> bytes:
        asks.append(parameters)
        return encode(world_map_message(cfg, grid)) if parameters == "points" else encode(off)

    with caplog.at_level(logging.WARNING):
        got = asked(zenoh_pair, run_id, reply)
    assert asks == ["", "points"]
    assert "differs from the world's" in caplog.text and f"where the world drew {honest.validation.count + 50}" in caplog.text
    np.testing.assert_array_equal(got.val_points.numpy(), points)


def test_a_world_map_carries_one_validation_set():
    base = dict(run="r", sender=0, resolution=0.1, origin=[0.0, 0.0], grid=Tensor.of(np.eye(3, dtype=np.uint8)), robots=2)
    recipe = ValidationRecipe(scans=2, beams=4, max_range=3.5, samples_per_beam=3, seed=1, occupied_depth=0.03,
                              count=10, occupied=2, centroid=[0.0, 0.0])
    points = dict(val_points=Tensor.of(np.zeros((2, 2), np.float32)), val_labels=Tensor.of(np.zeros(2, np.float32)))
    with pytest.raises(ValidationError, match="not both"):
        WorldMap(**base)
    with pytest.raises(ValidationError, match="not both"):
        WorldMap(**base, **points, validation=recipe)
    with pytest.raises(ValidationError, match="more than"):  # a world cannot make its receivers draw without end
        ValidationRecipe.model_validate(recipe.model_dump() | {"scans": 100_000, "beams": 100_000})


@pytest.mark.integration
def test_a_recipe_that_cannot_be_drawn_asks_for_the_points(zenoh_pair, run_id, world, caplog):
    cfg, grid, points, labels = world
    cfg = cfg.model_copy(update={"run_id": run_id})
    honest = world_map_message(cfg, grid, points=False)
    solid = honest.model_copy(update={"grid": Tensor.of(np.ones_like(grid.grid, dtype=np.uint8), "|u1")})  # no free cell

    def reply(parameters: str) -> bytes:
        return encode(world_map_message(cfg, grid)) if parameters == "points" else encode(solid)

    with caplog.at_level(logging.WARNING):
        got = asked(zenoh_pair, run_id, reply)
    assert "it cannot be drawn" in caplog.text and "no free cell" in caplog.text
    np.testing.assert_array_equal(got.val_points.numpy(), points)
