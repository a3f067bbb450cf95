"""The config's sections: one pydantic model per service (its own settings, validated on
construction), the field types they share, and the checks that need a plug-in (a consensus rule's
models and options). :mod:`swarmmap.shared.run.config` puts them together into a RunConfig."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from swarmmap.shared import plugins


class Section(BaseModel):
    """Base of every config model: unknown keys are errors, assignments are validated."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


def parse_shape(value: Any) -> list[int]:
    """A model shape as users write it, in one syntax everywhere: ``2,64,32,1``, ``[2, 64, 32, 1]``
    (``--set``, the environment, a config file, the experiments' ``--shapes``), a list of ints,
    or ``2 64 32 1`` split by the shell (``--model-shape``); raises ValueError naming the form."""
    if isinstance(value, (list, tuple)):
        if all(isinstance(v, int) and not isinstance(v, bool) for v in value):
            return list(value)
        value = ",".join(str(v) for v in value)
    if not isinstance(value, str):
        raise ValueError(f"a model shape is a list of layer widths like 2,64,32,1 or [2, 64, 32, 1], got {value!r}")
    parts = [p for p in value.strip().strip("[]").replace(",", " ").split()]
    try:
        return [int(p) for p in parts]
    except ValueError:
        raise ValueError(f"a model shape is a list of layer widths like 2,64,32,1 or [2, 64, 32, 1], got {value!r}") from None


# learner.algorithm: the learning rules (services/learner/registry.py names the same)
AlgorithmKind = Literal["dinno", "dsgd", "dsgt", "individual", "centralized"]


def model_kinds() -> tuple[str, ...]:
    """The learner's networks (``learner.model``): the model plug-ins installed, swarmmap's first."""
    return tuple(plugins.names("models"))


def std_models() -> tuple[str, ...]:
    """The learner models whose maps have a standard deviation (stochastic networks: bnn, dropout)."""
    return tuple(n for n in plugins.names("models") if plugins.load("models", n).std)


def installed(group: str, name: str) -> str:
    """``name`` when a part of ``group`` is installed under it, else a ValueError naming the close ones."""
    try:
        plugins.find(group, name)
    except plugins.PluginError as exc:
        raise ValueError(str(exc).split(": ", 1)[1]) from None
    return name


def consensus_fits(s: LearnerSettings) -> None:
    """Refuse a consensus rule that cannot serve these settings: one that fails to load, a model it
    does not work with, options it does not take (a ValueError naming the rule)."""
    try:
        rule = plugins.load("consensus", s.consensus)
    except plugins.PluginError as exc:
        raise ValueError(str(exc)) from None
    if rule.models is not None and s.model not in rule.models:
        why = f" {rule.why_models}:" if rule.why_models else ""
        raise ValueError(f"consensus {s.consensus}{why} it needs model {' or '.join(rule.models)} (not {s.model})")
    consensus_options(s.consensus, rule, s.consensus_options)


def consensus_options(name: str, rule: plugins.ConsensusPlugin, given: dict[str, Any]) -> Any:
    """The rule's options validated by its own model (None for a rule that takes none, refusing any given)."""
    return plugin_options("consensus", name, rule.options, given)


def plugin_options(field: str, name: str, model: type | None, given: dict[str, Any]) -> Any:
    """A plug-in's ``<field>_options`` validated by its own pydantic ``model`` (None for a part that takes
    none, refusing any given); a ValueError naming the field and what is wrong."""
    if model is None:
        if given:
            raise ValueError(f"{field}_options: {field} {name} takes no options (got {', '.join(sorted(given))})")
        return None
    try:
        return model.model_validate(given)
    except ValidationError as exc:
        raise ValueError(f"{field}_options: " + "; ".join(f"{'.'.join(str(x) for x in e['loc'])}: {e['msg']}"
                                                           for e in exc.errors())) from None


def compression_fits(name: str, given: dict[str, Any]) -> None:
    """Refuse a compression that cannot serve: one that fails to load, options it does not take, or
    one whose plug-in makes no Encoder (a ValueError naming it and its package)."""
    from swarmmap.shared.wire.compression import compressor

    try:
        compressor(name, options=part_options("compressions", "compression", name, given))
    except plugins.PluginError as exc:
        raise ValueError(str(exc)) from None


def part_options(group: str, field: str, name: str, given: dict[str, Any]) -> Any:
    """The options of the ``group`` part called ``name`` (it loads, or a ValueError names why not)."""
    try:
        spec = plugins.load(group, name)
    except plugins.PluginError as exc:
        raise ValueError(str(exc)) from None
    return plugin_options(field, name, spec.options, given)


class ZenohSettings(Section):
    """How a service's Zenoh session is opened; unset fields keep Zenoh's own defaults."""

    mode: Literal["peer", "client", "router"] | None = Field(
        None, description="Zenoh session mode (Zenoh's default: peer)")
    connect: list[str] = Field(
        default_factory=list, description="endpoints to connect to, e.g. tcp/10.0.0.5:7447")
    listen: list[str] = Field(
        default_factory=list, description="endpoints to listen on, e.g. tcp/0.0.0.0:7447")
    multicast_scouting: bool | None = Field(
        None, description="UDP multicast discovery of peers (Zenoh's default: on)")
    config_file: Path | None = Field(
        None, description="a Zenoh JSON5 config file; the fields above override it")
    secrets: Path | None = Field(
        None, description="folder of the run's credentials (swarmmap secrets; a folder per service, each reads its own): "
                          "every link is mutual TLS and the router enforces the run's access policy; default RUN_DIR/secrets")
    signer: Path | None = Field(
        None, description="folder where the run's signing step publishes its CA certificate and the certificates it "
                          "issues (compose; read-only to the services): a service makes its own key in zenoh.secrets "
                          "and asks for a certificate of the identity it serves")
    signer_requests: Path | None = Field(
        None, description="folder where services leave their certificate requests for the signer (compose: a folder "
                          "they may write, apart from zenoh.signer); unset: zenoh.signer/requests")
    keep_ca: Path | None = Field(
        None, description="swarmmap secrets: keep the run's CA key in this folder (outside zenoh.secrets and the run "
                          "directory) to issue more certificates later; unset: the key is discarded once they are issued")
    stuck_s: float | None = Field(
        None, gt=0, description="how long a session waits on a link that takes nothing before it closes the link (unset: "
                                "2 s for a router alone, so a stuck member cannot hold up the others; 30 s for a router "
                                "linked to other routers, whose slow link is busy, not dead; 60 s for every other service)")
    shared_memory: bool | None = Field(
        None, description="whether Zenoh passes a large message between processes of one machine through shared memory "
                          "(/dev/shm) rather than over the link (unset: Zenoh's default, on). Network namespaces share /dev/shm: "
                          "set it false with up --netns for the emulated links to carry every byte (bench/links.py does)")
    connect_timeout_s: float = Field(
        60.0, gt=0, description="a client session (every service but the router, with TLS) waits this long for the router at start")
    insecure: bool = Field(
        False, description="no TLS, no authentication, no access control: anyone who reaches the router is a member "
                           "(an explicit opt-out; every service warns)")


