"""The uncertainty scores: AUROC, calibration, observed cells, and the std ratio."""

from __future__ import annotations

import math

import numpy as np

from swarmmap.shared.learning.uncertainty import auroc, calibration_error, observed_mask, score_map


def test_auroc_ranks_perfectly_randomly_and_backwards():
    assert auroc([0.1, 0.2, 0.8, 0.9], [0, 0, 1, 1]) == 1.0
    assert auroc([0.9, 0.8, 0.2, 0.1], [0, 0, 1, 1]) == 0.0
    assert auroc([0.5, 0.5, 0.5, 0.5], [0, 1, 0, 1]) == 0.5  # ties count half
    assert math.isnan(auroc([0.1, 0.2], [1, 1]))


def test_calibration_error_is_zero_for_calibrated_and_large_for_confident_wrong():
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 1, 200_000)
    truth = rng.uniform(0, 1, p.size) < p  # events happen with the predicted probability
    assert calibration_error(p, truth) < 0.01
    assert calibration_error(np.full(100, 0.99), np.zeros(100)) > 0.9


def test_observed_mask_grows_by_the_radius():
    pts = np.array([[0.55, 0.55]])  # cell (5, 5) of a 0.1 m grid at the origin
    one = observed_mask((11, 11), (0.0, 0.0), 0.1, pts, radius_m=0.0)
    assert one.sum() == 1 and one[5, 5]
    grown = observed_mask((11, 11), (0.0, 0.0), 0.1, pts, radius_m=0.2)
    assert grown[5, 7] and grown[3, 5] and not grown[5, 8]
    assert not observed_mask((3, 3), (0.0, 0.0), 0.1, np.zeros((0, 2)), 0.1).any()


def test_score_map_reports_more_std_where_unobserved():
    truth = np.zeros((4, 4), bool)
    truth[:, 0] = True
    mean = np.where(truth, 0.9, 0.1)
    observed = np.zeros((4, 4), bool)
    observed[:, :2] = True
    std = np.where(observed, 0.01, 0.2)
    s = score_map(mean, std, truth, observed)
    assert s["accuracy"] == 1.0
    assert math.isclose(s["nll"], -math.log(0.9), rel_tol=1e-6)
    assert math.isclose(s["std_ratio"], 20.0, rel_tol=1e-6)
    assert s["observed_fraction"] == 0.5
    assert s["auroc_unobserved"] == 1.0  # every unseen cell more uncertain than every seen one
    assert score_map(mean, np.where(observed, 0.2, 0.01), truth, observed)["auroc_unobserved"] == 0.0
    assert math.isnan(s["auroc_error"])  # no error to find
    wrong = mean.copy()
    wrong[3, 3] = 0.8  # a confident mistake where the std is high
    assert score_map(wrong, std, truth, observed)["auroc_error"] > 0.5
