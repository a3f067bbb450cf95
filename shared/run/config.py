"""Configuration: one pydantic model per service, one shared Zenoh config, and how they load.

A run is described by one :class:`RunConfig` (written as ``RUN_DIR/config.yaml`` by
``swarmmap up``). Each service reads it with precedence

    defaults < preset < config file (``--config``) < environment (``SWARMMAP_...``) < command line

The layers are pydantic-settings sources (:func:`resolve`), merged section by section.
Environment variables name a field by its path: ``SWARMMAP_SEED`` for a top-level field,
``SWARMMAP_LEARNER__ROUNDS`` or ``SWARMMAP_ZENOH__CONNECT`` for a section's field; lists and
mappings are read as YAML (``[a, b]`` is a list), ``null`` unsets a field. ``--set learner.lr_start=0.01`` overrides any field.
A wrong value stops the service at start with a message naming the field and what it allows.
"""

from __future__ import annotations

import copy
import difflib
import os
import sys
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, Field, ValidationError, model_validator
from pydantic_settings import BaseSettings, EnvSettingsSource, PydanticBaseSettingsSource, SettingsConfigDict, SettingsError
from pydantic_settings.sources.types import EnvNoneType

from swarmmap.shared import plugins
from swarmmap.shared.learning.layout import state_copies
from swarmmap.shared.run.sections import (  # noqa: F401 - the sections, named where the config is
    Budget,
    ExploreSettings,
    FaultSettings,
    LearnerSettings,
    LidarSettings,
    ObserverSettings,
    RecorderSettings,
    Ros2Settings,
    RouterSettings,
    Section,
    UpSettings,
    WorldSettings,
    ZenohSettings,
    consensus_fits,
    consensus_options,
    model_kinds,
    parse_budgets,
    parse_shape,
    parse_starts,
    std_models,
)
from swarmmap.shared.wire.protocol import NAME_PATTERN

ENV_PREFIX = "SWARMMAP_"