class RouterSettings(Section):
    """The router service: a Zenoh session in router mode (listens on zenoh.listen, dials zenoh.connect)."""

    ident: str = Field("0", pattern=r"^(0|r[0-9]{1,2})$",
                       description="which of the run's routers this is: 0 (the run's router, or the base host's when each "
                                   "host has its own), r<i> (robot i's host; shared/wire/mesh.py)")
    hosts: list[str] = Field(default_factory=list,
                             description="more names every router's certificate carries: the hosts on which the routers of "
                                         "a run with a router per host reach each other (e.g. a SLURM job's nodes)")


class WorldSettings(Section):
    """The world simulator: floor plan, robots, paths and the simulated LiDAR."""

    floorplan: str = Field("procedural", description="procedural, a CubiCasa5K model.svg, a DiNNO occupancy .png, "
                                                      "or a ROS map_server .yaml")
    waypoints: str | None = Field(None, description="folder of .npy waypoint paths, one per robot (DiNNO normalised "
                                                    "coordinates for a .png plan, metres otherwise); none = plan paths")
    pixels_per_metre: float = Field(100.0, gt=0, description="scale of a .png plan")
    dinno_border_px: int = Field(30, ge=0, description="border of a .png plan forced occupied (DiNNO: 30)")
    export: Path | None = Field(None, description="write plan.stl, occupancy.png, occupancy.npz and a ROS map "
                                                    "(map.yaml, map.pgm) to this folder and exit")
    rooms_x: int = Field(3, ge=1, le=12, description="procedural plan: rooms along x")
    rooms_y: int = Field(2, ge=1, le=12, description="procedural plan: rooms along y")
    room_min_m: float = Field(2.5, gt=0.5, description="procedural plan: smallest room side (m)")
    room_max_m: float = Field(4.5, gt=0.5, description="procedural plan: largest room side (m)")
    wall_thickness_m: float = Field(0.12, gt=0.01, le=1.0, description="wall thickness (m)")
    wall_height_m: float = Field(2.5, gt=0.2, description="extruded wall height (m)")
    door_width_m: float = Field(0.9, gt=0.3, description="door opening width (m)")
    extra_door_prob: float = Field(0.3, ge=0, le=1, description="procedural plan: chance of an extra door between neighbours")
    corridor_width_m: float = Field(1.3, ge=0, description="procedural plan: corridor between the middle rows (0: none)")
    robot_clearance_m: float = Field(0.2, gt=0, description="planned paths keep this far from walls (m)")
    grid_resolution_m: float = Field(0.05, gt=0.005, le=1.0, description="ground-truth grid cell size (m)")
    speed_mps: float = Field(0.22, gt=0, le=5, description="robot speed along its path (m/s)")
    sim_step_s: float = Field(0.1, gt=0, le=1, description="simulation time step (s)")
    time_scale: float = Field(0.0, ge=0, description="simulated seconds per wall second; 0 = as fast as the consumers take it")
    rooms_per_robot: int = Field(0, ge=0, description="planned paths: rooms each robot visits; 0 = about twice its share")
    rooms: list[int] = Field(default_factory=list, description="planned paths: the rooms (numbers as the world logs them) "
                             "robots may visit; empty = all")
    closed_doors: list[int] = Field(default_factory=list, description="doors to close (numbers as the world logs them): "
                                    "the rooms behind them stay unseen")
    closed_door_fraction: float = Field(0.0, ge=0, le=1, description="share of the other doors to close, drawn with the run's seed")
    coverage_spacing_m: float = Field(2.5, gt=0.1, description="planned paths on a plan without room outlines (an image, a "
                                      "ROS map): every reachable free cell lies within this much path of a target (m)")
    lidar_beams: int = Field(360, ge=1, le=4096, description="beams per scan")
    lidar_fov_deg: float = Field(360.0, gt=0, le=360, description="angular range of a scan (deg)")
    lidar_min_range_m: float = Field(0.12, ge=0, description="closest measurable range (m)")
    lidar_max_range_m: float = Field(3.5, gt=0, description="farthest measurable range (m)")
    lidar_height_m: float = Field(0.18, gt=0, description="LiDAR height above the floor (m)")
    lidar_rate_hz: float = Field(5.0, gt=0, le=100, description="scans per simulated second")
    ray_batch: Literal["robot", "all"] = Field(
        "robot", description="one rayTestBatch per robot, or one for all robots' rays (bench/lidar_rays.py: per robot is faster here)")
    val_scans: int = Field(300, ge=1, description="validation scans from random free poses")
    val_beams: int = Field(60, ge=1, description="beams per validation scan")
    wait_for: list[Literal["lidar", "learner", "recorder", "observer"]] = Field(
        default_factory=lambda: ["lidar", "learner", "recorder"],
        description="services that must be alive before the robots drive (lidar and learner: one per robot); "
                    "add observer when one records the run, so that it sees every pose and scan")
    wait_for_consumers_s: float = Field(120.0, ge=0, description="how long to wait for the services of wait_for before driving anyway")
    drive: bool = Field(True, description="drive the robots; false = only serve the map (when the streamers replay recordings)")
    dataset: list[str] = Field(default_factory=list, description="real LiDAR logs to serve instead of a floor plan: CARMEN logs "
                               "(.log, .clf, gzipped or not), ROS 1 bags, rosbag2 folders or .mcap files; each gives robots / "
                               "(number of logs) robots, contiguous segments of its trajectory (docs/datasets.md)")
    dataset_pose: Literal["auto", "log", "odom", "tf"] = Field(
        "auto", description="the scans' poses: a CARMEN log's laser-line pose (log: its corrected poses) or odometry; a bag's "
                            "odometry topic or tf; auto = log for CARMEN, odometry when a bag has the topic, else tf")
    dataset_scan_topic: str = Field("/scan", description="a bag's sensor_msgs/LaserScan topic")
    dataset_odom_topic: str = Field("/odom", description="a bag's nav_msgs/Odometry topic")
    dataset_fixed_frame: str | None = Field(None, description="tf poses: the fixed frame (none: map when the bag has it, else odom)")
    dataset_holdout_every: int = Field(10, ge=2, description="every k-th scan of each robot is held out: never trained on, the "
                                                             "validation set's beams")
    dataset_margin_m: float = Field(1.0, ge=0, description="the map reaches this far beyond the farthest hit and pose (m)")

    @field_validator("dataset", mode="before")
    @classmethod
    def _dataset_as_list(cls, value: Any) -> Any:
        return [value] if isinstance(value, (str, Path)) else value

    @model_validator(mode="after")
    def _ranges(self) -> WorldSettings:
        if self.room_min_m > self.room_max_m:
            raise ValueError(f"room_min_m ({self.room_min_m}) must not exceed room_max_m ({self.room_max_m})")
        if self.lidar_min_range_m >= self.lidar_max_range_m:
            raise ValueError("lidar_min_range_m must be below lidar_max_range_m")
        if self.door_width_m >= self.room_min_m - 2 * self.wall_thickness_m:
            raise ValueError("door_width_m must be narrower than the smallest room")
        return self


