"""The ``swarmmap`` command: the whole system (``up``), its services one by one, the paper's
experiments and the tools that look at runs.

Every subcommand's ``--help`` lists its options; each option is a field of the run's config
(see swarmmap.shared.run.config) and overrides the config file and the environment.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

from swarmmap.shared.run.config import DEFAULT_PRESET, PRESETS, ConfigError, Ros2Settings, RunConfig, resolve
from swarmmap.shared.run.flags import add_common_arguments, add_field_argument, add_model_arguments, config_from_args
from swarmmap.shared.run.runtime import Stopped, setup_logging, shutdown_event

SUMMARY = ("swarmmap: decentralised multi-robot mapping with uncertainty (DiNNO and Bayesian networks) "
           "as services on Zenoh.")
EXAMPLES = """examples:
  swarmmap up --preset smoke                  a first run: 3 robots, 60 rounds
  swarmmap up                                 the demo: 7 robots, 800 rounds
  swarmmap up --model bnn --robots 5 --rounds 300
  swarmmap up --floorplan plan/model.svg      a CubiCasa5K plan (or a DiNNO .png, a ROS map .yaml)
  swarmmap runs                               the runs in ./runs, their status and final loss
  swarmmap status runs/RUN_ID                 a run: live services, round and val_bce per learner
  swarmmap compare runs/A runs/B --out ab.png their val_bce curves
  swarmmap experiment kl-sweep --preset smoke --out results/kl
"""
UP_EXAMPLES = """examples:
  swarmmap up --preset smoke                        3 robots, 60 rounds: a first try
  swarmmap up --model bnn --rounds 300              the Bayesian network: std maps show the uncertainty
  swarmmap up --floorplan plan/model.svg --robots 4 a CubiCasa5K plan
  swarmmap up --floorplan floor_img.png --waypoints tight_paths --preset dinno-fast
  swarmmap up --set learner.model_shape=[2,64,32,1] --device cpu
  SWARMMAP_LEARNER__ROUNDS=50 swarmmap up            any field from the environment