class RunConfig(Section):
    """The whole resolved configuration of one run (``RUN_DIR/config.yaml``)."""

    preset: str | None = Field(None, description="named preset applied under the config file (smoke, quickstart, demo, dinno, "
                                                 "dinno-fast, paper)")
    run_id: str = Field("default", pattern=NAME_PATTERN, description="run id: every key lives under <key_prefix>/<run_id>")
    key_prefix: str = Field("swarmmap", pattern=r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$", description="first chunks of every key expression")
    robots: int = Field(3, ge=1, le=64, description="number of robots (and lidar streamers and learners)")
    seed: int = Field(0, ge=0, description="seed of the floor plan, paths, sampling and model initialisation")
    run_dir: Path | None = Field(None, description="directory for the run's outputs (config, metrics, models, maps)")
    label: str = Field("", max_length=80, description="a few words that tell this run apart (swarmmap runs, compare's "
                                                      "legends, overview.png's title); changes nothing it computes")
    log_level: Literal["debug", "info", "warning", "error"] = Field("info", description="log verbosity")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    router: RouterSettings = Field(default_factory=RouterSettings)
    world: WorldSettings = Field(default_factory=WorldSettings)
    explore: ExploreSettings = Field(default_factory=ExploreSettings)
    lidar: LidarSettings = Field(default_factory=LidarSettings)
    learner: LearnerSettings = Field(default_factory=LearnerSettings)
    observer: ObserverSettings = Field(default_factory=ObserverSettings)
    recorder: RecorderSettings = Field(default_factory=RecorderSettings)
    faults: FaultSettings = Field(default_factory=FaultSettings)
    up: UpSettings = Field(default_factory=UpSettings)
    ros2: Ros2Settings = Field(default_factory=Ros2Settings)

    @model_validator(mode="after")
    def _attackers(self) -> RunConfig:
        f = self.faults
        if any(not 0 <= r < self.robots for r in f.attackers):
            raise ValueError(f"faults.attackers {f.attackers}: robots are 0..{self.robots - 1}")
        if f.attack == "none" or not f.attackers:
            return self
        try:
            attack = plugins.load("attacks", f.attack)
        except plugins.PluginError as exc:
            raise ValueError(str(exc)) from None
        if attack.models is not None and self.learner.model not in attack.models:
            raise ValueError(f"faults.attack {f.attack} ({attack.summary}): it needs learner.model {' or '.join(attack.models)}")
        if attack.sends == "both" and plugins.load("compressions", self.learner.compression).chained:
            raise ValueError(f"faults.attack {f.attack} sends two States a round: a compressed chain carries one "
                             "(a learner.compression whose States stand alone: none, f16 or bf16)")
        return self

    @model_validator(mode="after")
    def _exploration(self) -> RunConfig:
        e, s = self.explore, self.learner
        if not e.active:
            return self
        clash = [why for bad, why in (
            (bool(self.world.dataset), "world.dataset (a log's robots drive where they drove)"),
            (bool(self.lidar.replay), "lidar.replay (a recording's robots drove already)"),
            (s.exchange_every_s > 0, "learner.exchange_every_s (goals are chosen at stated rounds)"),
            (s.algorithm == "centralized", "learner.algorithm centralized (no learner per robot chooses a goal)"),
            (s.rounds <= e.decide_every, f"learner.rounds {s.rounds} (no goal before round decide_every {e.decide_every})"),
            (bool(self.ros2.namespaces and e.starts), "explore.starts (ROS 2 robots start where they are)"),
            (bool(self.ros2.namespaces) and e.policy == "planned", "ROS 2 robots (they have no planned paths)"),
            (bool(self.ros2.namespaces) and not self.ros2.extent,
             "no ros2.extent (ROS 2 robots exploring need the area to map: --extent xmin,ymin,xmax,ymax)"),
        ) if bad]
        if clash:
            raise ValueError(f"explore.policy {e.policy} cannot run with " + "; ".join(clash))
        if e.policy == "uncertainty" and s.model not in (stochastic := std_models()):
            raise ValueError(f"explore.policy uncertainty needs a model with a std: learner.model {s.model} has none "
                             f"({' or '.join(stochastic)})")
        if e.starts:
            parse_starts(e.starts, self.robots)
        return self

    @model_validator(mode="after")
    def _budgets(self) -> RunConfig:
        if self.up.budget:
            parse_budgets(self.up.budget, self.robots)
        return self

    def budget(self, robot: int) -> Budget | None:
        """Robot ``robot``'s budget (``up.budget``), or None."""
        return parse_budgets(self.up.budget, self.robots)[robot] if self.up.budget else None

    @model_validator(mode="after")
    def _secrets_in_run_dir(self) -> RunConfig:
        if self.zenoh.secrets is None and self.run_dir is not None and not self.zenoh.insecure:
            self.zenoh.secrets = self.run_dir / "secrets"
        return self

    def dump_yaml(self) -> str:
        """The config as YAML, loadable again with ``--config``."""
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)

    # Facts of the whole run that several services need. A service reads its own section and
    # these; this is the one place that knows which section each comes from.

    def network(self) -> NetworkSpec:
        """The network every learner trains and every State is evaluated with."""
        s = self.learner
        return NetworkSpec(s.model, tuple(s.model_shape), s.siren_scale, s.prior_sigma, s.bnn_rho_init, s.dropout_p,
                           s.bnn_local_reparam)

    def graph(self) -> GraphSpec:
        """Who exchanges States with whom: none for the baselines that do not communicate
        (individual, centralized); complete for a dynamic disk graph (graph disk with online data),
        whose links come and go with the robots' distance; else ``learner.graph``."""
        s = self.learner
        dynamic = s.graph == "disk" and s.data == "online"
        kind = "none" if s.algorithm in ("individual", "centralized") else "complete" if dynamic else s.graph
        return GraphSpec(kind, s.graph_file, s.comm_radius_m, dynamic)

    def state_copies(self) -> int:
        """Parameter-sized vectors in a State (:func:`~swarmmap.shared.learning.layout.state_copies`)."""
        return state_copies(self.learner.algorithm, self.learner.consensus)

    def rounds(self) -> int:
        """Training rounds of every learner."""
        return self.learner.rounds

    def legs(self) -> int:
        """Exploring: the legs of the drive after the start (leg 0), one goal each, chosen at rounds
        decide_every, 2 decide_every, ... below ``learner.rounds``."""
        return (self.learner.rounds - 1) // self.explore.decide_every

    def report_every(self) -> int:
        """Learners report Metrics (and the observer maps their States) every this many rounds."""
        return self.learner.eval_every

    def world_wait_s(self) -> float:
        """How long a service waits for the world's map (it answers once the plan is built): the
        learners' ``learner.collect_timeout_s``, the longest any service waits for the world."""
        return self.learner.collect_timeout_s

    def labelling(self) -> Labelling:
        """How points along a beam are labelled: the lidar's training points, the world's validation set."""
        return Labelling(self.lidar.samples_per_beam, self.lidar.occupied_depth_m)

    def lidar_min_range_m(self) -> float:
        """The LiDAR's closest measurable range (the world simulates the sensor, streamers apply it)."""
        return self.world.lidar_min_range_m

    def transport(self) -> str:
        """How the learners exchange States: ``zenoh`` (a process each) or ``inproc`` (one process)."""
        return self.learner.transport

    def plan(self) -> str:
        """The run's floor plan (``world.floorplan``), as recordings name it."""
        return self.world.floorplan

    def ros2_maps(self) -> list[str] | None:
        """The ROS 2 namespace of every robot's maps when the observer publishes them, else None."""
        if not self.ros2.publish:
            return None
        return self.ros2.namespaces or [f"robot_{i}" for i in range(self.robots)]

    def consumers_wait_s(self) -> float:
        """How long a source of scans waits for their consumers before it starts anyway."""
        return self.world.wait_for_consumers_s

    def std_max(self) -> float:
        """The std that gets the top colour of the std colour map: in the viewer and in every picture of a map."""
        return self.observer.std_max

    def leave_s(self) -> float:
        """How long, once the run is over, services take to leave (the router stays for them)."""
        return self.recorder.linger_s + 5.0

    def router_per_host(self) -> bool:
        """Whether the run has a router on each host (shared/wire/mesh.py), not one for the run."""
        return self.up.routers == "per-host" or self.up.netns


