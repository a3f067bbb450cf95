"""swarmmap from Python: start a run and read one back, for notebooks and scripts.

    from swarmmap.shared.api import open_run, run

    r = run("smoke", robots=3, learner__rounds=20)   # swarmmap up, as its own processes; blocks
    r.ok, r.summary["learners"]["0"]["final_val_bce"]
    m = r.metrics                                     # a table: m["val_bce"][m["robot"] == 0]
    r.maps(0)["mean"], r.maps(0).get("std")           # arrays over the map's cells
    model = r.model(0)                                # the robot's torch network
    r = open_run("runs/run-20261207-101500")          # any run directory, whoever made it

Overrides are the config's fields, a section's with a double underscore (``learner__rounds=20``,
as ``SWARMMAP_LEARNER__ROUNDS``) or as a dict (``learner={"rounds": 20}``); they are validated
here, before anything starts (a :class:`~swarmmap.shared.run.config.ConfigError` names the field).
:func:`run` starts ``swarmmap up`` with this interpreter and returns when it ends; a run that
fails returns too (``Run.ok`` False, ``Run.failure`` why) and a run that could not start raises
:class:`RunError` with ``up``'s words.
"""

from __future__ import annotations

import functools
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from swarmmap.shared.run.config import ConfigError, RunConfig, deep_merge, read_config_file, resolve, validate_config
from swarmmap.shared.run.rundir import final_val_bce, metric_rows, read_summary


class RunError(RuntimeError):
    """A run that could not start (``swarmmap up`` refused it) or a folder that holds no run."""


def overrides_tree(overrides: dict[str, Any]) -> dict[str, Any]:
    """``{"learner__rounds": 20, "robots": 3}`` -> ``{"learner": {"rounds": 20}, "robots": 3}``."""
    tree: dict[str, Any] = {}
    for key, value in overrides.items():
        *path, last = key.split("__")
        node = tree
        for part in path:
            node = node.setdefault(part, {})
        node[last] = deep_merge(node.get(last, {}), value) if isinstance(value, dict) else value
    return tree


CONFIG_SUFFIXES = (".yaml", ".yml", ".json")


def _config_file(preset_or_file: str | Path | None) -> Path | None:
    """``preset_or_file`` when it names a config file (by its suffix), None for a preset's name."""
    return Path(preset_or_file) if preset_or_file is not None and Path(preset_or_file).suffix in CONFIG_SUFFIXES else None


def _resolve(preset_or_file: str | Path | None, tree: dict[str, Any]) -> RunConfig:
    if (file := _config_file(preset_or_file)) is not None:
        return resolve(tree, config_file=file, environ={})
    return resolve({"preset": preset_or_file, **tree} if preset_or_file else tree, environ={})


def config(preset_or_file: str | Path | None = None, **overrides: Any) -> RunConfig:
    """The config :func:`run` would start: a preset's name or a config file, with ``overrides``."""
    return _resolve(preset_or_file, overrides_tree(overrides))


def run(preset_or_file: str | Path | None = None, *, quiet: bool = False, timeout: float | None = None,
        **overrides: Any) -> Run:
    """Run ``swarmmap up`` with a preset (``"smoke"``) or a config file and ``overrides``; the run
    directory is ``run_dir`` if given, else ``runs/<run id>`` under the current folder. Its console
    goes to this process's standard output unless ``quiet``."""
    tree = overrides_tree(overrides)
    cfg = _resolve(preset_or_file, tree)
    run_id = cfg.run_id if cfg.run_id != "default" else time.strftime("run-%Y%m%d-%H%M%S")
    run_dir = (cfg.run_dir or Path("runs") / run_id).resolve()
    file = _config_file(preset_or_file)
    base = read_config_file(file) if file is not None else {"preset": preset_or_file} if preset_or_file else {}
    doc = deep_merge(base, deep_merge(tree, {"run_id": run_id, "run_dir": str(run_dir)}))
    with tempfile.TemporaryDirectory(prefix="swarmmap-api-") as tmp:
        given = Path(tmp) / "config.yaml"
        given.write_text(yaml.safe_dump(doc))
        proc = subprocess.run([sys.executable, "-m", "swarmmap.services.cli", "up", "--config", str(given)],
                              stdout=subprocess.DEVNULL if quiet else None, stderr=subprocess.PIPE, text=True, timeout=timeout)
    if proc.returncode == 2 or not (run_dir / "config.yaml").exists():
        raise RunError(f"swarmmap up refused the run (status {proc.returncode}): {proc.stderr.strip()[-2000:]}")
    if not quiet and proc.stderr:
        sys.stderr.write(proc.stderr)
    return Run(run_dir)


