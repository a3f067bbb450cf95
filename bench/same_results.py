"""Same results, bit for bit: eleven seeded in-process runs whose every final parameter a refactor
must leave unchanged (FourierNet with dinno, DSGD and DSGT; the Bayesian network with each Figure 7
strategy, sigma, ramen, quant compression, exchange every 3 rounds, and sigma + quant + every 3 +
the prior on unseen space).

    python bench/same_results.py --out before.json     # on one checkout (its own swarmmap)
    python bench/same_results.py --out after.json      # on the other
    python bench/same_results.py --compare before.json after.json

Each case is ``swarmmap up --preset smoke --robots 3 --rounds 12 --seed 5 --transport inproc
--no-observer`` and its own flags; the output holds, per case and robot, the SHA-256 of every
parameter tensor's bytes in order. ``--compare`` prints a line per case and the headline
``same final parameters, 11 in-process cases: 11 of 11``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BASE = ["--preset", "smoke", "--robots", "3", "--rounds", "12", "--seed", "5", "--transport", "inproc", "--no-observer"]
BNN = ["--model", "bnn"]
CASES = {
    "fourier-dinno": [],
    "fourier-dsgd": ["--algorithm", "dsgd"],
    "fourier-dsgt": ["--algorithm", "dsgt"],
    "bnn-uniform-l2": [*BNN, "--regularization", "uniform-l2"],
    "bnn-separate-l2": [*BNN, "--regularization", "separate-l2"],
    "bnn-separate-kl": [*BNN, "--regularization", "separate-kl"],
    "bnn-sigma": [*BNN, "--set", "learner.consensus=sigma"],
    "bnn-ramen": [*BNN, "--set", "learner.consensus=ramen"],
    "bnn-quant": [*BNN, "--set", "learner.compression=quant"],
    "bnn-every3": [*BNN, "--set", "learner.exchange_every=3"],
    "bnn-sigma-quant-every3-unseen": [*BNN, "--set", "learner.consensus=sigma", "--set", "learner.compression=quant",
                                      "--set", "learner.exchange_every=3", "--set", "learner.unseen_weight=0.05"],
}


def parameter_hashes(model_path: Path) -> list[str]:
    import torch

    state = torch.load(model_path, map_location="cpu", weights_only=False)
    tensors = state["state_dict"] if isinstance(state, dict) and "state_dict" in state else state
    if hasattr(tensors, "state_dict"):
        tensors = tensors.state_dict()
    return [hashlib.sha256(t.detach().cpu().contiguous().numpy().tobytes()).hexdigest()[:16] for t in tensors.values()]


def run_cases(out: Path) -> None:
    results = {}
    with tempfile.TemporaryDirectory(prefix="same-results-") as tmp:
        for name, flags in CASES.items():
            run_dir = Path(tmp) / name
            t0 = time.monotonic()
            proc = subprocess.run([sys.executable, "-m", "swarmmap.services.cli", "up", *BASE, *flags, "--run-dir", str(run_dir)],
                                  capture_output=True, text=True)
            if proc.returncode != 0:
                print(f"{name}: up exited {proc.returncode}: {proc.stderr[-1500:]}", file=sys.stderr)
                results[name] = None
                continue
            results[name] = {str(r): parameter_hashes(run_dir / "models" / f"robot-{r}.pt") for r in range(3)}
            print(f"{name}: {time.monotonic() - t0:.1f} s", flush=True)
    out.write_text(json.dumps(results, indent=1) + "\n")


def compare(a: Path, b: Path) -> int:
    left, right = json.loads(a.read_text()), json.loads(b.read_text())
    same = 0
    for name in CASES:
        equal = left.get(name) is not None and left.get(name) == right.get(name)
        same += equal
        print(f"{name}: {'same' if equal else 'DIFFERENT'}")
    print(f"same final parameters, {len(CASES)} in-process cases: {same} of {len(CASES)}")
    return 0 if same == len(CASES) else 1


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, help="run the cases with this interpreter's swarmmap, write their hashes here")
    p.add_argument("--compare", type=Path, nargs=2, metavar=("A", "B"), help="compare two outputs")
    args = p.parse_args()
    if args.compare:
        return compare(*args.compare)
    if not args.out:
        p.error("give --out FILE or --compare A B")
    run_cases(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
