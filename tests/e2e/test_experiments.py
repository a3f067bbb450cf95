"""``swarmmap experiment`` at smoke size: each runs the real system and writes its figures,
the CSV behind them and a report with the uncertainty scores."""

from __future__ import annotations

import csv
import json
import subprocess

import pytest
from PIL import Image

from tests.conftest import SWARMMAP, clean_env

pytestmark = pytest.mark.e2e



def run(*args: str) -> subprocess.CompletedProcess:
    proc = subprocess.run([*SWARMMAP, "experiment", *args], capture_output=True, text=True, timeout=600, env=clean_env())
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc


def assert_png(path, min_size=(300, 200)):
    with Image.open(path) as img:
        assert img.size[0] >= min_size[0] and img.size[1] >= min_size[1], f"{path}: {img.size}"


def test_kl_sweep_writes_maps_csv_and_report(tmp_path):
    out = tmp_path / "kl"
    run("kl-sweep", "--preset", "smoke", "--rounds", "10", "--kl-weights", "1e-4", "0.5", "--rooms", "1", "--out", str(out))
    assert_png(out / "kl_sweep_maps.png")
    rows = list(csv.DictReader((out / "kl_sweep.csv").open()))
    assert [float(r["kl_weight"]) for r in rows] == [1e-4, 0.5]
    for r in rows:
        assert 0 < float(r["final_val_bce"]) < 0.7
        assert 0 <= float(r["std_observed"]) <= 0.5 and float(r["ece"]) >= 0
    # A larger KL weight keeps the weights' spread nearer the prior: more std everywhere.
    assert float(rows[1]["std_observed"]) > float(rows[0]["std_observed"])
    report = (out / "report.md").read_text()
    assert "kl_sweep_maps.png" in report and "auroc_error" in report and "std_unobserved" in report
    assert "auroc_unobserved" in report and "reliability.png" in report
    assert_png(out / "reliability.png")
    for r in rows:
        assert 0 <= float(r["auroc_unobserved"]) <= 1
    # scoring a finished run writes its scores and reliability diagram, and keeps earlier ones
    first = run("score", str(out / "runs" / "kl-0.0001"))
    assert "auroc_unobserved" in first.stdout
    folder = out / "runs" / "kl-0.0001" / "scores"
    doc = json.loads((folder / "scores.json").read_text())
    assert set(doc["robots"]) == {"0"} and len(doc["robots"]["0"]["reliability"]["cells"]) == 10
    assert_png(folder / "reliability.png")
    second = run("score", str(out / "runs" / "kl-0.0001"), "--ensemble")
    assert list(folder.parent.glob("scores.replaced-*")), "earlier scores were not kept"
    assert "ensemble of 1 robot model(s)" in second.stdout
    ens = json.loads((folder / "scores.json").read_text())["ensemble"]
    assert ens["members"] == 1 and 0 <= ens["auroc_unobserved"] <= 1
    # one Bayesian member: its own spread, as its maps have it (the same 50 draws, seed 0)
    assert ens["std_observed"] == pytest.approx(doc["robots"]["0"]["std_observed"], rel=1e-3)
    # the spread of the logits instead: the same draws, unsquashed, so larger everywhere
    logit = run("score", str(out / "runs" / "kl-0.0001"), "--std-of", "logit")
    assert "auroc_unobserved" in logit.stdout
    lz = json.loads((folder / "scores.json").read_text())
    assert lz["std_of"] == "logit" and lz["robots"]["0"]["std_observed"] > doc["robots"]["0"]["std_observed"]
    assert 0 <= lz["robots"]["0"]["auroc_error"] <= 1
    # Run again: the finished runs are reused; with other settings they are not.
    again = run("kl-sweep", "--preset", "smoke", "--rounds", "10", "--kl-weights", "1e-4", "--rooms", "1", "--out", str(out))
    assert "reusing it" in again.stderr
    other = run("kl-sweep", "--preset", "smoke", "--rounds", "5", "--kl-weights", "1e-4", "--rooms", "1", "--out", str(out))
    assert "reusing it" not in other.stderr
    assert [float(r["final_val_bce"]) for r in csv.DictReader((out / "kl_sweep.csv").open())] != [
        float(rows[0]["final_val_bce"])], "a run of 5 rounds reported the 10-round result"