def open_run(path: str | Path) -> Run:
    """The run in ``path`` (a run directory: it holds ``config.yaml``)."""
    p = Path(path).expanduser().resolve()
    if not (p / "config.yaml").is_file():
        raise RunError(f"{p} holds no run (no config.yaml)")
    return Run(p)


class Run:
    """A run directory read back: its config, summary, metrics, maps and models."""

    def __init__(self, path: Path):
        self.path = Path(path)

    def __repr__(self) -> str:
        state = "no summary yet" if self.summary is None else ("ok" if self.ok else f"failed: {self.failure}")
        return f"Run({str(self.path)!r}, {state})"

    @functools.cached_property
    def config(self) -> RunConfig:
        """The run's resolved config (``config.yaml``)."""
        try:
            return validate_config(yaml.safe_load((self.path / "config.yaml").read_text()) or {})
        except ConfigError as exc:
            raise RunError(f"{self.path / 'config.yaml'}: {exc.message}") from None

    @property
    def summary(self) -> dict | None:
        """``summary.json`` (None while the run is going on, or when it was cut off)."""
        return read_summary(self.path)

    @property
    def ok(self) -> bool:
        """Whether the run finished with every learner done."""
        return bool(self.summary and self.summary.get("ok"))

    @property
    def failure(self) -> str | None:
        """Why the run failed, in the recorder's words (None when it did not)."""
        s = self.summary
        return None if s is None or s.get("ok") else str(s.get("reason") or "unknown")

    @property
    def robots(self) -> list[int]:
        return list(range(self.config.robots))

    @property
    def metrics(self) -> np.ndarray:
        """``metrics.csv`` as a table: a structured array, a row per report, a field per column
        (``robot``, ``round``, ``val_bce``, ``consensus_error``, ``bytes_sent``, ...); ``pandas.DataFrame(m)``
        makes a frame of it."""
        rows = metric_rows(self.path)
        if not rows:
            return np.zeros(0, dtype=[("robot", "i8"), ("round", "i8"), ("val_bce", "f8")])
        ints = {"robot", "round", "bytes_sent", "bytes_received", "n_points", "final"}
        dtype = [(name, "i8" if name in ints else "f8") for name in rows[0]]
        return np.array([tuple(float(r[n]) if t == "f8" else int(float(r[n])) for n, t in dtype) for r in rows], dtype=dtype)

    def final_val_bce(self) -> dict[int, float]:
        """Each robot's last reported validation loss."""
        return final_val_bce(self.path)

    def maps(self, robot: int) -> dict[str, np.ndarray]:
        """Robot ``robot``'s learned map: ``mean`` occupancy (and ``std`` for a model that has
        one) over the map's cells, row 0 at the south, with ``origin`` and ``resolution``."""
        path = self.path / "maps" / f"robot-{robot}.npz"
        if not path.exists():
            raise RunError(f"{path} does not exist: robot {robot}'s learner wrote no map (the run has robots {self.robots})")
        with np.load(path) as f:
            return {k: f[k] for k in f.files}

    def groundtruth(self) -> dict[str, np.ndarray]:
        """The world's grid and validation set (``groundtruth.npz``)."""
        with np.load(self.path / "groundtruth.npz") as f:
            return {k: f[k] for k in f.files}

    def model(self, robot: int):
        """Robot ``robot``'s trained network (a torch module, on the CPU)."""
        from swarmmap.shared.learning.networks import load_model

        path = self.path / "models" / f"robot-{robot}.pt"
        if not path.exists():
            raise RunError(f"{path} does not exist: robot {robot}'s learner wrote no model")
        return load_model(path)
