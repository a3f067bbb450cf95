"""The settings that change what a run computes, which a resumed run must share with the run it resumes.

A learner refuses to resume from a checkpoint, or to train on a training-points file, written
with another fingerprint (it names the settings that differ); the launchers use the same
fingerprint to tell whether a run directory holds this run or another one.

Every config field counts unless :data:`NOT_COUNTED` names it: those only say where and how the
services run (names, places, connections, timeouts, threads, devices, log level, who watches),
never what the learners compute. :data:`COUNTED` names the fields that count, so that
``tests/shared/run/test_fingerprint.py`` fails when a field is added without being put in one of the
two (an unclassified field counts: a refused resume is safe, a wrong one is not).

    fp = settings_fingerprint(cfg)              # {"learner.lr_start": 0.001, ...}
    fingerprint_diff(old, fp)                   # "learner.lr_start 0.001 there, 0.002 here"
"""

from __future__ import annotations

from pathlib import Path

from swarmmap.shared import plugins
from swarmmap.shared.run.config import RunConfig

CHECKPOINT_FORMAT = 3

# Fields that do not change what a run computes, by section ("" is the top level).
NOT_COUNTED: dict[str, tuple[str, ...]] = {
    # names and places (a preset is only the fields it sets, which count one by one), verbosity
    "": ("preset", "run_id", "key_prefix", "run_dir", "label", "log_level"),
    # how sessions find each other, authenticate and how long a stuck link is borne
    "zenoh": ("mode", "connect", "listen", "multicast_scouting", "config_file", "secrets", "connect_timeout_s", "insecure",
              "signer", "signer_requests", "keep_ca", "stuck_s", "shared_memory"),
    "router": ("ident", "hosts"),
    # exporting the plan and exiting; the pace of the simulation and who it waits for (the scans are the same)
    "world": ("export", "time_scale", "wait_for", "wait_for_consumers_s"),
    # which robot a streamer serves, recording what it serves, the pace of a replay
    "lidar": ("robot", "record", "replay_speed"),
    # which robot a learner serves, how often it checkpoints, timeouts, floods, threads, slots, devices
    "learner": ("robot", "checkpoint_every", "collect_timeout_s", "peer_timeout_s", "rejoin_wait_s", "silent_after_s",
                "resend_after_s", "inbox_limit", "torch_threads", "compute_slots", "device"),
    # the observer only watches
    "observer": ("map_resolution_m", "mc_samples", "map_every", "std_max", "scan_every", "save", "spawn", "connect",
                 "serve_web", "web_port", "grpc_port", "torch_threads", "device", "map_dtype", "bind", "mcap"),
    # when the recorder ends a run
    "recorder": ("start_timeout_s", "linger_s", "rejoin_timeout_s", "stall_timeout_s", "unreachable_timeout_s"),
    "faults": (),
    # how long the world and a robot wait for a goal (a robot that goes on without one says so)
    "explore": ("goal_wait_s",),
    # the launcher (a replay's settings are the world's and lidar's fields it sets); where the services run and the
    # network between their hosts (routers, namespaces, link rates and loss: how fast the States arrive, not what they are)
    "up": ("record", "replay", "observer", "viewer", "stop_grace_s", "observer_grace_s", "learner_grace_s", "start_timeout_s",
           "restarts", "resume", "mcap", "routers", "router_links", "netns", "link_rate", "link_loss", "budget"),
    # where ROS 2 robots' scans are heard and their maps published (the scans themselves are the dataset's)
    "ros2": ("namespaces", "scan_topic", "odom_topic", "idle_s", "wait_s", "max_input_s", "max_scans", "publish", "live",
             "extent", "initial_poses", "warmup_s", "unknown_std", "serve_s"),
}