COMMON_FIELDS = ("run_id", "key_prefix", "robots", "seed", "run_dir", "log_level")
SECTION_NAMES = ("zenoh", "router", "world", "lidar", "learner", "observer", "recorder", "faults", "up")


@dataclass(frozen=True)
class NetworkSpec:
    """The learner's network (``learner.model`` and the settings of its kind)."""

    kind: str
    shape: tuple[int, ...]
    scale: float  # the sine layer's frequency scale
    prior_sigma: float = 0.1  # bnn
    rho_init: float = -5.0  # bnn
    dropout_p: float = 0.1  # dropout
    local_reparam: bool = False  # bnn


@dataclass(frozen=True)
class GraphSpec:
    """A run's communication graph: ``kind`` (complete, ring, file, disk or none), its file, the
    disk's radius, and whether it changes while the robots drive (``dynamic``)."""

    kind: str
    file: Path | None = None
    radius_m: float = 15.0
    dynamic: bool = False


@dataclass(frozen=True)
class Labelling:
    """Free points sampled along each beam, and how far behind the hit the occupied one lies."""

    samples_per_beam: int
    occupied_depth_m: float


class ConfigError(SystemExit):
    """A refused configuration; exits with status 2 and a message naming the field."""

    def __init__(self, message: str):
        super().__init__(2)
        self.message = message

    def __str__(self) -> str:
        return self.message


# ----------------------------------------------------------------------------- presets

