"""Parts found by name through Python entry points: consensus rules, dataset readers, services, attacks,
the learners' networks and the compressions of their States.

swarmmap's own parts are registered the same way as anyone's, in its ``pyproject.toml``; a
package of one's own adds a part without touching swarmmap by declaring an entry point in the
part's group, e.g. in that package's ``pyproject.toml``::

    [project.entry-points."swarmmap.consensus"]
    damped = "my_rules:DAMPED"           # a ConsensusPlugin

    [project.entry-points."swarmmap.datasets"]
    scans-csv = "my_readers:SCANS_CSV"   # a DatasetReader

and installing it beside swarmmap. ``swarmmap plugins`` lists what is installed and where each
comes from; the config refuses a name no installed part has (naming the close ones), and the
settings fingerprint of a run names the package and version of a part from another package.
A part that fails to import or breaks its contract is refused with a :class:`PluginError` that
names it and its package. docs/layout.md says how to write one.

An entry point names a spec object (:class:`ConsensusPlugin`, :class:`DatasetReader`): keep the
module it lives in light (import torch and the like inside ``make``/``read``), since every
service that validates a config loads the spec of the part the config names.
"""

from __future__ import annotations

import difflib
import functools
import importlib
import importlib.metadata as metadata
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any


class PluginError(Exception):
    """A part that cannot be had: unknown, ambiguous, failing to import, or breaking its contract."""


@dataclass(frozen=True)
class ConsensusPlugin:
    """A consensus rule (``learner.consensus``): how hard each parameter is pulled towards each
    neighbour in DiNNO's update (services/learner/consensus/base.py says what a rule is).

    ``make(model, settings)`` builds one node's rule for its torch ``model`` (settings: the
    learner's ConsensusSettings, ``options`` among them: ``learner.consensus_options`` validated
    by ``options``); ``models``: the learner models it works with (None: any); ``extra_vector``:
    its States carry a vector after the parameters (what :meth:`extra` returns); ``summary``:
    one line for ``swarmmap plugins`` and the docs."""

    make: Callable[[Any, Any], Any]
    summary: str
    models: tuple[str, ...] | None = None
    why_models: str = ""
    extra_vector: bool = False
    options: type | None = None  # a pydantic model of the rule's own knobs


@dataclass(frozen=True)
class DatasetReader:
    """A reader of real LiDAR logs (``world.dataset``, ``swarmmap up --dataset``).

    ``claims(path)`` says whether a file or folder is one it reads (by its name, cheaply);
    ``read(path, pose, topics)`` returns a :class:`~swarmmap.shared.world.datasets.LaserLog` (``pose``:
    ``world.dataset_pose``; ``topics``: a BagTopics, for readers of ROS bags) or raises
    :class:`~swarmmap.shared.world.datasets.DatasetError` naming what is wrong; ``describe`` says
    what it reads, for help texts and refusals."""

    claims: Callable[[Path], bool]
    read: Callable[..., Any]
    describe: str


@dataclass(frozen=True)
class ModelPlugin:
    """A learner's network (``learner.model``).

    ``build(spec, bounds)`` returns the network, a torch module mapping (N, 2) points in metres to
    occupancy probabilities with ``logits(points)``, ``shape`` and ``scale`` (swarmmap's FourierNet,
    swarmmap.shared.learning.models, is the model to subclass); it is called with torch's generator
    seeded by the run's seed, so every learner starts from the same network. ``spec`` holds
    ``learner.model_shape`` (``shape``), ``siren_scale`` (``scale``) and the Bayesian and dropout
    settings. ``std``: the network is a StochasticNet whose passes differ, and its maps have a
    standard deviation."""

    build: Callable[[Any, Any], Any]
    summary: str
    std: bool = False


