"""The Python API's example in docs/python.md runs as written, and its refusals are named."""

from __future__ import annotations

import os
import re

import pytest

from swarmmap.shared.api import RunError, open_run, run
from swarmmap.shared.run.config import ConfigError
from tests.conftest import REPO

pytestmark = pytest.mark.e2e


def test_the_documented_example_runs(tmp_path, monkeypatch, capsys):
    code = "\n".join(re.findall(r"```python\n(.*?)```", (REPO / "docs" / "python.md").read_text(), re.S))
    monkeypatch.chdir(tmp_path)
    for key in [k for k in os.environ if k.startswith("SWARMMAP_")]:
        monkeypatch.delenv(key)
    exec(compile(code, "docs/python.md", "exec"), {})
    out = capsys.readouterr().out
    start, end = map(float, re.search(r"at round 0: ([\d.]+), at round 20: ([\d.]+)", out).groups())
    assert end < start  # the team learned
    assert len(list((tmp_path / "runs").iterdir())) == 1


def test_a_bad_override_is_refused_before_anything_starts_and_a_refused_run_raises(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match="learner.rounds"):
        run("smoke", learner__rounds=-3)
    with pytest.raises(ConfigError, match="unknown preset 'smok'"):
        run("smok")
    with pytest.raises(RunError, match="refused the run"):
        run("smoke", world__floorplan=str(tmp_path / "missing.svg"), quiet=True)
    assert not (tmp_path / "runs").exists()
    with pytest.raises(RunError, match="holds no run"):
        open_run(tmp_path)