PRESETS: dict[str, dict[str, Any]] = {
    # Seconds per robot: for tests and a first try.
    "smoke": {
        "robots": 3,
        "world": {"rooms_x": 2, "rooms_y": 2, "lidar_beams": 72, "lidar_rate_hz": 5.0,
                  "speed_mps": 0.5, "val_scans": 150, "val_beams": 48, "grid_resolution_m": 0.05},
        "lidar": {"samples_per_beam": 8},
        "learner": {"rounds": 60, "primal_iterations": 10, "batch_size": 1024,
                    "model_shape": [2, 128, 64, 64, 1], "lr_start": 1e-2, "lr_finish": 1e-3, "rho_init": 0.03,
                    "eval_every": 5, "siren_scale": 8.0, "checkpoint_every": 5},
    },
    # The default: 7 robots, about ten minutes on two CPU cores, maps that show the rooms.
    "demo": {
        "robots": 7,
        "world": {"rooms_x": 3, "rooms_y": 3, "lidar_beams": 120, "lidar_rate_hz": 2.0,
                  "speed_mps": 0.5, "val_scans": 400, "val_beams": 60},
        "lidar": {"samples_per_beam": 10},
        # DiNNO's network and optimiser; rho starts at 0.03 instead of DiNNO's 0.3 so that the
        # maps form within the rounds that fit ten minutes here (DiNNO runs 4000 rounds).
        "learner": {"rounds": 800, "primal_iterations": 5, "batch_size": 2048,
                    "model_shape": [2, 256, 64, 64, 64, 1], "lr_start": 3e-3, "lr_finish": 3e-4,
                    "rho_init": 0.03, "eval_every": 20},
    },
    # DiNNO's published mapping setting (experiments/dist_online_dense_PAPER.yaml) for its
    # floor plan: run with --floorplan .../dinno-floorplan-32/floor_img.png --waypoints
    # .../tight_paths. A 20-beam noiseless LiDAR whose beam is 0.2 x the image's larger side
    # (433 px = 4.334 m at 100 px/m), 25 samples a beam, 500 validation scans; FourierNet
    # [2, 256, 64, 64, 64, 1]; rho 0.3 x1.0004 a round, 5 Adam steps a round, lr 1e-3 -> 1e-4
    # (log), batch 12,500, 4000 rounds (shorten with --rounds). Training is offline here
    # (DiNNO's sliding window of 800 scans is not implemented yet).
    "dinno": {
        "robots": 7,
        "world": {"lidar_beams": 20, "lidar_fov_deg": 360.0, "lidar_min_range_m": 0.01, "lidar_max_range_m": 4.334,
                  "pixels_per_metre": 100.0, "dinno_border_px": 30, "val_scans": 500, "val_beams": 20,
                  "speed_mps": 0.5, "lidar_rate_hz": 5.0},
        "lidar": {"samples_per_beam": 25, "range_noise_std_m": 0.0, "dropout_prob": 0.0, "sampling": "fixed",
                  "occupied_depth_m": 0.01},
        "learner": {"model": "fourier", "rounds": 4000, "primal_iterations": 5, "batch_size": 12500,
                    "model_shape": [2, 256, 64, 64, 64, 1], "optimizer": "adam", "lr_start": 1e-3, "lr_finish": 1e-4,
                    "lr_schedule": "log", "rho_init": 0.3, "rho_growth": 1.0004, "optimizer_per_round": True,
                    "graph": "complete", "eval_every": 20},
    },
    # The paper's Section 5 network and Algorithm 2 with seven agents: SIREN (256) -> 4 x Bayesian
    # linear (256, ReLU) -> linear (1, sigmoid), separate-kl regularisation, 50 passes a map
    # point. Sized for a GPU (the paper ran on GPU nodes under SLURM); shorten with --rounds.
    "paper": {
        "robots": 7,
        "world": {"rooms_x": 3, "rooms_y": 3, "lidar_beams": 360, "lidar_rate_hz": 5.0, "speed_mps": 0.22,
                  "val_scans": 500, "val_beams": 60},
        "lidar": {"samples_per_beam": 12},
        "learner": {"model": "bnn", "model_shape": [2, 256, 256, 256, 256, 256, 1], "regularization": "separate-kl",
                    "kl_weight": 5e-3, "rounds": 2000, "primal_iterations": 5, "batch_size": 4096,
                    "lr_start": 1e-3, "lr_finish": 1e-4, "rho_init": 0.03, "mc_samples": 50, "eval_every": 20},
    },
}
# The first try: the smoke run with a small Bayesian network, so that its maps have a std (about
# a minute on two CPU cores); the noise-contrastive prior (learner.unseen_weight) makes the std
# bright where no robot looked (around the building) and dark where they mapped.
PRESETS["quickstart"] = {
    **PRESETS["smoke"],
    "learner": {**PRESETS["smoke"]["learner"], "model": "bnn", "unseen_weight": 0.05},
}
# DiNNO's setting (plan, sensor, data, network, Adam re-created each round, complete graph) with
# the schedule that reaches DiNNO's published quality (mean val_bce 0.102) soonest here
# (bench/time_to_quality.py; the README's "Performance"): rho 0.01 instead of 0.3 (less pull
# early, so each robot fits its own data while the duals build up), lr 2e-3 -> 2e-4 (log), batch
# 4,096 instead of 12,500, 150 rounds. Give it the same --floorplan and --waypoints as `dinno`.
PRESETS["dinno-fast"] = {
    **PRESETS["dinno"],
    "learner": {**PRESETS["dinno"]["learner"], "rounds": 150, "batch_size": 4096, "lr_start": 2e-3, "lr_finish": 2e-4,
                "rho_init": 0.01},
}
DEFAULT_PRESET = "demo"
# Under a preset and over it nothing but what a user gives: a run on a real LiDAR log (world.dataset)
# serves real ranges (no added noise or dropouts) of a scanner that sees farther than a
# TurtleBot's, labelled every half metre or so.
DATASET_DEFAULTS: dict[str, Any] = {
    "world": {"lidar_max_range_m": 10.0, "lidar_min_range_m": 0.05},
    "lidar": {"range_noise_std_m": 0.0, "dropout_prob": 0.0, "samples_per_beam": 20},
}