def test_mc_dropout_agent_saves_and_scores_its_spread(tmp_path):
    """The MC-dropout baseline through the same experiment: its maps have a std and are scored."""
    out = tmp_path / "drop"
    run("kl-sweep", "--preset", "smoke", "--rounds", "10", "--kl-weights", "0", "--rooms", "1", "--out", str(out),
        "--set", "learner.model=dropout", "--set", "learner.dropout_p=0.2")
    row = next(csv.DictReader((out / "kl_sweep.csv").open()))
    assert 0 < float(row["final_val_bce"]) < 0.7
    assert 0 < float(row["std_observed"]) <= 0.5 and 0 <= float(row["auroc_error"]) <= 1
    assert "MC dropout p 0.2" in (out / "report.md").read_text()
    assert (out / "runs" / "kl-0" / "maps" / "robot-0-std.png").exists()


def test_regularization_writes_curves_table_maps_and_report(tmp_path):
    """A grid of two W_rho/W_mu ratios: uniform-l2 (which has no W_rho) runs once and serves
    both; separate-kl runs at each ratio, with its W_rho in its config."""
    out = tmp_path / "reg"
    proc = run("regularization", "--preset", "smoke", "--robots", "2", "--rounds", "10", "--seeds", "0",
               "--strategies", "uniform-l2", "separate-kl", "--w-rho", "1", "2", "--out", str(out))
    for name in ("regularization_curves.png", "best_run_maps.png"):
        assert_png(out / name)
    runs = list(csv.DictReader((out / "regularization_runs.csv").open()))
    assert sorted((r["strategy"], r["w_rho_over_w_mu"]) for r in runs) == [
        ("separate-kl", "1.0"), ("separate-kl", "2.0"), ("uniform-l2", "")]
    assert sorted(p.name for p in (out / "runs").iterdir()) == [
        "separate-kl-128x64x64-kl0.005-wrho1-seed0", "separate-kl-128x64x64-kl0.005-wrho2-seed0",
        "uniform-l2-128x64x64-kl0.005-seed0"]
    assert "w_rho: 2.0" in (out / "runs" / "separate-kl-128x64x64-kl0.005-wrho2-seed0" / "config.yaml").read_text()
    curves = list(csv.DictReader((out / "regularization_curves.csv").open()))
    assert {(r["strategy"], r["w_rho_over_w_mu"]) for r in curves} == {
        ("separate-kl", "1.0"), ("separate-kl", "2.0"), ("uniform-l2", "1.0"), ("uniform-l2", "2.0")}
    assert {int(r["round"]) for r in curves} >= {0, 10}
    for r in curves:
        assert float(r["val_bce_min"]) <= float(r["val_bce_mean"]) <= float(r["val_bce_max"])
    report = (out / "report.md").read_text()
    assert report.count("separate-kl against it") == 1 and "seeds where separate-kl is lower" in report
    assert "W_rho/W_mu 1, kl_weight 0.005:" in report and "W_rho/W_mu 2, kl_weight 0.005:" in report
    assert "nll" in report and "best_run_maps.png" in report
    assert "Where separate-kl (Algorithm 2) stands" in proc.stdout  # the report is printed too


@pytest.mark.faults  # poor links; with the fault trials, so that the everyday tier stays under 15 min
def test_consensus_writes_curves_bytes_table_and_report(tmp_path):
    """A small grid: two rules over perfect and lossy links, and one compressed run; the bytes
    each learner sent come from the wire and topk sends far fewer."""
    out = tmp_path / "cons"
    run("consensus", "--preset", "smoke", "--robots", "2", "--rounds", "10", "--seeds", "0", "--consensus", "dinno",
        "sigma", "--link-success", "1", "0.3", "--exchange-every", "1", "--compression", "none", "topk",
        "--round-wait", "0.1", "--set", "learner.topk_density=0.02", "--out", str(out))
    rows = list(csv.DictReader((out / "consensus_runs.csv").open()))
    cells = {(r["consensus"], float(r["link_success"]), r["compression"]) for r in rows}
    assert cells == {("dinno", 1.0, "none"), ("sigma", 1.0, "none"), ("dinno", 0.3, "none"), ("sigma", 0.3, "none"),
                     ("dinno", 1.0, "topk")}
    by = {(r["consensus"], float(r["link_success"]), r["compression"]): r for r in rows}
    for r in rows:
        assert 0 < float(r["final_val_bce_mean_over_agents"]) < 1.0
    plain, thin = float(by["dinno", 1.0, "none"]["bytes_sent_per_learner"]), float(by["dinno", 1.0, "topk"]["bytes_sent_per_learner"])
    assert plain > 11 * 25_000 * 4 and plain / thin > 5  # 11 States of float32 at least, against 2% of them
    assert float(by["dinno", 0.3, "none"]["bytes_sent_per_learner"]) > 0
    assert_png(out / "consensus_curves.png")
    assert_png(out / "consensus_bytes.png")
    report = (out / "report.md").read_text()
    assert "sigma against dinno" in report and "fewer" in report and "auroc_unobserved" in report