def parse_tuples(text: str, count: int | None, names: tuple[str, ...], what: str, noun: str = "value"
                 ) -> list[tuple[float, ...]]:
    """``"a,b;a,b;..."``: tuples of finite numbers named ``names``, ``count`` of them (None: any number);
    a ValueError naming ``what`` and what is wrong."""
    form = ",".join(names)
    parts = [p for p in text.replace(" ", "").split(";") if p]
    if count is not None and len(parts) != count:
        raise ValueError(f"{what} gives {len(parts)} {noun}(s) for {count} robot(s) (\"{form};{form};...\")")
    out = []
    for p in parts:
        try:
            values = tuple(float(v) for v in p.split(","))
        except ValueError:
            values = ()
        if len(values) != len(names):
            raise ValueError(f"{what}: {p!r} is no \"{form}\"" + (" pair" if len(names) == 2 else ""))
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"{what}: {p!r} is not finite")
        out.append(values)
    return out


def parse_starts(text: str, robots: int) -> list[tuple[float, float]]:
    """``"x,y;x,y;..."`` (metres, the plan's frame) as one (x, y) per robot; a ValueError naming what is wrong."""
    return parse_tuples(text, robots, ("x", "y"), "explore.starts", "start")  # type: ignore[return-value]


def parse_extent(text: str) -> tuple[float, float, float, float]:
    """``"xmin,ymin,xmax,ymax"`` (metres); a ValueError naming what is wrong."""
    boxes = parse_tuples(text, None, ("xmin", "ymin", "xmax", "ymax"), "ros2.extent")
    if len(boxes) != 1:
        raise ValueError(f"ros2.extent: {text!r}: one box \"xmin,ymin,xmax,ymax\"")
    box = boxes[0]
    if not (box[2] > box[0] and box[3] > box[1]):
        raise ValueError(f"ros2.extent: {text!r}: xmax must exceed xmin and ymax ymin")
    return box  # type: ignore[return-value]


BUDGET_UNITS = {"": 1, "K": 1024, "M": 1024**2, "G": 1024**3}


@dataclass(frozen=True)
class Budget:
    """A robot's budget (``up.budget``): memory in bytes and CPUs (cores, fractions allowed)."""

    memory_bytes: int
    cpus: float

    def __str__(self) -> str:
        return f"{self.memory_bytes / 1024**2:.0f} MiB, {self.cpus:g} CPU"


def parse_budget(text: str) -> Budget:
    """``"512M,0.5"`` as a Budget; a ValueError naming what is wrong."""
    found = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([KMG]?)i?B?\s*,\s*([0-9]*\.?[0-9]+)\s*", text, re.IGNORECASE)
    if not found:
        raise ValueError(f"{text!r} is no \"MEMORY,CPUS\" such as 512M,0.5 (K, M, G: powers of 1024)")
    memory = int(float(found[1]) * BUDGET_UNITS[found[2].upper()])
    cpus = float(found[3])
    if memory < 32 * 1024**2 or not 0.01 <= cpus <= 1024 or not math.isfinite(cpus):
        raise ValueError(f"{text!r}: give at least 32M of memory and between 0.01 and 1024 CPUs")
    return Budget(memory, cpus)


def parse_budgets(text: str, robots: int | None) -> list[Budget]:
    """``up.budget``: one ``"MEMORY,CPUS"`` for every robot, or one per robot separated by ``;``
    (``"512M,0.5;1G,1"``); ``robots`` of them (None: any number); a ValueError naming what is wrong."""
    parts = [p for p in text.split(";") if p.strip()]
    if not parts:
        raise ValueError(f"{text!r} gives no budget")
    budgets = [parse_budget(p) for p in parts]
    if robots is not None and len(budgets) == 1:
        return budgets * robots
    if robots is not None and len(budgets) != robots:
        raise ValueError(f"{text!r} gives {len(budgets)} budgets for {robots} robot(s): one for every robot, or one each")
    return budgets


