"""Experiments refuse wrong arguments in plain words with status 2, before anything runs, and
leave no ``--out`` folder behind; ``score`` of a path that is no run says so."""

from __future__ import annotations

import subprocess

import pytest

from tests.conftest import SWARMMAP, clean_env

pytestmark = pytest.mark.timeout(120)


def experiment(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*SWARMMAP, "experiment", *args], capture_output=True, text=True, timeout=60, env=clean_env())


@pytest.mark.parametrize(("args", "said"), [
    (("consensus", "--link-success", "1.5"), "--link-success (faults.link_success): must be at most 1.0 (got 1.5)"),
    (("kl-sweep", "--kl-weights", "-1"), "--kl-weights (learner.kl_weight): must be at least 0"),
    (("regularization", "--shapes", "2,sixty,1"), "--shapes: a model shape is a list of layer widths"),
    (("consensus", "--exchange-every", "7", "--rounds", "10"), "rounds (10) must be a multiple of exchange_every (7)"),
])
@pytest.mark.integration
def test_a_refused_argument_is_named_and_nothing_is_created(tmp_path, args, said):
    out = tmp_path / "out"
    proc = experiment(*args, "--preset", "smoke", "--out", str(out))
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert said in proc.stderr, proc.stderr
    assert "http" not in proc.stderr and "Traceback" not in proc.stderr and "validation error" not in proc.stderr
    assert not out.exists(), "a refused experiment left its --out folder"


@pytest.mark.integration
def test_an_out_folder_that_cannot_be_made_is_refused(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    proc = experiment("kl-sweep", "--preset", "smoke", "--out", str(blocker / "out"))
    assert proc.returncode == 2 and "--out: " in proc.stderr and "which is a file" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.integration
def test_scoring_a_path_that_is_no_run_says_so(tmp_path):
    f = tmp_path / "file.txt"
    f.write_text("not a run")
    for path, said in ((f, "is a file, not a run directory"), (tmp_path / "nope", "does not exist"),
                       (tmp_path, "holds no groundtruth.npz")):
        proc = experiment("score", str(path))
        assert proc.returncode == 2 and said in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