# ----------------------------------------------------------------------------- loading

# Variables under SWARMMAP_ that the launchers read and that are not config fields (every other
# SWARMMAP_* variable must name a field, so that a misspelt one is refused, not ignored).
LAUNCHER_VARIABLES: dict[str, str] = {
    "SWARMMAP_UID": "compose.yaml: the user id the services run as",
    "SWARMMAP_GID": "compose.yaml: the group id the services run as",
    "SWARMMAP_RUNS": "compose.yaml: the host folder that holds the run directories (default ./runs)",
    "SWARMMAP_SIF": "deploy/slurm: the Apptainer/Singularity image to run the services in",
    "SWARMMAP_LEARNER_CPUS": "deploy/slurm/team.sbatch: CPUs per learner task",
    "SWARMMAP_GPUS_PER_LEARNER": "deploy/slurm/team.sbatch: GPUs per learner task",
    "SWARMMAP_ROUTER_PORT": "deploy/slurm/team.sbatch: the base router's port (robot i's router, with a router per "
                            "host: that + 1 + i)",
    "SWARMMAP_END_GRACE_S": "deploy/slurm/team.sbatch: how long the services get to leave once the run is over",
    "SWARMMAP_ROBOT_CLAIMS": "compose.yaml (inside each container): where replicas claim their robot ids",
    "SWARMMAP_START": "compose.yaml (inside each container): the folder of the start's verdict, read-only to the services",
    "SWARMMAP_VIEWER_PORT": "compose.yaml: the host port of the observer's web viewer (on 127.0.0.1)",
    "SWARMMAP_VIEWER_GRPC_PORT": "compose.yaml: the host port of the observer's gRPC server (on 127.0.0.1)",
}


