"""The ``swarmmap`` command: one subcommand per service, plus ``status`` and ``up``.

    swarmmap up --preset demo            # the whole system on this machine
    swarmmap router|recorder|world|lidar|learner|observer  # one service (what up, compose and SLURM start)
    swarmmap prepare --run-dir DIR [up options]   # write DIR/config.yaml for services started by hand or SLURM
    swarmmap status --config RUN_DIR/config.yaml
    swarmmap experiment kl-sweep|regularization --out DIR   # the paper's figures

Every subcommand's ``--help`` lists its options; each option is a field of the run's config
(see swarmmap.shared.config) and overrides the config file and the environment.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable

from swarmmap.shared.config import DEFAULT_PRESET, ConfigError, RunConfig, add_common_arguments, config_from_args
from swarmmap.shared.runtime import setup_logging, shutdown_event

DESCRIPTIONS = {
    "up": "Run the whole system locally: router, world, a lidar streamer and a learner per robot.",
    "prepare": "Write a run's config.yaml (what up would run) for services started one by one, e.g. by SLURM.",
    "secrets": "Write a run's credentials: a CA, a certificate per service and the router's access policy.",
    "router": "A Zenoh router for discovery across hosts and containers.",
    "recorder": "The recorder: writes the run directory (config, metrics, summary, ground truth) and ends the run.",
    "world": "The pybullet world: floor plan, robots on their paths, LiDAR scans, the ground-truth map.",
    "lidar": "A LiDAR streamer: one robot's scans -> labelled training points.",
    "learner": "A learner: DiNNO consensus training of one robot's occupancy network (Algorithm 1).",
    "observer": "The Rerun observer: every learner's mean and std maps, the robots and the curves, live.",
    "status": "List the live services of a run and their message rates.",
}
SECTIONS = {"up": "up", "prepare": "up", "secrets": None, "router": None, "recorder": "recorder", "world": "world", "lidar": "lidar",
            "learner": "learner", "observer": "observer",
            "status": None}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="swarmmap", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, description in DESCRIPTIONS.items():
        p = sub.add_parser(name, help=description, description=description)
        add_common_arguments(p, SECTIONS[name])
        if name in ("up", "prepare"):
            p.add_argument("--rounds", dest="learner.rounds", default=argparse.SUPPRESS,
                           help="communication rounds per learner (learner.rounds)")
            p.add_argument("--transport", dest="learner.transport", default=argparse.SUPPRESS, metavar="{zenoh,inproc}",
                           help="Algorithm 1 over Zenoh, one learner process per robot (default), or in one process (learner.transport)")
            p.add_argument("--model", dest="learner.model", default=argparse.SUPPRESS, metavar="{fourier,bnn,dropout}",
                           help="DiNNO's FourierNet, the paper's Bayesian network or a FourierNet with MC dropout (learner.model)")
            p.add_argument("--regularization", dest="learner.regularization", default=argparse.SUPPRESS,
                           metavar="{uniform-l2,separate-l2,separate-kl}", help="bnn consensus regularisation (learner.regularization)")
            p.add_argument("--algorithm", dest="learner.algorithm", default=argparse.SUPPRESS,
                           metavar="{dinno,dsgd,dsgt,individual,centralized}", help="DiNNO or a baseline (learner.algorithm)")
            p.add_argument("--floorplan", dest="world.floorplan", default=argparse.SUPPRESS,
                           help="procedural, a CubiCasa5K model.svg or a DiNNO .png (world.floorplan)")
            p.add_argument("--waypoints", dest="world.waypoints", default=argparse.SUPPRESS,
                           help="folder of .npy waypoint paths, one per robot (world.waypoints)")
            p.add_argument("--insecure", dest="zenoh.insecure", action="store_const", const=True, default=argparse.SUPPRESS,
                           help="no TLS, authentication or access control (zenoh.insecure; warns)")
            p.add_argument("--replay-speed", dest="lidar.replay_speed", default=argparse.SUPPRESS,
                           help="with --replay: multiple of the recorded rate, 0 = as fast as the learners take it")
        if name == "status":
            p.add_argument("--window", type=float, default=2.0, help="seconds to measure message rates over")
    from swarmmap.services.experiments import add_parser

    add_parser(sub)
    return parser


def _runner(command: str) -> Callable:
    # Imported lazily: `swarmmap status --help` should not pay for torch and pybullet.
    if command == "up":
        from swarmmap.services.launcher import run
    elif command == "prepare":
        from swarmmap.services.launcher import run_prepare as run
    elif command == "secrets":
        from swarmmap.services.launcher import run_secrets as run
    elif command == "router":
        from swarmmap.services.router import run
    elif command == "recorder":
        from swarmmap.services.recorder import run
    elif command == "world":
        from swarmmap.services.world import run
    elif command == "lidar":
        from swarmmap.services.lidar import run
    elif command == "learner":
        from swarmmap.services.learner.service import run
    elif command == "observer":
        from swarmmap.services.observer import run
    else:
        raise ValueError(command)
    return run


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "experiment":
        from swarmmap.services.experiments import main as experiment

        setup_logging("info", "experiment")
        logging.getLogger("up").setLevel(logging.WARNING)  # one line per Metrics is too much here; Progress reports
        return experiment(args)
    try:
        cfg: RunConfig = config_from_args(args, preset=DEFAULT_PRESET if args.command in ("up", "prepare") else None)
    except ConfigError as exc:
        print(exc.message, file=sys.stderr)
        return 2
    log = setup_logging(cfg.log_level, args.command)
    stop = shutdown_event()
    try:
        if args.command == "status":
            from swarmmap.services.status import report

            print(report(cfg, args.window))
            return 0
        return _runner(args.command)(cfg, stop)
    except ConfigError as exc:
        print(exc.message, file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        log.info("interrupted")
        return 130


if __name__ == "__main__":
    sys.exit(main())
