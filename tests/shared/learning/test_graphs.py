"""Communication graphs and mixing weights."""

from __future__ import annotations

import numpy as np
import pytest

from swarmmap.shared.learning.graphs import GraphError, metropolis_weights, neighbour_sets


def test_complete_ring_and_none():
    assert neighbour_sets("complete", 3) == {0: {1, 2}, 1: {0, 2}, 2: {0, 1}}
    assert neighbour_sets("ring", 4) == {0: {1, 3}, 1: {0, 2}, 2: {1, 3}, 3: {0, 2}}
    assert neighbour_sets("ring", 1) == {0: set()}
    assert neighbour_sets("none", 2) == {0: set(), 1: set()}


def test_disk_graph_joins_robots_within_the_radius():
    pos = np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 0.0]])
    assert neighbour_sets("disk", 3, radius=1.5, positions=pos) == {0: {1}, 1: {0}, 2: set()}
    with pytest.raises(GraphError, match="need 3 robot positions"):
        neighbour_sets("disk", 3, radius=1.0, positions=None)


def test_graph_file_is_read_symmetric_and_checked(tmp_path):
    f = tmp_path / "g.yaml"
    f.write_text("edges: [[0, 1], [2, 1]]\n")
    assert neighbour_sets("file", 3, graph_file=f) == {0: {1}, 1: {0, 2}, 2: {1}}
    f.write_text("[[0, 5]]")
    with pytest.raises(GraphError, match="g.yaml: edge #0 .* outside 0..2"):
        neighbour_sets("file", 3, graph_file=f)
    f.write_text("[[0, 1, 2]]")
    with pytest.raises(GraphError, match="pair of robot ids"):
        neighbour_sets("file", 3, graph_file=f)
    with pytest.raises(GraphError, match="does not exist"):
        neighbour_sets("file", 3, graph_file=tmp_path / "nope.yaml")


def test_metropolis_weights_are_doubly_stochastic():
    g = {0: {1, 2, 3}, 1: {0}, 2: {0, 3}, 3: {0, 2}}
    w = np.zeros((4, 4))
    for i in g:
        for j, v in metropolis_weights(g, i).items():
            w[i, j] = v
    np.testing.assert_allclose(w.sum(0), 1)
    np.testing.assert_allclose(w.sum(1), 1)
    np.testing.assert_allclose(w, w.T)
    assert (w >= 0).all()
