"""The regularisation experiment's grid: shapes as users type them, and the cells it runs."""

from __future__ import annotations

import argparse

import pytest

from swarmmap.services.experiments.regularization import parse_shape, regularization_cells
from swarmmap.shared.run.config import ConfigError, resolve


def test_shapes_parse_as_typed_and_nonsense_is_refused_naming_the_flag():
    assert parse_shape("2,256,256,256,256,256,1") == (2, 256, 256, 256, 256, 256, 1)
    assert parse_shape("[2, 128, 64, 1]") == (2, 128, 64, 1)
    for bad in ("2,abc,1", "3,64,64,1", "2,64,64,2", "2,64,1", "2,0,64,1"):
        with pytest.raises(ConfigError, match="--shapes"):
            parse_shape(bad)


@pytest.mark.integration
def test_the_grid_is_every_shape_ratio_and_weight_with_the_configs_where_not_given():
    base = resolve({"learner": {"model": "bnn", "w_rho": 2.0, "w_mu": 1.0, "kl_weight": 0.01}}, preset="smoke")
    args = argparse.Namespace(shapes=None, w_rho=None, kl_weights=None)
    assert regularization_cells(args, base) == [(tuple(base.learner.model_shape), 2.0, 0.01)]
    args = argparse.Namespace(shapes=["2,64,32,1", "2,64,32,1", "2,128,64,64,1"], w_rho=[1.0, 10.0], kl_weights=None)
    cells = regularization_cells(args, base)
    assert len(cells) == 4 and cells[0] == ((2, 64, 32, 1), 1.0, 0.01) and cells[-1] == ((2, 128, 64, 64, 1), 10.0, 0.01)