class ExploreSettings(Section):
    """Exploration: robots that choose where to drive from what their team has learned (docs/exploration.md)."""

    policy: Literal["none", "planned", "uncertainty", "frontier"] = Field(
        "none", description="none: the robots drive their planned paths once, then the learners train (the paper's "
                            "setting); planned: the same paths, driven in legs while the learners train; uncertainty: "
                            "each robot's next goal where its own model's std (or entropy) is highest per metre of path; "
                            "frontier: the nearest frontier of a log-odds grid of its own and its neighbours' scans")
    starts: str = Field("", description="start positions \"x,y;x,y;...\" in metres in the plan's frame, one per robot; "
                                        "empty: spread over the plan's free space by the seed (planned paths: their own start)")
    decide_every: int = Field(10, ge=1, description="training rounds between two goals: a robot's goal for leg L is "
                                                     "chosen at round L x decide_every")
    leg_s: float = Field(8.0, gt=0, description="simulated seconds a robot drives towards its goal in one leg")
    distance_m: float = Field(60.0, gt=0, description="each robot's distance budget (m): it stops once it has driven this far")
    stall_legs: int = Field(4, ge=1, description="the drive stops when the team's coverage grew less than stall_gain "
                                                 "over this many legs")
    stall_gain: float = Field(0.005, ge=0, description="see stall_legs (a share of the reachable free space)")
    separation_m: float = Field(1.5, ge=0, description="a robot passes over goals within this distance of a teammate's")
    min_travel_m: float = Field(1.0, ge=0, description="a robot passes over goals nearer than this much path (it would "
                                                       "see nothing new there) while another is left")
    clearance_m: float = Field(0.2, gt=0, description="paths to goals keep this far from what the robot believes occupied (m)")
    map_resolution_m: float = Field(0.1, gt=0.01, description="cell size of the map a robot chooses its goal on (m)")
    information: Literal["std", "entropy"] = Field("std", description="uncertainty: what a cell's observation is worth, "
                                                                      "the model's std or its predictive entropy")
    mc_samples: int = Field(16, ge=2, description="uncertainty: stochastic passes for the std map a goal is chosen on")
    seen_weight: float = Field(0.1, ge=0, le=1, description="uncertainty: what a cell's std counts for where the robot (or, "
                                                            "with learner.unseen_weight, a teammate) has data on it: a "
                                                            "scan there would mostly see a wall's edge again")
    min_gain: float = Field(1.0, ge=0, description="uncertainty: a robot whose best scan would bring no more than this "
                                                  "(summed std) has nowhere left to go")
    goal_wait_s: float = Field(120.0, gt=0, description="how long the world waits for a robot's goal (and a robot for "
                                                        "its lower-numbered neighbours') before it goes on without")

    @property
    def active(self) -> bool:
        """Whether the robots drive in legs while the learners train."""
        return self.policy != "none"


class LidarSettings(Section):
    """A LiDAR streamer: turns its robot's scans into labelled training points."""

    robot: int | None = Field(None, ge=0, description="which robot this streamer serves (0..robots-1)")
    samples_per_beam: int = Field(12, ge=1, le=1000, description="free points sampled along each beam")
    sampling: Literal["fixed", "uniform"] = Field(
        "fixed", description="free samples at fixed spacing over the beam's full length (DiNNO) or uniformly at random up to the hit")
    occupied_depth_m: float = Field(0.03, ge=0, le=0.5, description="how far behind the surface the occupied point lies (m)")
    range_noise_std_m: float = Field(0.01, ge=0, le=1, description="Gaussian range noise (m); 0 = ideal")
    dropout_prob: float = Field(0.01, ge=0, lt=1, description="chance that a beam returns nothing (no points from it)")
    free_on_max_range: bool = Field(True, description="a beam with no return within max range labels its whole length free")
    record: str | None = Field(None, description="record the served stream to this file ({robot} is replaced by the robot id)")
    replay: str | None = Field(None, description="serve this recording instead of live scans ({robot} is replaced by the robot id)")
    replay_speed: float = Field(0.0, ge=0, description="replay at this multiple of the recorded rate; 0 = as fast as the learner takes it")
    replay_incomplete: bool = Field(False, description="accept a recording whose recorder crashed (a .partial file)")