Then look at what it left: rerun RUN_DIR/recording.rrd, swarmmap experiment score RUN_DIR.
"""

# The commands that are not one of the run's services; each service's comes from its kind
# (swarmmap.shared.wire.services: the registry), placed where SERVICES_AT says.
COMMANDS = {
    "up": "Run the whole system locally: router, recorder, observer, world, a lidar streamer and a learner per robot.",
    "prepare": "Write a run's config.yaml (what up would run) for services started one by one, e.g. by SLURM.",
    "experiment": "The paper's experiments (kl-sweep, regularization, consensus) and the scores of a run.",
    "status": "A run's state: finished or not, and for a live one its services, round and val_bce per learner.",
    "runs": "List the runs in a folder (default ./runs): status, robots, rounds, final mean val_bce, start time.",
    "logs": "List a run's service logs, or print one service's log.",
    "compare": "Plot runs' mean val_bce against round and against wall time into one PNG.",
    "secrets": "Write a run's credentials: a CA, a certificate per service and the router's access policy.",
    "net": "Change the network of a run started with up --netns: cut the team in two, heal it, set link rates and "
           "loss (root).",
    "plugins": "List the installed parts (consensus rules, networks, dataset readers, services, attacks), built-in and "
               "from other packages, each checked.",
    "services": "List the run's kinds of service (the registry): one per run or per robot, config section, command.",
    "ros2": "A team of ROS 2 robots mapped live: their LaserScan and Odometry heard on ROS 2, learned from as they "
            "come, their maps published there (nav_msgs/OccupancyGrid) and, exploring, their goals (/<ns>/goal_pose).",
}
SERVICES_AT = "secrets"  # the services' own commands follow this one in swarmmap --help


def descriptions() -> dict[str, str]:
    """Every subcommand and its one-line description: the commands above with a command per
    kind of service that has one (the registry's, swarmmap's own and other packages')."""
    from swarmmap.shared.wire.services import kinds

    services = {name: k.summary for name, k in kinds().items() if k.runner}
    out: dict[str, str] = {}
    for name, text in COMMANDS.items():
        out[name] = text
        if name == SERVICES_AT:
            out |= services
    return out


def section_of(command: str) -> str | None:
    """The config section whose flags a service's command takes (None: the common ones only)."""
    from swarmmap.shared.wire.services import kinds

    k = kinds().get(command)
    return k.section if k is not None and k.runner else None


TOOLS = ("runs", "logs", "compare", "plugins", "services")  # read run directories or what is installed: no config, no Zenoh
# What a user sets most, first in up's and prepare's help: (config path, flag, help where the field's own does not fit).
EVERYDAY = (("preset", "--preset", None), ("robots", "--robots", None), ("learner.rounds", "--rounds", None),
            ("learner.model", "--model", None),
            ("world.floorplan", "--floorplan", "procedural, a CubiCasa5K model.svg, a DiNNO .png or a ROS map_server .yaml"),
            ("world.waypoints", "--waypoints", "folder of .npy waypoint paths, one per robot (default: paths planned "
                                               "through the plan)"),
            ("world.dataset", "--dataset", "real LiDAR logs instead of a floor plan: a CARMEN log (.log, .clf, gzipped or not), "
                                           "a ROS 1 bag, a rosbag2 folder or an .mcap file (docs/datasets.md)"),
            ("explore.policy", "--explore", "the robots choose where to drive while they learn: uncertainty (where their "
                                            "map's std is highest), frontier (the classic), planned (the planned paths, "
                                            "in legs); none: drive the planned paths, then learn (docs/exploration.md)"),
            ("explore.starts", "--starts", "exploring: start positions \"x,y;x,y;...\" in metres in the plan's frame "
                                            "(--starts=-1,2;... where the first is negative)"),
            ("run_dir", "--run-dir", None),
            ("learner.device", "--device", "torch device of the learners: auto (a GPU when there is one), cpu, cuda, "
                                           "cuda:1 (the observer's: --set observer.device=...)"),
            ("seed", "--seed", None))
UP_RUN_FLAGS = (("learner.transport", "--transport", "Algorithm 1 over Zenoh, one learner process per robot, or in one process"),
                ("learner.algorithm", "--algorithm", None), ("learner.regularization", "--regularization", None),
                ("lidar.replay_speed", "--replay-speed", "with --replay: multiple of the recorded rate, 0 = as fast as "
                                                         "the learners take it"))
UP_SHOWN = {"run_id": "run-<date>-<time>, made from the time the run starts", "run_dir": "runs/<run id>"}


def version() -> str:
    """The installed package's version (its metadata), e.g. ``0.1.0``."""
    try:
        return metadata.version("swarmmap")
    except metadata.PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def add_up_arguments(p: argparse.ArgumentParser) -> None:
    """``up``'s and ``prepare``'s options: everyday ones first, Zenoh and TLS last."""
    defaults = resolve(preset=DEFAULT_PRESET, environ={})  # what a plain `swarmmap up` runs
    everyday = p.add_argument_group(f"everyday options (defaults: what a plain swarmmap up runs, the {DEFAULT_PRESET} preset)")
    for path, flag, text in EVERYDAY:
        if path == "preset":
            everyday.add_argument("--preset", dest="top.preset", default=argparse.SUPPRESS, metavar="{" + ",".join(PRESETS) + "}",
                                  help=f"named preset applied under the config file [default: {DEFAULT_PRESET}]")
            continue
        add_field_argument(everyday, path, flag, defaults=defaults, help=text, shown_default=UP_SHOWN.get(path))
    advanced = add_common_arguments(p, "up", defaults=defaults, skip={"preset", "robots", "seed", "run_dir"}, shown=UP_SHOWN,
                                    more=UP_RUN_FLAGS)
    advanced.add_argument("--insecure", dest="zenoh.insecure", action="store_const", const=True, default=argparse.SUPPRESS,
                          help="no TLS, authentication or access control (the same as --zenoh-insecure; every service warns)")


def add_tool_arguments(name: str, p: argparse.ArgumentParser) -> None:
    """The run tools' own options (they read run directories, not a config)."""
    if name == "status":
        p.add_argument("run_dir", nargs="?", type=Path, metavar="RUN_DIR", help="the run directory (or give --config)")
        p.add_argument("--window", type=float, default=2.0, help="seconds to listen to a live run [default: 2.0]")
    elif name == "runs":
        p.add_argument("folder", nargs="?", type=Path, default=Path("runs"), metavar="FOLDER",
                       help="a folder of run directories [default: runs]")
    elif name == "logs":
        p.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="the run directory")
        p.add_argument("service", nargs="?", metavar="SERVICE", help="a service's log, e.g. learner-0 (or learner: every "
                                                                      "learner's); without it, the list of logs")
        p.add_argument("--tail", type=int, default=0, metavar="N", help="only the last N lines of each log (0: all)")
    elif name == "compare":
        p.add_argument("runs", nargs="+", metavar="RUN_DIR[=LABEL]", help="run directories, each optionally with its label")
        p.add_argument("--out", type=Path, default=None, help="the PNG to write, never over a file [default: "
                                                               "compare.png in the first run, -2, -3... beside one there]")
        p.add_argument("--target", type=float, default=None, help="draw this val_bce as a line and say when each run reached it")
    elif name == "services":
        p.add_argument("--slurm", action="store_true", help="one line per kind the SLURM job starts beside its routers: "
                                                            "NAME one|per-robot compute|light [ends-run] (deploy/slurm/team.sbatch)")