@dataclass(frozen=True)
class AttackPlugin:
    """A hostile member's lie (``faults.attack``, for tests, the bench and research on robust consensus).

    ``lie(liar, theta)`` rewrites ``theta``, the attacker's honest parameters of the round (a float32
    view: write into it), given ``liar`` (services/learner/attacks.py's Liar: its seeded ``rng``, a
    ``direction(n)``, the ``rho`` mask of a Bayesian network's spreads, the ``out`` layer's indices);
    None for an attack that changes no value; ``sends``: ``lie`` (the lie instead of the State),
    ``both`` (the honest State and the lie: two stories a round), ``nothing`` (RoundCompletes,
    never a State), ``ahead`` (its State as one of three rounds ahead, no RoundComplete),
    ``repeat`` (its first State again and again, no RoundComplete), ``bomb`` (object bombs instead
    of its messages) or ``metrics`` (honest States, a flood of Metrics); ``models``: the learner
    models it applies to (None: any)."""

    lie: Callable[[Any, Any], None] | None
    summary: str
    sends: str = "lie"
    models: tuple[str, ...] | None = None


@dataclass(frozen=True)
class CompressionPlugin:
    """A way of sending a State's vector (``learner.compression``, ``learner.slow_link_compression``).

    ``make(knobs)`` builds one learner's encoder (a :class:`~swarmmap.shared.wire.compression.Encoder`,
    the class to subclass, or its ``Chain`` for differences with error feedback) from its
    :class:`~swarmmap.shared.wire.compression.Knobs` (``options``: ``learner.compression_options``
    validated by ``options``). An encoder writes the wire's encodings (f32, f16, bf16, topk, sign,
    quant, lowrank: docs/protocol.md), so receivers rebuild its States without it: a plug-in
    chooses what to send, not a new format. ``chained``: each State adds to the one before (one
    State a round, none sent twice with different values); ``summary``: one line for ``swarmmap
    plugins`` and the docs."""

    make: Callable[[Any], Any]
    summary: str
    chained: bool = False
    options: type | None = None  # a pydantic model of the compression's own knobs


@dataclass(frozen=True)
class Group:
    """A kind of part: its entry-point group, what names one, and its spec type (``module:Class``,
    imported when a part is checked: a spec type may live in a module that uses this one)."""

    name: str
    field: str
    spec: str

    @property
    def entry_points(self) -> str:
        return f"swarmmap.{self.name}"

    def spec_type(self) -> type:
        module, _, attr = self.spec.partition(":")
        return getattr(importlib.import_module(module), attr)


GROUPS = {g.name: g for g in (Group("consensus", "learner.consensus", "swarmmap.shared.plugins:ConsensusPlugin"),
                              Group("datasets", "world.dataset", "swarmmap.shared.plugins:DatasetReader"),
                              Group("services", "service", "swarmmap.shared.wire.services:ServiceKind"),
                              Group("attacks", "faults.attack", "swarmmap.shared.plugins:AttackPlugin"),
                              Group("models", "learner.model", "swarmmap.shared.plugins:ModelPlugin"),
                              Group("compressions", "learner.compression", "swarmmap.shared.plugins:CompressionPlugin"))}


@dataclass(frozen=True)
class Plugin:
    """One installed part: its group and name, the entry point's target and the package it comes from."""

    group: str
    name: str
    target: str
    package: str
    version: str

    @property
    def builtin(self) -> bool:
        return self.package == "swarmmap"

    def origin(self) -> str:
        """Where it comes from, as ``package version``."""
        return f"{self.package} {self.version}"

    def describe(self) -> str:
        return f"{self.group} plug-in {self.name!r} ({self.target}, from {self.origin()})"


def _group(group: str) -> Group:
    if group not in GROUPS:
        raise PluginError(f"no such kind of plug-in {group!r}; known: {', '.join(GROUPS)}")
    return GROUPS[group]


@functools.cache
def _scan(group: str) -> tuple[dict[str, Plugin], dict[str, list[Plugin]]]:
    """The group's parts by name, and the names that more than one package registers."""
    found: dict[str, list[Plugin]] = {}
    for ep in metadata.entry_points(group=_group(group).entry_points):
        dist = ep.dist
        plugin = Plugin(group, ep.name, ep.value, dist.name if dist else "?", dist.version if dist else "?")
        if plugin not in found.get(ep.name, []):
            found.setdefault(ep.name, []).append(plugin)
    one = {name: ps[0] for name, ps in found.items() if len(ps) == 1}
    many = {name: ps for name, ps in found.items() if len(ps) > 1}
    return one, many