class LearnerSettings(Section):
    """A learner: DiNNO consensus training of an implicit occupancy network (Algorithm 1)."""

    robot: int | None = Field(None, ge=0, description="which robot this learner serves (0..robots-1)")
    transport: Literal["zenoh", "inproc"] = Field(
        "zenoh", description="Algorithm 1 over Zenoh (one process per robot) or in memory (one process serves every robot)")
    rounds: int = Field(200, ge=1, description="communication rounds of Algorithm 1 (DiNNO outer iterations)")
    primal_iterations: int = Field(5, ge=1, description="optimizer steps per round")
    batch_size: int = Field(4096, ge=1, description="training points per optimizer step")
    optimizer: Literal["adam", "adamw", "sgd"] = Field("adam", description="primal optimizer")
    lr_start: float = Field(1e-3, gt=0, description="primal learning rate at round 0")
    lr_finish: float = Field(1e-4, gt=0, description="primal learning rate at the last round")
    lr_schedule: Literal["constant", "linear", "log"] = Field("log", description="primal learning-rate schedule")
    rho_init: float = Field(0.3, ge=0, description="initial ADMM penalty rho")
    rho_growth: float = Field(1.0004, ge=1.0, description="rho is multiplied by this each round")
    algorithm: AlgorithmKind = Field(
        "dinno", description="DiNNO, or a baseline: DiNNO's DSGD and DSGT, individual (no communication), "
                             "centralized (one model on every robot's data; needs transport inproc)")
    graph: Literal["complete", "ring", "file", "disk"] = Field(
        "complete", description="communication graph: complete, ring, an edge-list file, or DiNNO's disk graph")
    graph_file: Path | None = Field(None, description="graph = file: YAML/JSON list of [i, j] edges")
    comm_radius_m: float = Field(15.0, gt=0, description="graph = disk: robots within this distance talk (m)")
    model: str = Field(
        "fourier", description="the network, a model plug-in (swarmmap plugins lists those installed): fourier (DiNNO's "
                                "deterministic FourierNet), bnn (the paper's Bayesian network) or dropout (a FourierNet with "
                                "MC dropout, a baseline for the BNN's uncertainty), or one from another package")
    model_shape: list[int] = Field(
        default_factory=lambda: [2, 256, 64, 64, 64, 1],
        description="layer widths: input 2, sine layer, hidden ReLU layers (Bayesian for bnn), output 1")
    regularization: Literal["uniform-l2", "separate-l2", "separate-kl"] = Field(
        "separate-kl", description="bnn consensus regularisation (the paper's Figure 7); separate-kl is Algorithm 2")
    kl_weight: float = Field(5e-3, ge=0, description="bnn: weight of the KL to the prior in the loss (equation 7)")
    prior_sigma: float = Field(0.1, gt=0, description="bnn: standard deviation of the Gaussian prior")
    bnn_rho_init: float = Field(-5.0, description="bnn: initial rho of every weight and bias (sigma = softplus(rho))")
    bnn_local_reparam: bool = Field(False, description="bnn: train with the local reparameterisation trick (each example's "
                                                       "activations drawn from their Gaussian, not one weight draw a batch)")
    dropout_p: float = Field(0.1, ge=0, lt=1, description="dropout: probability of dropping a unit, in training and in "
                                                            "each of the mc_samples passes of a map")
    w_mu: float = Field(1.0, ge=0, description="Algorithm 2: W_mu, the mu-regularisation weight, as a multiple of rho")
    w_rho: float = Field(1.0, ge=0, description="Algorithm 2: W_rho, the rho-regularisation weight, as a multiple of rho")
    mc_samples: int = Field(50, ge=1, description="bnn, dropout: forward passes per point for the mean and std maps")
    unseen_weight: float = Field(
        0.0, ge=0, description="bnn: weight of the noise-contrastive prior on points away from the data (0: off): "
                               "the network's draws should disagree there as N(0, unseen_prior_std^2) logits do")
    unseen_prior_std: float = Field(3.0, gt=0, description="bnn: std of the logit prior at points away from the data")
    unseen_points: int = Field(256, ge=1, description="bnn: points away from the data per optimizer step")
    unseen_draws: int = Field(4, ge=2, description="bnn: weight draws per step at those points")
    unseen_margin_m: float = Field(0.25, gt=0, description="bnn: a point is away from the data when farther than this "
                                                          "from every training point (of the robot or, with "
                                                          "share_coverage, of a teammate heard of)")
    share_coverage: bool = Field(True, description="bnn with unseen_weight: States carry the cells their senders "
                                                   "know to be covered, so no robot teaches its network to doubt a "
                                                   "place a teammate mapped")
    optimizer_per_round: bool = Field(True, description="re-create the optimizer every round (DiNNO's default) or keep it")
    siren_scale: float = Field(5.0, gt=0, description="frequency scale of the sine layer (inputs in metres from the map centre)")
    data: Literal["offline", "online"] = Field(
        "offline", description="train once the traversal is done (the paper), or from the start on a sliding window "
                               "of recent scans (DiNNO)")
    window_scans: int = Field(800, ge=1, description="online: scans in the sliding window (DiNNO: 800)")
    eval_every: int = Field(10, ge=1, description="evaluate and publish Metrics every this many rounds (and at least once a minute)")
    checkpoint_every: int = Field(50, ge=0, description="write RUN_DIR/checkpoints/robot-<i>.pt every this many rounds (0: never); "
                                                        "a learner started on a run directory with a checkpoint resumes from it")
    map_resolution_m: float | None = Field(None, gt=0.005, description="cell size of the saved maps (m); none: the "
                                                                   "ground truth's (world.grid_resolution_m)")
    collect_timeout_s: float = Field(600.0, gt=0, description="give up waiting for the end of the traversal after this long")
    peer_timeout_s: float = Field(120.0, gt=0, description="fail when this node has had no neighbour (all left or silent) for this long")
    max_state_distance: float = Field(
        0.5, gt=0, description="refuse a neighbour's State whose parameters lie farther from this node's own than this "
                               "multiple of their norm (and constant ones, e.g. all zero): defence against a hostile member")
    rejoin_wait_s: float = Field(10.0, ge=0, description="wait this long for a neighbour whose liveliness token vanished "
                                                       "(a launcher restarts it) before going on without it")
    silent_after_s: float = Field(30.0, gt=0, description="leave a neighbour out of the round when it has been silent "
                                                         "this long (it is taken back when it sends again)")
    resend_after_s: float = Field(2.0, gt=0, description="resend this round's messages after this long without progress "
                                                         "(then after twice as long each time, up to 8 times it)")
    inbox_limit: int = Field(64, ge=4, description="messages that may wait from any one neighbour; a flood beyond this is "
                                                   "dropped (Algorithm 1 resends what an honest neighbour lost)")
    consensus: str = Field(
        "dinno", description="how hard each parameter is pulled towards each neighbour, a consensus plug-in (swarmmap "
                             "plugins lists those installed): dinno (alike), ramen (RAMEN's gradient counts, sent in the "
                             "State), sigma (the BNN's own posterior sigma; model bnn), dgvi (DGVI's precision-weighted "
                             "pool of the neighbourhood's Gaussians; model bnn), or one from another package")
    consensus_options: dict[str, Any] = Field(
        default_factory=dict, description="the consensus rule's own knobs, as its plug-in defines them (e.g. "
                                          "--set 'learner.consensus_options={\"pull\": 0.5}'); the built-in rules take none")
    robust: bool = Field(
        True, description="a member that lies can neither pass for honest nor pull the team far: each round's "
                          "neighbour States are judged together, block by block, against the round's honest spread; "
                          "each link's pull and dual are bounded; sigma trusts a neighbour's certainty at most "
                          "sigma_max_weight x DiNNO's pull (false: DiNNO's consensus with only each State's own checks)")
    robust_spread_factor: float = Field(
        4.0, gt=1, description="robust: a State one of whose blocks lies farther from this node's than this many times "
                               "the round's honest spread (the median over the neighbours) is refused")
    robust_pull_factor: float = Field(
        3.0, gt=0, description="robust: each link's pull and dual, per block, at most this many times the median over "
                               "the links")
    sigma_max_weight: float = Field(
        1.5, gt=1, le=2, description="sigma with robust: a node's pull on a mean is at most this many times DiNNO's "
                                     "however sure the neighbour says it is (2: as sure as it says)")
    consensus_min_weight: float = Field(
        0.05, gt=0, le=1, description="sigma: a node's pull on a parameter stays within [this, 2 - this] x DiNNO's")
    sigma_memory_rounds: int = Field(
        100, ge=0, description="sigma: a neighbour's newest State keeps pulling for up to this many rounds after it "
                               "came, its sigma widened by how far the parameters drift a round (0: only the rounds "
                               "it was meant for, as dinno)")
    exchange_every: int = Field(1, ge=1, description="exchange States every this many rounds; the rounds between train "
                                                     "against the neighbours' last States (rounds must be a multiple)")
    exchange_every_s: float = Field(0.0, ge=0, description="exchange on a clock instead: send the State every this many "
                                                         "seconds and train without waiting for anyone, taking the "
                                                         "neighbours' States as they come (0: by rounds, Algorithm 1)")
    stale_rounds: int = Field(0, ge=0, description="keep pulling towards a neighbour's newest State for this many rounds "
                                                  "when no newer one comes (0: the rounds it was meant for only, i.e. "
                                                  "exchange_every; on a clock, until the neighbour goes silent)")
    round_wait_s: float = Field(0.0, ge=0, description="poor links: after this long in a round, go on with the neighbours' "
                                                       "States that arrived (0: wait for every neighbour, as Algorithm 1)")
    compression: str = Field(
        "none", description="State encoding on the wire, a compression plug-in (swarmmap plugins lists those installed): "
                            "none (float32), f16 (half precision), bf16 (bfloat16), or differences with error feedback: "
                            "topk, sign (the sign of every value with a scale per 256), quant (every value quantised to "
                            "quant_bits with a step per 256), lowrank (each weight matrix as a rank-lowrank_rank product), "
                            "or one from another package")
    compression_options: dict[str, Any] = Field(
        default_factory=dict, description="the compression's own knobs, as its plug-in defines them; the built-in "
                                          "compressions take none (their knobs are the fields below)")
    slow_link_compression: str = Field(
        "none", description="with compression none over Zenoh: when a learner's rounds wait mostly for its neighbours' "
                             "States (a median wait twice its training, at least 0.25 s, over 20 rounds), its links set "
                             "the pace and its States go out with this compression from then on, said in its log (none: "
                             "never; quant suits a radio link; a switch depends on timing, so two such runs may differ)")
    topk_density: float = Field(0.01, gt=0, le=1, description="topk: share of the values each State carries")
    quant_bits: int = Field(3, ge=2, le=8, description="quant: bits a value before Huffman coding (2-8)")
    lowrank_rank: int = Field(1, ge=1, le=64, description="lowrank: rank of each weight matrix's update (PowerGossip; "
                                                              "measured to lose consensus under Adam: docs/results.md)")
    keyframe_every: int = Field(100, ge=1, description="topk, sign, quant, lowrank: every this many States, one carries the whole "
                                                       "vector (quant: at 16 bits)")
    torch_threads: int = Field(1, ge=1, description="CPU threads per learner process")
    compute_slots: int | None = Field(
        None, ge=0, description="at most this many learner processes of one host train at once (lock files in its "
                                "temporary directory; 0: no limit; unset: swarmmap up sets the host's cores when it "
                                "starts more learners than that, else no limit)")
    device: str = Field("auto", description="torch device: auto (cuda when available), cpu, cuda, cuda:1 ...")

    @field_validator("model_shape", mode="before")
    @classmethod
    def _shape_as_typed(cls, value: Any) -> list[int]:
        return parse_shape(value)

    @field_validator("consensus")
    @classmethod
    def _installed_rule(cls, value: str) -> str:
        return installed("consensus", value)

    @field_validator("model")
    @classmethod
    def _installed_model(cls, value: str) -> str:
        return installed("models", value)

    @field_validator("compression", "slow_link_compression")
    @classmethod
    def _installed_compression(cls, value: str) -> str:
        return installed("compressions", value)

    @model_validator(mode="after")
    def _shape(self) -> LearnerSettings:
        if self.algorithm == "centralized" and self.transport != "inproc":
            raise ValueError("algorithm centralized trains one model in one process: set transport to inproc")
        if self.graph == "file" and self.graph_file is None:
            raise ValueError("graph file needs graph_file")
        if len(self.model_shape) < 3 or self.model_shape[0] != 2 or self.model_shape[-1] != 1:
            raise ValueError(f"model_shape must start with 2, end with 1 and have a hidden layer, got {self.model_shape}")
        if any(w < 1 for w in self.model_shape):
            raise ValueError("model_shape widths must be positive")
        consensus_fits(self)
        compression_fits(self.compression, self.compression_options)
        if self.unseen_weight > 0 and self.model != "bnn":
            raise ValueError("unseen_weight (the noise-contrastive prior on unseen space) shapes a Bayesian network's "
                             "weight draws: it needs model bnn")
        if self.consensus != "dinno" and self.algorithm != "dinno":
            raise ValueError(f"consensus {self.consensus} weighs DiNNO's consensus: it needs algorithm dinno")
        if self.exchange_every_s > 0 and (self.algorithm != "dinno" or self.exchange_every != 1):
            raise ValueError("exchange_every_s (exchange on a clock) runs DiNNO's update against the newest States: it "
                             "needs algorithm dinno and exchange_every 1")
        if self.graph == "disk" and self.data == "online" and self.round_wait_s == 0 and self.exchange_every_s == 0:
            raise ValueError("a disk graph with online data changes while the robots drive: set round_wait_s > 0 (a "
                             "neighbour out of range sends nothing the round could wait for)")
        if self.rounds % self.exchange_every:
            raise ValueError(f"rounds ({self.rounds}) must be a multiple of exchange_every ({self.exchange_every})")
        return self


