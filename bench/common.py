"""What the benches that launch whole runs share: one ``swarmmap up``, kept and reused."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository: tests.conftest

from swarmmap.shared.run.progress import duration, eta_words, time_left  # noqa: E402
from swarmmap.shared.run.rundir import run_state  # noqa: E402
from tests.conftest import SWARMMAP, clean_env  # noqa: E402


class Runs:
    """A bench's runs, each said as it ends with the time the rest will take at the pace so far
    (the estimate swarmmap's own progress lines use)."""

    def __init__(self, total: int):
        self.total, self.done, self.t0 = total, 0, time.monotonic()

    def ended(self, name: str) -> None:
        self.done += 1
        elapsed = time.monotonic() - self.t0
        print(f"  [{self.done}/{self.total}] {name} done, {duration(elapsed)} elapsed, "
              f"{eta_words(time_left(self.done, self.total, elapsed))}", flush=True)


def up_run(run_dir: Path, args: list[str]) -> dict:
    """The summary of ``swarmmap up --run-dir RUN_DIR ARGS``, running it unless its summary is
    there already (its console goes to ``RUN_DIR.log``); one that was interrupted is resumed."""
    if run_state(run_dir) != "finished":
        t0 = time.monotonic()
        resume = ["--resume"] if run_dir.exists() else []
        with open(f"{run_dir}.log", "a") as out:
            subprocess.run([*SWARMMAP, "up", "--run-dir", str(run_dir), *resume, *args], stdout=out, stderr=subprocess.STDOUT,
                           env=clean_env(), timeout=4 * 3600)
        print(f"  ({run_dir.name}: {time.monotonic() - t0:.0f} s)", flush=True)
    return json.loads((run_dir / "summary.json").read_text())