def did_you_mean(word: str, choices: typing.Iterable[str]) -> str:
    """`` (did you mean 'learner'?)`` for the choice closest to ``word``, or "" when none is close."""
    close = difflib.get_close_matches(str(word), list(choices), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """A copy of ``base`` with ``over`` merged in, nested dicts merged key by key."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _set_path(tree: dict[str, Any], path: list[str], value: Any) -> None:
    for part in path[:-1]:
        tree = tree.setdefault(part, {})
        if not isinstance(tree, dict):
            raise ConfigError(f"config error:\n  {'.'.join(path)}: {part} is not a section")
    tree[path[-1]] = value


def apply_override(tree: dict[str, Any], item: str) -> None:
    """Apply one ``--set SECTION.FIELD=VALUE`` (VALUE read as YAML) to a nested dict."""
    if "=" not in item:
        raise ConfigError(f"config error:\n  --set {item!r}: expected KEY=VALUE, e.g. --set learner.rounds=50")
    key, raw = item.split("=", 1)
    _set_path(tree, key.strip().split("."), _parse_scalar(raw))


def _parse_scalar(text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


MAX_CONFIG_BYTES = 1 << 20  # a config file, at most
MAX_CONFIG_NODES = 100_000  # the values of a config file, aliases counted each time they are used


def read_config_file(path: Path) -> dict[str, Any]:
    """Read a YAML (or JSON) config file; refuse anything but a mapping, a file over
    MAX_CONFIG_BYTES, and one whose aliases make more than MAX_CONFIG_NODES values."""
    try:
        if (size := Path(path).stat().st_size) > MAX_CONFIG_BYTES:
            raise ConfigError(f"config error:\n  --config: config file {path} is {size} bytes, over {MAX_CONFIG_BYTES}")
        doc = yaml.safe_load(Path(path).read_text())
    except FileNotFoundError:
        raise ConfigError(f"config error:\n  --config: config file {path} does not exist") from None
    except IsADirectoryError:
        raise ConfigError(f"config error:\n  --config: {path} is a folder; name its config.yaml") from None
    except (OSError, UnicodeDecodeError, RecursionError, yaml.YAMLError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConfigError(f"config error:\n  --config: config file {path} is not valid YAML: {first[:200]}") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise ConfigError(f"config error:\n  --config: config file {path} must hold a mapping, got {type(doc).__name__}")
    if not _within(doc, [MAX_CONFIG_NODES]):
        raise ConfigError(f"config error:\n  --config: config file {path} holds more than {MAX_CONFIG_NODES} values "
                          "(its aliases repeat themselves?)")
    return doc


def _within(value: Any, budget: list[int], depth: int = 0) -> bool:
    """Whether ``value`` (aliases counted each time) holds at most ``budget[0]`` values, 64 deep."""
    budget[0] -= 1
    if budget[0] < 0 or depth > 64:
        return False
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    return all(_within(v, budget, depth + 1) for _, v in items)


def env_names() -> dict[str, list[str]]:
    """Every ``SWARMMAP_*`` variable that names a config field, with the field's path."""
    names: dict[str, list[str]] = {}
    for name, field in RunConfig.model_fields.items():
        if _is_model(field.annotation):
            for sub in field.annotation.model_fields:
                names[f"{ENV_PREFIX}{name.upper()}__{sub.upper()}"] = [name, sub]
        else:
            names[f"{ENV_PREFIX}{name.upper()}"] = [name]
    return names


def refuse_unknown_variables(environ: typing.Mapping[str, str]) -> None:
    """Refuse a ``SWARMMAP_*`` variable that names no field (and is none of LAUNCHER_VARIABLES),
    with the closest name: a misspelt variable is an error, not silently ignored."""
    names = env_names()
    unknown = [f"  {key}: not a swarmmap setting{did_you_mean(key, [*names, *LAUNCHER_VARIABLES])}; a variable "
               f"names a field by its path, as {ENV_PREFIX}SEED or {ENV_PREFIX}LEARNER__ROUNDS"
               for key in sorted(environ) if key.startswith(ENV_PREFIX) and key not in LAUNCHER_VARIABLES and key not in names]
    if unknown:
        raise ConfigError("config error (environment):\n" + "\n".join(unknown) + "\n  unset the variable(s) or correct the name")


class EnvironmentLayer(EnvSettingsSource):
    """The environment's layer: ``SWARMMAP_SEED=3`` -> {seed: 3}, ``SWARMMAP_LEARNER__ROUNDS=9`` ->
    {learner: {rounds: 9}} (pydantic-settings' nested variables); lists and mappings written as
    YAML (``[a, b]``), ``null`` for none. Only upper-case ``SWARMMAP_*`` names, from ``environ``."""

    def __init__(self, settings_cls: type[BaseSettings], environ: typing.Mapping[str, str]):
        super().__init__(settings_cls, case_sensitive=False, env_prefix=ENV_PREFIX, env_nested_delimiter="__",
                         env_parse_none_str="null")
        self.env_vars = {key.lower(): EnvNoneType(value) if value == "null" else value for key, value in environ.items()
                         if key.startswith(ENV_PREFIX) and key not in LAUNCHER_VARIABLES}

    def decode_complex_value(self, field_name: str, field: Any, value: Any) -> Any:
        return _parse_scalar(value)


class FileLayer(PydanticBaseSettingsSource):
    """The config file's layer (``--config``), read by :func:`read_config_file`."""

    def __init__(self, settings_cls: type[BaseSettings], path: Path | None):
        super().__init__(settings_cls)
        self.doc = read_config_file(path) if path else {}

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:
        return self.doc.get(field_name), field_name, False

    def __call__(self) -> dict[str, Any]:
        return copy.deepcopy(self.doc)


class PresetLayer(PydanticBaseSettingsSource):
    """The lowest layer: the preset that the layers above name (or ``preset``), and for a run on
    real data (``world.dataset``, or ROS 2 robots: ``ros2.namespaces``) :data:`DATASET_DEFAULTS` over it."""

    def __init__(self, settings_cls: type[BaseSettings], preset: str | None):
        super().__init__(settings_cls)
        self.preset = preset

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:
        return None, field_name, False

    def __call__(self) -> dict[str, Any]:
        above = self.current_state  # what the layers above give, merged
        name = above.get("preset") or self.preset
        layer: dict[str, Any] = {}
        if name is not None:
            if not isinstance(name, str) or name not in PRESETS:
                raise ConfigError(f"config error:\n  preset: unknown preset {name!r}{did_you_mean(name, PRESETS)}; "
                                  f"allowed: {', '.join(PRESETS)}")
            layer = {**copy.deepcopy(PRESETS[name]), "preset": name}
        if any(isinstance(tree.get(section), dict) and tree[section].get(field) for tree in (above, layer)
               for section, field in (("world", "dataset"), ("ros2", "namespaces"))):  # a run on real data
            layer = deep_merge(layer, DATASET_DEFAULTS)
        return layer


def _is_model(annotation: Any) -> bool:
    return isinstance(annotation, type) and issubclass(annotation, BaseModel)


def _model_at(loc: tuple) -> type[BaseModel] | None:
    """The config model that holds the field at ``loc`` (a pydantic error location)."""
    model: type[BaseModel] = RunConfig
    for part in loc[:-1]:
        field = model.model_fields.get(part) if isinstance(part, str) else None
        if field is None or not _is_model(field.annotation):
            return None
        model = field.annotation
    return model


# Pydantic's words for a refused value, in the config's: (error type, what to say; {ctx} filled in).
PLAIN_ERRORS = {
    "missing": "is required",
    "int_parsing": "must be a whole number", "int_type": "must be a whole number",
    "int_from_float": "must be a whole number",
    "float_parsing": "must be a number", "float_type": "must be a number", "finite_number": "must be a finite number",
    "bool_parsing": "must be true or false", "bool_type": "must be true or false",
    "string_type": "must be text", "list_type": "must be a list, e.g. [a, b]",
    "model_type": "must be a section: a mapping of its fields", "dict_type": "must be a mapping",
    "greater_than": "must be greater than {gt}", "greater_than_equal": "must be at least {ge}",
    "less_than": "must be less than {lt}", "less_than_equal": "must be at most {le}",
    "string_pattern_mismatch": "must match the pattern {pattern}",
    "path_type": "must be a path", "too_short": "must hold at least {min_length} item(s)",
    "too_long": "must hold at most {max_length} item(s)",
}


def plain_error(err: dict) -> str:
    """One refused field in plain words: ``learner.optimizer: must be 'adam', 'adamw' or 'sgd' (got 'adan')``."""
    loc = tuple(err["loc"])
    where = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc).lstrip(".") or "config"
    kind, ctx, given = err["type"], err.get("ctx") or {}, err.get("input")
    if kind == "extra_forbidden":
        model = _model_at(loc)
        section = ".".join(str(p) for p in loc[:-1])
        fields = list(model.model_fields) if model is not None else []
        hint = did_you_mean(loc[-1], fields) or (f"; swarmmap {section} --help lists its fields" if section in SECTION_NAMES
                                                 else f"; the sections are {', '.join(SECTION_NAMES)}" if not section else "")
        return f"  {where}: unknown {'field' if section else 'field or section'}{hint}"
    hint = ""
    if kind == "literal_error":
        text = f"must be {ctx.get('expected', '')}"
        if isinstance(given, str):
            hint = did_you_mean(given, [c.strip(" '") for c in str(ctx.get("expected", "")).replace(" or ", ",").split(",")])
    elif kind in ("value_error", "assertion_error"):
        return f"  {where}: {ctx.get('error', err['msg'])}"  # the validator's own words name the value
    elif kind in PLAIN_ERRORS:
        text = PLAIN_ERRORS[kind].format(**ctx)
    else:
        text = err["msg"][:1].lower() + err["msg"][1:]
    got = f" (got {given!r})" if kind != "missing" and given is not None and not isinstance(given, dict) else ""
    return f"  {where}: {text}{got}{hint}"