def installed(group: str) -> list[Plugin]:
    """Every part of ``group`` installed, built-in ones first, then by name (a name two packages
    register appears twice)."""
    one, many = _scan(group)
    every = [*one.values(), *(p for ps in many.values() for p in ps)]
    return sorted(every, key=lambda p: (not p.builtin, p.name, p.package))


def names(group: str) -> list[str]:
    """The names a config may give for ``group``, built-in ones first."""
    return list(dict.fromkeys(p.name for p in installed(group)))


def find(group: str, name: str) -> Plugin:
    """The installed part called ``name``; a PluginError naming the close names, or the packages
    that both register it."""
    one, many = _scan(group)
    if name in many:
        raise PluginError(f"{_group(group).field}: {name!r} is registered by more than one package "
                          f"({', '.join(sorted(p.origin() for p in many[name]))}): uninstall one of them")
    if name not in one:
        close = difflib.get_close_matches(name, names(group), n=3, cutoff=0.6)
        hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
        raise PluginError(f"{_group(group).field}: no {group} plug-in is called {name!r} (installed: "
                          f"{', '.join(names(group)) or 'none'}; `swarmmap plugins` lists them){hint}")
    return one[name]


@functools.cache
def load(group: str, name: str) -> Any:
    """The spec object of the part called ``name``, imported and checked against its group's
    contract; a PluginError naming the part and its package when it cannot be."""
    plugin = find(group, name)
    try:
        obj = metadata.EntryPoint(plugin.name, plugin.target, GROUPS[group].entry_points).load()
    except Exception as exc:  # whatever a foreign module raises on import is that module's fault
        raise PluginError(f"{plugin.describe()} failed to import: {type(exc).__name__}: {exc}") from None
    spec = GROUPS[group].spec_type()
    if not isinstance(obj, spec):
        raise PluginError(f"{plugin.describe()} breaks its contract: {plugin.target} is a {type(obj).__name__}, "
                          f"not a {GROUPS[group].spec.replace(':', '.')}")
    return obj


def origin(group: str, name: str) -> str | None:
    """``package version`` of a part from another package (what the settings fingerprint records);
    None for a built-in one or a name nothing registers."""
    one, _ = _scan(group)
    plugin = one.get(name)
    return None if plugin is None or plugin.builtin else plugin.origin()


def refresh() -> None:
    """Forget what was found and loaded (after installing a package into a running process)."""
    _scan.cache_clear()
    load.cache_clear()


def broken_contract(plugin_name: str, group: str, what: str) -> PluginError:
    """The error for a part whose product breaks its group's contract (a rule without a method, a
    reader that returns no LaserLog), naming the part and its package."""
    try:
        where = find(group, plugin_name).describe()
    except PluginError:
        where = f"{group} plug-in {plugin_name!r}"
    return PluginError(f"{where} breaks its contract: {what}")


def report() -> tuple[list[str], int]:
    """What ``swarmmap plugins`` prints: every group's parts, each loaded and checked (name,
    where it comes from, what it is, or why it is refused); and how many are refused."""
    lines, refused = [], 0
    for group in GROUPS.values():
        lines.append(f"{group.name} ({group.field}; entry points {group.entry_points}):")
        parts = installed(group.name)
        for plugin in parts:
            try:
                spec = load(group.name, plugin.name)  # a name two packages register is refused here
                what = spec.describe if isinstance(spec, DatasetReader) else spec.summary
                if isinstance(spec, (ConsensusPlugin, AttackPlugin)) and spec.models:
                    what += f" (model {' or '.join(spec.models)})"
                if isinstance(spec, ModelPlugin) and spec.std:
                    what += " (std maps)"
            except PluginError as exc:
                refused += 1
                what = f"REFUSED: {exc}"
            lines.append(f"  {plugin.name:<13} {plugin.origin():<28} {what}")
        if not parts:
            lines.append("  (none installed)")
    return lines, refused