class ObserverSettings(Section):
    """The Rerun observer: each learner's mean and std maps, the robots, scans and curves, live."""

    map_resolution_m: float = Field(0.1, gt=0.005, description="cell size of the observer's mean and std maps (m)")
    mc_samples: int = Field(50, ge=1, description="Monte-Carlo forward passes per map cell for a bnn's mean and std")
    map_every: int = Field(0, ge=0, description="map a learner's States of every this many rounds, and its final one "
                                                "(0: learner.eval_every, the rounds its metrics are reported for)")
    std_max: float = Field(0.25, gt=0, le=0.5, description="std that gets the top colour of the std colormap")
    scan_every: int = Field(1, ge=1, description="log every n-th scan of each robot (poses, trajectory, scan points)")
    save: Path | None = Field(None, description="write the recording to this .rrd file (swarmmap up: RUN_DIR/recording.rrd)")
    mcap: Path | None = Field(None, description="also write the run as a rosbag2 folder in MCAP here: every map as a "
                                                "nav_msgs/OccupancyGrid, the scans, poses and tf (docs/datasets.md#a-run-as-a-rosbag2)")
    spawn: bool = Field(False, description="start a local Rerun viewer and stream to it")
    connect: str | None = Field(None, description="stream to a running viewer at this gRPC URL, "
                                                  "e.g. rerun+http://127.0.0.1:9876/proxy")
    serve_web: bool = Field(False, description="serve the web viewer (for containers and remote machines)")
    bind: str = Field("127.0.0.1", description="serve_web: the address the web viewer and its gRPC server listen on "
                                               "(another than loopback opens the run's maps and scans to the network: warned)")
    web_port: int = Field(9090, ge=0, le=65535, description="serve_web: port of the web viewer page")
    grpc_port: int = Field(9876, ge=0, le=65535, description="serve_web: port of the gRPC server the page connects to")
    torch_threads: int = Field(1, ge=1, description="CPU threads for map evaluation")
    device: str = Field("auto", description="torch device for map evaluation: auto (cuda when available), cpu, cuda ...")
    map_dtype: Literal["auto", "fp32", "bf16"] = Field(
        "auto", description="precision of the map products: auto (bf16 where the device multiplies it in hardware: "
                            "a GPU, a CPU with AMX or AVX512-BF16; fp32 elsewhere), fp32 or bf16")