# Fields that change what a run computes: its team, its plan and sensor, training, faults.
COUNTED: dict[str, tuple[str, ...]] = {
    "": ("robots", "seed"),
    "world": ("floorplan", "waypoints", "pixels_per_metre", "dinno_border_px", "rooms_x", "rooms_y", "room_min_m", "room_max_m",
              "wall_thickness_m", "wall_height_m", "door_width_m", "extra_door_prob", "corridor_width_m", "robot_clearance_m",
              "grid_resolution_m", "speed_mps", "sim_step_s", "rooms_per_robot", "rooms", "closed_doors", "closed_door_fraction",
              "coverage_spacing_m", "lidar_beams", "lidar_fov_deg", "lidar_min_range_m", "lidar_max_range_m", "lidar_height_m",
              "lidar_rate_hz", "ray_batch", "val_scans", "val_beams", "drive", "dataset", "dataset_pose", "dataset_scan_topic",
              "dataset_odom_topic", "dataset_fixed_frame", "dataset_holdout_every", "dataset_margin_m"),
    "lidar": ("samples_per_beam", "sampling", "occupied_depth_m", "range_noise_std_m", "dropout_prob", "free_on_max_range",
              "replay", "replay_incomplete"),
    "learner": ("transport", "rounds", "primal_iterations", "batch_size", "optimizer", "lr_start", "lr_finish", "lr_schedule",
                "rho_init", "rho_growth", "algorithm", "graph", "graph_file", "comm_radius_m", "model", "model_shape",
                "regularization", "kl_weight", "prior_sigma", "bnn_rho_init", "bnn_local_reparam", "dropout_p", "w_mu", "w_rho",
                "mc_samples", "unseen_weight", "unseen_prior_std", "unseen_points", "unseen_draws", "unseen_margin_m",
                "share_coverage", "optimizer_per_round", "siren_scale", "data", "window_scans", "eval_every", "map_resolution_m",
                "max_state_distance", "consensus", "consensus_options", "consensus_min_weight", "sigma_memory_rounds", "exchange_every",
                "exchange_every_s", "stale_rounds", "round_wait_s", "compression", "compression_options", "slow_link_compression",
                "topk_density", "quant_bits", "lowrank_rank", "keyframe_every", "robust", "robust_spread_factor", "robust_pull_factor",
                "sigma_max_weight"),
    "faults": ("link_success", "duplicate", "delay_s", "links", "seed", "per_round", "attack", "attackers"),
    "explore": ("policy", "starts", "decide_every", "leg_s", "distance_m", "stall_legs", "stall_gain", "separation_m",
                "min_travel_m", "clearance_m", "map_resolution_m", "information", "mc_samples", "seen_weight", "min_gain"),
}


def config_fields() -> dict[str, tuple[str, ...]]:
    """Every field of the run's config by section ("" is the top level), as the models define them."""
    top = tuple(n for n, f in RunConfig.model_fields.items() if not _is_section(f.annotation))
    return {"": top} | {n: tuple(f.annotation.model_fields) for n, f in RunConfig.model_fields.items() if _is_section(f.annotation)}


def _is_section(annotation: object) -> bool:
    return isinstance(annotation, type) and hasattr(annotation, "model_fields")


def settings_fingerprint(cfg: RunConfig) -> dict:
    """Every field that counts, as ``"section.field": value`` (JSON values), the checkpoint format,
    for a plan file its SHA-256 (the same path may hold another plan), and for a consensus rule,
    a network, an attack or a compression from another package that package's name and version."""
    doc = cfg.model_dump(mode="json")
    out: dict = {"checkpoint_format": CHECKPOINT_FORMAT}
    for section, names in config_fields().items():
        values = doc if section == "" else doc[section]
        skip = NOT_COUNTED.get(section, ())
        out |= {f"{section}.{n}".lstrip("."): values[n] for n in names if n not in skip}
    out["world.floorplan_sha256"] = plan_sha256(cfg.world.floorplan)
    for options in ("consensus_options", "compression_options"):
        if not getattr(cfg.learner, options):  # as a run of a swarmmap before parts took options: its runs resume
            del out[f"learner.{options}"]
    for group, field, name in (("consensus", "learner.consensus", cfg.learner.consensus), ("models", "learner.model", cfg.learner.model),
                               ("attacks", "faults.attack", cfg.faults.attack),
                               ("compressions", "learner.compression", cfg.learner.compression),
                               ("compressions", "learner.slow_link_compression", cfg.learner.slow_link_compression)):
        if (where := plugins.origin(group, name)) is not None:  # a part from another package: its package and version
            out[f"{field}_plugin"] = where
    return out


def plan_sha256(spec: str) -> str | None:
    """The SHA-256 of a plan file; None for the procedural plan or a file this process cannot read
    (then the path alone identifies it)."""
    if spec == "procedural":
        return None
    import hashlib

    try:
        return hashlib.sha256(Path(spec).read_bytes()).hexdigest()
    except OSError:
        return None


def fingerprint_diff(theirs: dict | None, mine: dict, limit: int = 6) -> str:
    """The settings two fingerprints disagree on, in words: ``seed 0 there, 7 here; ...`` ("" when
    they agree); a fingerprint of another checkpoint format is named as such."""
    if theirs is None:
        return "it comes from an older swarmmap"
    if theirs.get("checkpoint_format") != mine.get("checkpoint_format"):
        return f"it was written in checkpoint format {theirs.get('checkpoint_format')}, this swarmmap writes {mine['checkpoint_format']}"
    keys = [k for k in mine if theirs.get(k, "(unset)") != mine[k]] + [k for k in theirs if k not in mine]
    words = [f"{k} {theirs.get(k, '(unset)')!r} there, {mine.get(k, '(unset)')!r} here" for k in keys]
    more = f" and {len(words) - limit} more" if len(words) > limit else ""
    return ", ".join(words[:limit]) + more