def format_validation_error(exc: ValidationError) -> str:
    """One line per refused field, in plain words (no pydantic dump, no links)."""
    return "config error:\n" + "\n".join(plain_error(err) for err in exc.errors())


def validate_config(doc: dict[str, Any]) -> RunConfig:
    """``doc`` as a RunConfig; a refused value raises ConfigError in plain words."""
    try:
        return RunConfig.model_validate(doc)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc)) from None


def resolve(cli: dict[str, Any] | None = None, *, config_file: Path | None = None,
            preset: str | None = None, environ: typing.Mapping[str, str] | None = None) -> RunConfig:
    """Build the RunConfig from defaults < preset < file < environment < ``cli`` (a nested dict),
    the layers merged by pydantic-settings, nested sections field by field (see the layers above)."""
    environ = os.environ if environ is None else environ
    refuse_unknown_variables(environ)

    class Layers(BaseSettings, RunConfig):
        model_config = SettingsConfigDict(extra="forbid", validate_default=False)

        @classmethod
        def settings_customise_sources(cls, settings_cls, init_settings, **_):
            return (init_settings, EnvironmentLayer(settings_cls, environ), FileLayer(settings_cls, config_file),
                    PresetLayer(settings_cls, preset))

    try:
        layered = Layers(**copy.deepcopy(cli or {}))
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc)) from None
    except SettingsError as exc:  # a variable's value that is not YAML of its field's shape
        raise ConfigError(f"config error (environment):\n  {exc}") from None
    return validate_config(layered.model_dump(exclude_unset=True))