class RecorderSettings(Section):
    """The recorder: writes the run directory and says when the run is over (``run/done``)."""

    start_timeout_s: float = Field(600.0, gt=0, description="fail the run when a learner has not come alive after this long")
    linger_s: float = Field(30.0, ge=0, description="once the run is over, how long to wait for the other services to leave")
    rejoin_timeout_s: float = Field(20.0, ge=0, description="a learner, lidar or the world that left while needed fails the run "
                                                             "unless it is back within this long (0: at once)")
    unreachable_timeout_s: float = Field(600.0, ge=0, description="with a router per host: a service whose host's router "
                                         "left too is unreachable (its host or links lost, a partition), not crashed; the run "
                                         "waits this long for it to come back before it fails")
    stall_timeout_s: float = Field(600.0, gt=0, description="fail the run when, once every learner is alive, it makes no "
                                                            "progress (no new Metrics, no scans) for this long, naming the "
                                                            "learners that hold it up")


class FaultSettings(Section):
    """Faults injected on Algorithm 1's links, per link [sender, receiver] (tests, bench/, experiments on poor links)."""

    link_success: float = Field(1.0, gt=0, le=1, description="probability that a State or RoundComplete reaches its neighbour")
    duplicate: float = Field(0.0, ge=0, le=1, description="probability that a message arrives twice")
    delay_s: float = Field(0.0, ge=0, description="extra delay of each message, uniform in [0, delay_s] (reorders them)")
    links: list[list[int]] = Field(default_factory=list, description="the faulty links as [sender, receiver] pairs; empty: every link")
    seed: int = Field(0, ge=0, description="seed of the fault draws")
    per_round: bool = Field(False, description="draw link_success once per link and round, for both directions and "
                                               "every message of the round (a radio link up or down), not per message")
    attack: str = Field(
        "none", description="what the robots of attackers tell their neighbours instead of their States (each with its "
                            "own credentials), an attack plug-in (swarmmap plugins lists those installed): ratchet (a random "
                            "direction at 0.45 of the norm, anew each round), signflip (the output layer negated), scale "
                            "(x 1.45), noise (0.05 of the norm), sigma (a BNN's rho lowered by 2, its means moved), stall "
                            "(RoundCompletes, never a State), equivocate (two States a round), far-future (States of three "
                            "rounds ahead), repeat (its first State again and again), bomb (object bombs), metrics-flood "
                            "(Metrics of a new round as fast as it can for 2 s); none: no attack; see "
                            "services/learner/attacks.py")
    attackers: list[int] = Field(default_factory=list, description="the robots whose learners attack (attack); empty: none")

    @field_validator("attack")
    @classmethod
    def _installed_attack(cls, value: str) -> str:
        return value if value == "none" else installed("attacks", value)


