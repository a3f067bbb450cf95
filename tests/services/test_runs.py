"""``swarmmap runs``, ``logs`` and ``compare`` on run directories as the recorder leaves them."""

from __future__ import annotations

import argparse
import subprocess

import pytest
from PIL import Image

from swarmmap.services.runs import ToolError, compare, list_runs, show_logs
from tests.conftest import SWARMMAP, clean_env, recorded_run

pytestmark = pytest.mark.timeout(60)


def test_runs_lists_every_run_with_its_status_robots_rounds_and_final_loss(tmp_path, capsys):
    recorded_run(tmp_path / "runs" / "good", ok=True, losses=(0.10, 0.20))
    recorded_run(tmp_path / "runs" / "bad", ok=False, losses=(0.30, 0.40, 0.50), rounds=40)
    (tmp_path / "runs" / "not-a-run").mkdir()
    assert list_runs(argparse.Namespace(folder=tmp_path / "runs")) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["run", "status", "robots", "rounds", "final", "val_bce", "started", "what"]
    rows = {line.split()[0]: line.split() for line in lines[1:]}
    assert sorted(rows) == ["bad", "good"]
    assert rows["good"][1:5] == ["ok", "2", "60", "0.1500"] and rows["bad"][1:5] == ["failed", "3", "40", "0.4000"]
    assert all(line.endswith("smoke, fourier, procedural 2x2, 2 robots") for line in lines[1:] if "good" in line)
    with pytest.raises(ToolError, match="does not exist"):
        list_runs(argparse.Namespace(folder=tmp_path / "elsewhere"))


def test_logs_lists_a_runs_logs_and_prints_one_or_every_learners(tmp_path, capsys):
    run_dir = recorded_run(tmp_path / "run")
    for name, text in (("learner-0", "a\nb\nc\n"), ("learner-1", "d\n"), ("world-0", "w\n")):
        (run_dir / "logs" / f"{name}.log").write_text(text)
    show_logs(argparse.Namespace(run_dir=run_dir, service=None, tail=0))
    assert [line.split()[0] for line in capsys.readouterr().out.splitlines()] == ["learner-0", "learner-1", "world-0"]
    show_logs(argparse.Namespace(run_dir=run_dir, service="learner-0", tail=2))
    assert capsys.readouterr().out == "b\nc\n"
    show_logs(argparse.Namespace(run_dir=run_dir, service="learner", tail=0))
    out = capsys.readouterr().out
    assert "==> " in out and "learner-1.log <==\nd" in out and "w" not in out.replace("==>", "")
    with pytest.raises(ToolError, match="did you mean 'world-0'"):
        show_logs(argparse.Namespace(run_dir=run_dir, service="wrold-0", tail=0))


def test_compare_prints_each_runs_result_and_plots_both_curves(tmp_path, capsys):
    a = recorded_run(tmp_path / "a", losses=(0.10, 0.20))
    b = recorded_run(tmp_path / "b", losses=(0.30, 0.30))
    out = tmp_path / "fig" / "ab.png"
    assert compare(argparse.Namespace(runs=[str(a), f"{b}=slow"], out=out, target=0.2)) == 0
    text = capsys.readouterr().out
    assert "a (smoke, fourier, procedural 2x2, 2 robots): reached 0.2 at round 60, 42 s; final mean val_bce 0.1500" in text
    assert "slow: never reached 0.2; final mean val_bce 0.3000" in text
    with Image.open(out) as img:
        assert img.size[0] > 2 * img.size[1] * 0.9  # two panels side by side
    with pytest.raises(ToolError, match="exists; name another --out"):
        compare(argparse.Namespace(runs=[str(a), str(b)], out=out, target=None))
    for name in ("compare.png", "compare-2.png"):  # by default into the first run, never over a file
        assert compare(argparse.Namespace(runs=[str(a), str(b)], out=None, target=None)) == 0
        assert (a / name).exists() and f"curves: {a / name}" in capsys.readouterr().out
    with pytest.raises(ToolError, match="not a run directory"):
        compare(argparse.Namespace(runs=[str(tmp_path / "nope")], out=out, target=None))


@pytest.mark.integration
def test_a_wrong_path_is_a_message_and_status_2_not_a_traceback(tmp_path):
    for args in (["runs", str(tmp_path / "nope")], ["logs", str(tmp_path / "nope")], ["compare", str(tmp_path)]):
        proc = subprocess.run([*SWARMMAP, *args], capture_output=True, text=True, timeout=30, env=clean_env())
        assert proc.returncode == 2 and "Traceback" not in proc.stderr and str(tmp_path) in proc.stderr, proc.stderr