def build_parser() -> argparse.ArgumentParser:
    """The ``swarmmap`` argument parser: one subcommand per service, launcher, experiment and tool."""
    parser = argparse.ArgumentParser(prog="swarmmap", description=SUMMARY, epilog=EXAMPLES,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"swarmmap {version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, description in descriptions().items():
        if name == "experiment":
            from swarmmap.services.experiments import add_parser

            add_parser(sub, description)
            continue
        extra = {"epilog": UP_EXAMPLES, "formatter_class": argparse.RawDescriptionHelpFormatter} if name == "up" else {}
        p = sub.add_parser(name, help=description, description=description, **extra)
        if name in ("up", "prepare"):
            add_up_arguments(p)
        elif name == "ros2":
            add_up_arguments(p)
            add_model_arguments(p.add_argument_group("ros2"), Ros2Settings, "ros2")
        elif name in TOOLS or name == "status":
            add_tool_arguments(name, p)
        elif name == "net":
            from swarmmap.services.up.netns import add_net_arguments

            add_net_arguments(p)
        if name not in ("up", "prepare", "ros2", "net", *TOOLS):
            add_common_arguments(p, section_of(name))
    return parser


def _runner(command: str) -> Callable:
    # Imported lazily: `swarmmap status --help` should not pay for torch and pybullet.
    if command == "up":
        from swarmmap.services.up.launcher import run
    elif command == "prepare":
        from swarmmap.services.up.launcher import run_prepare as run
    elif command == "secrets":
        from swarmmap.services.up.launcher import run_secrets as run
    elif command == "ros2":
        from swarmmap.services.ros2 import run
    else:  # one of the run's services: the main loop its kind names
        from swarmmap.shared.wire.services import kind

        module, _, function = kind(command).runner.partition(":")
        run = getattr(importlib.import_module(module), function)
    return run


def list_plugins(args: argparse.Namespace) -> int:
    """``swarmmap plugins``: every installed part and where it comes from; status 2 when one is refused."""
    from swarmmap.shared.plugins import report

    lines, refused = report()
    print("\n".join(lines))
    if refused:
        print(f"{refused} plug-in(s) refused (above): a run that names one is refused at start", file=sys.stderr)
    return 2 if refused else 0


def list_services(args: argparse.Namespace) -> int:
    """``swarmmap services``: the run's kinds of service; ``--slurm``: the lines team.sbatch starts its steps from."""
    from swarmmap.shared.wire.services import kinds, slurm_lines

    if args.slurm:
        print("\n".join(slurm_lines()))
        return 0
    for name, k in kinds().items():
        started = f"up starts it {'per robot' if k.per_robot else 'once'}" if k.up_order is not None else \
            "a tool's session" if k.runner is None else "started on its own"
        print(f"{name:<10} {'per robot' if k.per_robot else 'one a run':<10} section {str(k.section):<9} {started:<24} "
              f"{k.runner or '-'}")
    return 0


def run_tool(args: argparse.Namespace) -> int:
    """``runs``, ``logs``, ``compare``: they read run directories and print what they found; ``plugins``."""
    if args.command == "plugins":
        return list_plugins(args)
    if args.command == "services":
        return list_services(args)
    from swarmmap.services import runs

    try:
        return {"runs": runs.list_runs, "logs": runs.show_logs, "compare": runs.compare}[args.command](args)
    except runs.ToolError as exc:
        print(exc, file=sys.stderr)
        return 2


def main(argv: list[str] | None = None) -> int:
    """Parse the command line and run the subcommand; returns the exit status (2: refused, 130:
    interrupted, also by a Ctrl-C before the command's own handler was in place)."""
    try:
        return command(argv)
    except KeyboardInterrupt:  # Ctrl-C while Python still imported what the command needs
        print("interrupted", file=sys.stderr)
        return 130


def command(argv: list[str] | None = None) -> int:
    """:func:`main`'s work: parse the command line and run the subcommand."""
    args = build_parser().parse_args(argv)
    if args.command == "experiment":
        from swarmmap.services.experiments import main as experiment

        setup_logging("info", "experiment")
        logging.getLogger("up").setLevel(logging.WARNING)  # the console of each run is too much here; Progress reports
        return experiment(args)
    if args.command in TOOLS:
        return run_tool(args)
    stop = shutdown_event()
    if args.command == "net":
        from swarmmap.services.up.netns import run_net

        return run_net(args, stop)
    if args.command == "status":
        from swarmmap.services.status import run_status

        setup_logging("warning", "status")
        return run_status(args, stop)
    try:
        cfg: RunConfig = config_from_args(args, preset=DEFAULT_PRESET if args.command in ("up", "prepare", "ros2") else None)
    except ConfigError as exc:
        print(exc.message, file=sys.stderr)
        return 2
    log = setup_logging(cfg.log_level, args.command)
    if node := os.environ.get("SLURMD_NODENAME"):  # a SLURM task: say where it runs
        log.info("SLURM job %s, task %s, on node %s", os.environ.get("SLURM_JOB_ID", "?"), os.environ.get("SLURM_PROCID", "?"), node)
    try:
        return _runner(args.command)(cfg, stop)
    except Stopped:
        log.info("stopped while it opened its session")
        return 130
    except ConfigError as exc:
        if stop.is_set():  # stopped while it opened its session (the router stopped first): no config error
            log.info("stopped before it was under way")
            return 130
        print(exc.message, file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        log.info("interrupted")
        return 130


if __name__ == "__main__":
    sys.exit(main())
