"""``swarmmap experiment``: the paper's experiments as commands that make its figures.

    swarmmap experiment kl-sweep --preset demo --out results/kl        # the paper's Figure 6
    swarmmap experiment regularization --preset demo --out results/reg # its Figures 7 and 8
    swarmmap experiment consensus --preset demo --out results/cons     # consensus rules, poor links, compression
    swarmmap experiment score RUN_DIR                                  # uncertainty scores of one run

Each experiment runs the real system (``swarmmap up``, learners in one process by default,
which gives the same parameters as over Zenoh) once per setting, then writes PNG figures, the
CSV behind them and ``report.md`` into ``--out``. Every report carries the uncertainty scores
of :mod:`swarmmap.shared.learning.uncertainty` (NLL, ECE, AUROC of the std for the map's errors, mean std
over observed and never-observed cells).

- ``kl-sweep``: one isolated agent (``--robots 1``, no communication) whose path visits only
  ``--rooms`` rooms, so part of the plan stays unseen; one run per ``--kl-weights`` value; a
  row of mean maps over a row of std maps.
- ``regularization``: ``--robots`` agents (7), the strategies ``uniform-l2``, ``separate-l2``,
  ``separate-kl`` and ``--seeds`` seeds each, over a grid of ``--shapes`` x ``--w-rho``
  (W_rho / W_mu) x ``--kl-weights``; validation-loss curves (a panel per cell: mean over
  agents and seeds, with their spread), a table of final losses with the percentage difference
  of separate-kl against each other strategy and the seeds on which it is lower, a verdict per
  cell, and the mean/std maps of the best run.
- ``consensus``: ``--robots`` agents, consensus rules (``learner.consensus``) x link success
  (``faults.link_success`` drawn per link and round, with ``learner.round_wait_s`` below 100%) x exchange intervals
  (``learner.exchange_every``), then each ``--compression`` mode over perfect links; curves of
  val_bce against round and against bytes sent, a table with sigma's wins per seed, and the
  bytes and loss of each compression against float32.
"""

from __future__ import annotations

import argparse
import sys
import typing
from pathlib import Path

from swarmmap.shared import plugins
from swarmmap.shared.run.config import DEFAULT_PRESET, PRESETS, ConfigError, LearnerSettings

# The choices, as the config's fields allow them.
BUILTIN_RULES = ("dinno", "ramen", "sigma", "dgvi")  # the consensus experiment's rules, in its order
STRATEGIES = typing.get_args(LearnerSettings.model_fields["regularization"].annotation)



