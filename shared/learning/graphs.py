"""Communication graphs: who exchanges State with whom, and DSGD/DSGT's mixing weights.

``complete`` and ``ring`` need nothing; ``file`` reads an edge list (YAML/JSON: a list of
[i, j] pairs, or a mapping ``{edges: [[i, j], ...]}``); ``disk`` joins robots within
``comm_radius_m`` of each other, from the positions where the world says the robots end their
traversal (offline data), or while they drive (online data: DiNNO's dynamic disk graph, each
State carrying its robot's position). Every learner computes the same graph from the same inputs, so neighbour sets are
symmetric, as Algorithm 1 needs. A robot with no neighbour trains alone.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from swarmmap.shared.run.config import GraphSpec


class GraphError(ValueError):
    """A graph file or setting that cannot be used; the message names the problem."""


def read_edges(path: Path, robots: int) -> set[tuple[int, int]]:
    """Undirected edges from a graph file, checked against the robot ids."""
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except FileNotFoundError:
        raise GraphError(f"{path}: graph file does not exist") from None
    except (OSError, yaml.YAMLError) as exc:
        raise GraphError(f"{path}: not a YAML/JSON graph file: {exc}") from None
    pairs = doc.get("edges") if isinstance(doc, dict) else doc
    if not isinstance(pairs, list):
        raise GraphError(f"{path}: expected a list of [i, j] edges (or {{edges: [...]}})")
    edges = set()
    for k, pair in enumerate(pairs):
        if not (isinstance(pair, list | tuple) and len(pair) == 2 and all(isinstance(v, int) for v in pair)):
            raise GraphError(f"{path}: edge #{k} must be a pair of robot ids, got {pair!r}")
        i, j = pair
        if not (0 <= i < robots and 0 <= j < robots) or i == j:
            raise GraphError(f"{path}: edge #{k} {pair} names a robot outside 0..{robots - 1} or a self-loop")
        edges.add((min(i, j), max(i, j)))
    return edges


def neighbour_sets(kind: str, robots: int, *, graph_file: Path | None = None, radius: float = 0.0,
                   positions: np.ndarray | None = None) -> dict[int, set[int]]:
    """Every robot's neighbours in the graph ``kind``."""
    out: dict[int, set[int]] = {i: set() for i in range(robots)}
    if kind == "complete":
        return {i: set(range(robots)) - {i} for i in range(robots)}
    if kind == "ring":
        return {i: {(i - 1) % robots, (i + 1) % robots} - {i} for i in range(robots)}
    if kind == "none":
        return out
    if kind == "file":
        if graph_file is None:
            raise GraphError("learner.graph_file: required with graph = file")
        edges = read_edges(graph_file, robots)
    elif kind == "disk":
        if positions is None or len(positions) != robots:
            raise GraphError(f"disk graph: need {robots} robot positions, got {None if positions is None else len(positions)}")
        d = np.linalg.norm(positions[:, None, :] - positions[None, :, :], axis=-1)
        edges = {(i, j) for i in range(robots) for j in range(i + 1, robots) if d[i, j] <= radius}
    else:
        raise GraphError(f"unknown graph {kind!r}; allowed: complete, ring, file, disk")
    for i, j in edges:
        out[i].add(j)
        out[j].add(i)
    return out


def metropolis_weights(graph: dict[int, set[int]], node: int) -> dict[int, float]:
    """Metropolis-Hastings weights of ``node``'s row (DiNNO's ``get_metropolis``): 1 / (1 +
    max(deg i, deg j)) per neighbour j, the rest on itself; the matrix is doubly stochastic."""
    deg = {i: len(n) for i, n in graph.items()}
    row = {j: 1.0 / (1 + max(deg[node], deg[j])) for j in graph[node]}
    row[node] = 1.0 - sum(row.values())
    return row


def run_graph(spec: GraphSpec, robots: int, positions: np.ndarray | None) -> dict[int, set[int]]:
    """The communication graph of a run (:meth:`~swarmmap.shared.run.config.RunConfig.graph`)."""
    return neighbour_sets(spec.kind, robots, graph_file=spec.file, radius=spec.radius_m, positions=positions)