def task_robot(given: int | None, robots: int, field: str, environ: dict[str, str] | None = None) -> int:
    """The robot a per-robot service serves: ``given`` (``--robot``), else its SLURM task rank
    (``SLURM_PROCID``), so that ``srun --ntasks N swarmmap learner`` serves robots 0..N-1, else
    one claimed in the folder ``SWARMMAP_ROBOT_CLAIMS`` names (compose's replicas; shared/wire/claims.py).
    Stops the service with a message naming ``field`` when there is none or it is out of range."""
    environ = os.environ if environ is None else environ
    robot = given
    if robot is None and environ.get("SLURM_PROCID", "").isdigit():
        robot = int(environ["SLURM_PROCID"])
    if robot is None and environ.get("SWARMMAP_ROBOT_CLAIMS"):
        from swarmmap.shared.wire.claims import ClaimError, claimed_robot

        try:
            robot = claimed_robot(environ["SWARMMAP_ROBOT_CLAIMS"], field, robots)
        except ClaimError as exc:
            fail(str(exc))
    if robot is None or not 0 <= robot < robots:
        fail(f"config error:\n  {field}: required (--robot, the SLURM task rank or SWARMMAP_ROBOT_CLAIMS), "
             f"one of 0..{robots - 1} (got {robot!r})")
    return robot


def fail(message: str) -> typing.NoReturn:
    """Print a configuration error and exit with status 2."""
    print(message, file=sys.stderr)
    raise SystemExit(2)