def add_parser(sub, text: str = "The paper's experiments (kl-sweep, regularization, consensus) and the scores of a run.") -> None:
    """The ``experiment`` subcommand (``text``: its help) and its experiments."""
    p = sub.add_parser("experiment", help=text, description=text)
    exp = p.add_subparsers(dest="experiment", required=True, metavar="EXPERIMENT")
    for name, text in (("kl-sweep", "One isolated agent, one run per kl_weight (the paper's Figure 6)."),
                       ("regularization", "7 agents, the three regularisation strategies (the paper's Figures 7 and 8)."),
                       ("consensus", "7 agents: consensus rules x link success x exchange interval, and compressed States.")):
        e = exp.add_parser(name, help=text, description=text, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
        e.add_argument("--out", type=Path, required=True, help="directory for the runs, figures, CSV and report.md")
        e.add_argument("--preset", choices=list(PRESETS), default=DEFAULT_PRESET, help="size: smoke, demo, paper (GPU)")
        e.add_argument("--rounds", type=int, default=0,
                       help="rounds per run (0: the preset's; for demo, 400 in kl-sweep and 300 in regularization)")
        e.add_argument("--transport", choices=["inproc", "zenoh"], default="inproc",
                       help="learners in one process (same result, faster) or one process per robot over Zenoh")
        e.add_argument("--observer", action="store_true", help="also record each run in Rerun (RUN_DIR/recording.rrd)")
        e.add_argument("--set", action="append", metavar="KEY=VALUE", help="any config field, e.g. learner.prior_sigma=0.1")
        e.add_argument("--device", default=None, help="torch device of the learners (learner.device): cpu, cuda, cuda:1; "
                                                      "default: the config's (auto: a GPU when there is one)")
        if name == "kl-sweep":
            e.add_argument("--kl-weights", type=float, nargs="+", default=[1e-4, 5e-3, 5e-1], help="kl_weight values")
            e.add_argument("--rooms", type=int, default=2, help="rooms the agent's path visits (the rest stays unseen)")
        else:
            e.add_argument("--robots", type=int, default=7, help="agents")
            e.add_argument("--seeds", type=int, nargs="+", default=[0, 1] if name == "regularization" else [0, 1, 2],
                           help="seeds (plan, paths, initialisation and lost messages)")
        if name == "regularization":
            e.add_argument("--strategies", nargs="+", choices=STRATEGIES, default=list(STRATEGIES), help="strategies to run")
            e.add_argument("--shapes", nargs="+", metavar="SHAPE", default=None,
                           help="model shapes of the grid, e.g. 2,256,64,64,64,1 2,256,256,256,256,256,1 (the paper's); "
                                "default: the preset's")
            e.add_argument("--w-rho", type=float, nargs="+", default=None, metavar="RATIO",
                           help="W_rho / W_mu ratios of the grid (1: separate-l2 equals uniform-l2); default: the config's")
            e.add_argument("--kl-weights", type=float, nargs="+", default=None,
                           help="kl_weight values of the grid; default: the config's")
        if name == "consensus":
            rules = plugins.names("consensus")  # any installed; by default swarmmap's own
            e.add_argument("--consensus", nargs="+", choices=rules, default=list(BUILTIN_RULES),
                           help="consensus rules (any installed: swarmmap plugins lists them)")
            e.add_argument("--link-success", type=float, nargs="+", default=[1.0, 0.3, 0.05],
                           help="probabilities that a message reaches a neighbour")
            e.add_argument("--exchange-every", type=int, nargs="+", default=[1, 10], help="exchange intervals (rounds)")
            e.add_argument("--compression", nargs="+", choices=plugins.names("compressions"),
                           default=["none", "f16", "bf16", "topk", "sign", "quant"],  # (lowrank fails under Adam: README)
                           help="State encodings, each run over perfect links exchanging every round")
            e.add_argument("--compression-consensus", nargs="+", choices=rules, default=["dinno"],
                           help="consensus rules the compression runs use")
            e.add_argument("--round-wait", type=float, default=0.3,
                           help="below 100%% link success, the most a round waits for messages (learner.round_wait_s)")
    s = exp.add_parser("score", help="Uncertainty scores of a finished bnn run's maps.",
                       description="Uncertainty scores of a finished bnn run's maps.")
    s.add_argument("run_dir", type=Path, help="the run directory")
    s.add_argument("--radius", type=float, default=0.1, help="cells within this distance (m) of a training point are observed")
    s.add_argument("--ensemble", action="store_true", help="also score the robots' final models as one deep ensemble "
                                                           "(any model: a FourierNet run too)")
    s.add_argument("--std-of", choices=("probability", "logit"), default="probability",
                   help="the spread scored: of the passes' occupancy probabilities (the saved maps), or of their "
                        "logits (maps computed anew from the robots' final models)")
    s.add_argument("--out", type=Path, default=None, help="folder for scores.csv, scores.json, reliability.png "
                                                          "(default RUN_DIR/scores)")


def main(args: argparse.Namespace) -> int:
    """Run the chosen experiment; 2 when its arguments are refused, 1 when a run failed."""
    from swarmmap.services.up import writable_problem

    if args.out is not None and (why := writable_problem("--out", args.out)) is not None:
        print(f"config error:\n  {why}", file=sys.stderr)
        return 2
    try:
        # Imported here: `swarmmap --help` does not pay for the experiments' figures and scoring.
        if args.experiment == "kl-sweep":
            from swarmmap.services.experiments.kl_sweep import kl_sweep as experiment
        elif args.experiment == "regularization":
            from swarmmap.services.experiments.regularization import regularization as experiment
        elif args.experiment == "consensus":
            from swarmmap.services.experiments.consensus import consensus as experiment
        else:
            from swarmmap.services.experiments.score import score as experiment
        return experiment(args)
    except ConfigError as exc:
        print(exc.message, file=sys.stderr)
        return 2
    except (RuntimeError, FileNotFoundError) as exc:
        print(f"experiment failed: {exc}", file=sys.stderr)
        return 1