class UpSettings(Section):
    """The launcher ``swarmmap up``."""

    record: Path | None = Field(None, description="record every robot's LiDAR stream into this folder (robot-<i>.swrec)")
    replay: Path | None = Field(None, description="run from the recordings in this folder instead of the world's robots")
    budget: str = Field("", description="every robot's services (lidar, learner, and its router with a router per host) "
                                        "held to \"MEMORY,CPUS\", e.g. 512M,0.5 (or one per robot: \"512M,0.5;1G,1;...\"), in "
                                        "a Linux control group each (root or a delegated cgroup subtree); a run whose learner "
                                        "cannot fit is refused at start naming the smallest budget that fits; each robot's "
                                        "learner fits itself to it (docs/deployment.md); peaks go to summary.json. Empty: none")

    @field_validator("budget")
    @classmethod
    def _budget(cls, value: str) -> str:
        if value:
            parse_budgets(value, None)
        return value

    @model_validator(mode="after")
    def _one_source(self) -> UpSettings:
        if self.record is not None and self.replay is not None:
            raise ValueError("record and replay exclude each other: choose one")
        return self

    observer: bool = Field(True, description="start the Rerun observer (it saves RUN_DIR/recording.rrd unless observer.save "
                                                          "says otherwise)")
    viewer: bool = Field(False, description="also open a local Rerun viewer (observer.spawn)")
    mcap: bool = Field(False, description="the observer also writes the run as a rosbag2 in MCAP, RUN_DIR/bag (observer.mcap)")
    stop_grace_s: float = Field(10.0, gt=0, description="how long services get to stop on SIGTERM before SIGKILL")
    observer_grace_s: float = Field(120.0, gt=0, description="how long the observer gets to map the final States and close "
                                                             "its recording once the learners are done")
    learner_grace_s: float = Field(120.0, gt=0, description="how long a learner gets to write its model and maps once the "
                                                            "run is over (an inproc learner writes every robot's)")
    start_timeout_s: float = Field(120.0, gt=0, description="how long to wait for services to come alive")
    restarts: int = Field(3, ge=0, description="restart a crashed learner, lidar or world up to this many times each "
                                               "(it resumes from its checkpoint and rejoins); 0: a crash ends the run")
    resume: bool = Field(False, description="go on with the interrupted run in run_dir (its checkpoints, metrics and logs); "
                                            "without it a run directory that holds a run is refused")
    routers: Literal["one", "per-host"] = Field(
        "one", description="one: a router for the run, every service its client; per-host: a router on each host (the "
                           "base and each robot's), each host's services clients of their own, the routers linked as "
                           "router_links says (no single point of failure; docs/deployment.md)")
    router_links: str = Field("ring", description="with per-host routers: ring (each host to two others), full, star, or "
                                                  "links such as base-r0,r0-r1,r1-base")
    netns: bool = Field(False, description="run each robot's services (and its router) in a network namespace of its own, "
                                           "joined by a bridge: a multi-host team on one machine (root; implies per-host "
                                           "routers); removed when the run ends")
    link_rate: str | None = Field(None, pattern=r"^[0-9]+(\.[0-9]+)?([kmg]?bit)$",
                                  description="with netns: each robot host's link rate, each way (tc tbf), e.g. 100mbit, "
                                              "10mbit, 1mbit")
    link_loss: float = Field(0.0, ge=0, lt=1, description="with netns: share of packets each robot host's link loses, each "
                                                          "way (nftables), e.g. 0.01")

    @model_validator(mode="after")
    def _links_need_netns(self) -> UpSettings:
        if (self.link_rate is not None or self.link_loss) and not self.netns:
            raise ValueError("link_rate and link_loss shape the links between network namespaces: add --netns")
        return self


class Ros2Settings(Section):
    """``swarmmap ros2``: a team of ROS 2 robots, their scans heard on ROS 2, their maps published there."""

    namespaces: list[str] = Field(default_factory=list, description="one robot per namespace: its sensor_msgs/LaserScan on "
                                  "/<namespace>/<scan_topic>, nav_msgs/Odometry on /<namespace>/<odom_topic>, maps published "
                                  "on /<namespace>/map (and map_std)")
    scan_topic: str = Field("scan", description="each robot's LaserScan topic under its namespace")
    odom_topic: str = Field("odom", description="each robot's Odometry topic under its namespace (the LiDAR's pose)")
    idle_s: float = Field(5.0, gt=0, description="not exploring: the robots' input is over once no robot sent a scan for "
                                                 "this long")
    wait_s: float = Field(600.0, gt=0, description="how long to wait for every robot's first scans (with odometry) before "
                                                   "refusing")
    max_input_s: float = Field(3600.0, gt=0, description="the input is over after this long, however busy (a publisher "
                                                         "that never stops cannot hold it open)")
    max_scans: int = Field(200_000, ge=1, description="scans kept per robot; beyond them its further scans are dropped, "
                                                      "counted and said once")
    publish: bool = Field(False, description="the observer publishes every robot's maps and the team's /map on ROS 2 "
                                             "(swarmmap ros2 sets it)")
    live: bool = Field(False, description="the world is the ROS 2 robots themselves: it hears their scans live and, "
                                          "exploring, sends their goals (swarmmap ros2 sets it)")
    extent: str = Field("", description="the area the robots map, \"xmin,ymin,xmax,ymax\" in metres in the shared frame; "
                                        "empty: what the robots' first scans saw, plus world.dataset_margin_m (exploring "
                                        "robots need it: they go where nobody has seen)")
    initial_poses: str = Field("", description="each robot's odometry origin in the shared frame, \"x,y,yaw;...\" "
                                               "(metres, radians; one per namespace); empty: the odometry frames are the "
                                               "shared frame. swarmmap ros2 publishes map -> each robot's odometry frame")
    warmup_s: float = Field(2.0, gt=0, description="the first seconds of each robot's scans, heard before the team "
                                                   "starts: the map's extent (unless given), the held-out validation set "
                                                   "and, exploring, the scans its first goals are chosen from")
    unknown_std: float = Field(0.2, gt=0, description="the published maps say -1 (unknown) where the model's std is at "
                                                      "least this, as where no beam went")
    serve_s: float = Field(0.0, ge=0, description="after the team finished, keep serving its final maps this long "
                                                  "(0: until Ctrl-C)")

    @field_validator("namespaces")
    @classmethod
    def _names(cls, value: list[str]) -> list[str]:
        names = [v.strip("/") for v in value]
        bad = [v for v in names if not v or not all(part.replace("_", "a").isalnum() and not part[0].isdigit()
                                                       for part in v.split("/"))]
        if bad:
            raise ValueError(f"{bad}: a ROS namespace is names of letters, digits and _ (not starting with a digit), "
                             "joined by /")
        if len(set(names)) < len(names):
            raise ValueError("namespaces must differ: one robot each")
        return names

    @model_validator(mode="after")
    def _frames(self) -> Ros2Settings:
        if self.extent:
            parse_extent(self.extent)
        if self.initial_poses:
            parse_tuples(self.initial_poses, len(self.namespaces) or None, ("x", "y", "yaw"), "ros2.initial_poses", "pose")
        return self

    def poses(self) -> list[tuple[float, float, float]] | None:
        """Each robot's odometry origin in the shared frame (``initial_poses``), or None."""
        if not self.initial_poses:
            return None
        return parse_tuples(self.initial_poses, len(self.namespaces), ("x", "y", "yaw"), "ros2.initial_poses", "pose")  # type: ignore[return-value]
