"""What a member's object bombs cost the honest learners: their peak memory and their seconds a round.

    python bench/bomb.py [--robots 3] [--rounds 40] [--seed 4] [--hostile 1] [--out /tmp/bomb]

Two ``swarmmap up --preset smoke`` runs over Zenoh (a learner process per robot, its own
credentials): ``clean``, and ``bomb``, in which robot ``--hostile``'s learner sends object bombs
(``faults.attack=bomb``: a valid header, then a million empty msgpack maps in 1 MB, for each of its
messages, and twice a 63 MB one of sixteen million) instead of its States and RoundCompletes. Per
honest learner: its process's peak resident set (the kernel's high-water mark, sampled from
/proc) and its seconds a round (from its first report to its last, over the rounds between),
against the clean run's. The headline names the worst honest learner of each.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: its common parts

from common import SWARMMAP, clean_env  # noqa: E402
from procmem import run_sampled  # noqa: E402


def run(run_dir: Path, args: list[str]) -> dict[int, int]:
    """Run ``swarmmap up`` into ``run_dir``; the peak RSS (KiB) of each robot's learner process."""
    status, err, seconds, sampler = run_sampled([*SWARMMAP, "up", "--run-dir", str(run_dir), *args], env=clean_env())
    Path(f"{run_dir}.log").write_text(err)
    print(f"  ({run_dir.name}: exit {status}, {seconds:.0f} s)", flush=True)
    peaks = {}
    for pid, kib in sampler.learner_peak.items():
        robot = re.search(r"--robot (\d+)", sampler.commands.get(pid, ""))
        if robot:
            peaks[int(robot.group(1))] = max(peaks.get(int(robot.group(1)), 0), kib)
    return peaks


def seconds_a_round(run_dir: Path) -> dict[int, float]:
    """Each robot's seconds a round, from its first report to its last (a member left out at round
    0 costs that round ``learner.silent_after_s``, before the first report)."""
    with (run_dir / "metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    out = {}
    for robot in {int(r["robot"]) for r in rows}:
        mine = sorted((int(r["round"]), float(r["wall_time_s"])) for r in rows if int(r["robot"]) == robot)
        (r0, t0), (r1, t1) = mine[0], mine[-1]
        out[robot] = (t1 - t0) / max(r1 - r0, 1)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=40)
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--hostile", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="bomb-"))
    out.mkdir(parents=True, exist_ok=True)
    base = ["--preset", "smoke", "--robots", str(args.robots), "--rounds", str(args.rounds), "--seed", str(args.seed),
            "--no-observer"]
    attack = ["--set", "faults.attack=bomb", "--set", f"faults.attackers=[{args.hostile}]"]
    peaks, rounds, summaries, first = {}, {}, {}, {}
    for case, extra in (("clean", []), ("bomb", attack)):
        peaks[case] = run(out / case, base + extra)
        rounds[case] = seconds_a_round(out / case)
        summaries[case] = json.loads((out / case / "summary.json").read_text())
        with (out / case / "metrics.csv").open() as f:
            first[case] = max(float(r["wall_time_s"]) for r in csv.DictReader(f) if r["round"] == "0")
    honest = [r for r in range(args.robots) if r != args.hostile]
    for r in honest:
        print(f"robot {r}: peak RSS {peaks['bomb'][r] / 1024:.0f} MiB (clean {peaks['clean'][r] / 1024:.0f} MiB), "
              f"{rounds['bomb'][r]:.3f} s a round (clean {rounds['clean'][r]:.3f} s), "
              f"refused {summaries['bomb']['learners'][str(r)]['refused']}")
    memory = max(peaks["bomb"][r] / peaks["clean"][r] for r in honest)
    pace = max(rounds["bomb"][r] / rounds["clean"][r] for r in honest)
    print(f"object bomb, smoke {args.robots} robots, worst honest learner: peak RSS {memory:.2f}x a clean run's, "
          f"seconds a round {pace:.2f}x a clean run's (round 0: {first['bomb']:.1f} s against {first['clean']:.1f} s, "
          f"the wait for a silent member); run {'ok' if summaries['bomb']['ok'] else 'FAILED'}")


if __name__ == "__main__":
    main()
