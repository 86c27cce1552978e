"""The calibrated support of ``fused``: the packaged calibration, its arithmetic against
scikit-learn's, what it says on the real sample, and the quality benchmark's calibration error."""

from __future__ import annotations

import numpy as np
import pytest

from shadowcorr import ShadowCorrConfig, correspond, load_model
from shadowcorr.stages import SUPPORT_FEATURES, SupportCalibration, support_calibration

from .harness import load_bench_quality
from .paths import SAMPLE_DIR


def test_the_packaged_calibration_reads_this_versions_features():
    calibration = support_calibration()
    assert calibration.features == SUPPORT_FEATURES
    assert calibration.coef.shape == calibration.mean.shape == calibration.scale.shape == (len(SUPPORT_FEATURES),)
    assert (calibration.scale > 0).all() and 0.0 < calibration.check_below < 1.0
    assert "scripts/fit_support.py" in calibration.fitted_on
    # The evidence margin for the segment's own group raises the probability that it sits right.
    assert calibration.coef[SUPPORT_FEATURES.index("margin")] > 0


def test_probability_is_the_logistic_regression_that_was_fitted():
    from sklearn.linear_model import LogisticRegression

    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, len(SUPPORT_FEATURES))) * rng.uniform(0.5, 3.0, len(SUPPORT_FEATURES))
    y = (x[:, 0] - 0.5 * x[:, 3] + rng.normal(size=400)) > 0
    mean, scale = x.mean(axis=0), x.std(axis=0)
    model = LogisticRegression().fit((x - mean) / scale, y)
    calibration = SupportCalibration(SUPPORT_FEATURES, mean, scale, model.coef_[0], float(model.intercept_[0]), 0.3, "t")
    expected = model.predict_proba((x - mean) / scale)[:, 1]
    np.testing.assert_allclose(calibration.probability(x), expected, rtol=1e-10)
    again = SupportCalibration.from_json(calibration.to_json())
    np.testing.assert_allclose(again.probability(x), expected, rtol=1e-10)


@pytest.mark.skipif(not SAMPLE_DIR.is_dir(), reason="sample data not available")
def test_the_clean_samples_support_says_it_is_right():
    """Every segment of the clean sample sits with its own rock (purity 100). A calibrated support
    says so on average (its mean is near the share that sits right), and the flag, tuned for 50 %
    precision on scenes with errors, raises few false alarms here."""
    from shadowcorr.convert.ue import load_ue_scene

    result = correspond(load_ue_scene(SAMPLE_DIR, 2001, (0, 2, 4, 6)), load_model(), ShadowCorrConfig())
    assert result.metrics["average_purity"] == 100.0
    support = np.array([s.support for s in result.segments])
    assert ((support > 0) & (support < 1)).all()
    assert support.mean() > 0.95
    assert (support < support_calibration().check_below).mean() < 0.05


def test_the_benchmarks_calibration_error_is_the_binned_gap():
    bench = load_bench_quality()
    # Two runs' bins: 10 segments at support ~0.95 of which 9 right, 4 at ~0.25 of which 2 right.
    first = [[0] * 10, [0.0] * 10, [0.0] * 10]
    first[0][9], first[1][9], first[2][9] = 6, 5.7, 5.0
    second = [[0] * 10, [0.0] * 10, [0.0] * 10]
    second[0][9], second[1][9], second[2][9] = 4, 3.8, 4.0
    second[0][2], second[1][2], second[2][2] = 4, 1.0, 2.0
    expected = 10 / 14 * abs(9 / 10 - 9.5 / 10) + 4 / 14 * abs(2 / 4 - 1.0 / 4)
    assert bench.calibration_error([first, second]) == pytest.approx(expected)
    assert np.isnan(bench.calibration_error([]))


def _two_groups_and_a_stray():
    """Four segments in three views: 0 (view 0) and 1 (view 1) grouped, 2 (view 2) alone but
    landing on 0 and 0 on it, 3 (view 2) alone without evidence.  100 sample points each."""
    from shadowcorr.stages._03_surface_evidence import SurfaceEvidence
    from shadowcorr.stages._09_grouping import EvidenceGroups, SegmentGraph

    on_mask = np.zeros((4, 3), dtype=np.int64)
    on_mask[0, 1], on_mask[0, 2], on_mask[1, 0], on_mask[2, 0] = 90, 70, 90, 60
    source, target, count = np.array([0, 1, 0, 2]), np.array([1, 0, 2, 0]), np.array([80, 80, 60, 50])
    samples = np.full(4, 100)
    surface = SurfaceEvidence(samples, np.zeros((400, 3), np.float32), on_mask.copy(), on_mask, source, target, count)
    none = np.zeros(0, dtype=np.int64)
    graph = SegmentGraph(np.array([0, 1, 2, 2]), np.array([1, 1, 1, 2]), surface, none, none, np.zeros(0), np.zeros(0))
    return EvidenceGroups(np.array([0, 0, 1, 2]), graph, np.zeros(4, dtype=bool))


def test_support_features_read_the_group_and_its_rivals():
    from shadowcorr.stages import support_features

    x = support_features(_two_groups_and_a_stray(), ShadowCorrConfig())
    column = {name: x[:, i] for i, name in enumerate(SUPPORT_FEATURES)}
    assert x.shape == (4, len(SUPPORT_FEATURES))
    # Segment 0 lands in views 1 and 2; its group holds nothing in view 2.
    np.testing.assert_array_equal(column["landing_views"], [2, 1, 1, 0])
    np.testing.assert_array_equal(column["missing_views"], [1, 0, 1, 0])
    np.testing.assert_allclose(column["group_size"], np.log([2, 2, 1, 1]))
    # Evidence with one other group (0 and 2 land on each other), none for 1's and 3's.
    np.testing.assert_allclose(column["candidates"], np.log1p([1, 0, 1, 0]))
    # 2's group (100 points) against the group it is linked to (200): the smaller one.
    assert column["pull_size"][2] == pytest.approx(np.log(101 / 201))
    assert column["pull_size"][0] == pytest.approx(np.log(201 / 101))
    assert column["pull_size"][3] == 0.0
    # 60 of 0's 70 landings in view 2 fall on the other group there, none of 1's: their group's mean is 3/7.
    np.testing.assert_allclose(column["group_other_share"][:2], [3 / 7, 3 / 7])
    assert column["group_other_share"][2] == pytest.approx(50 / 60)  # 50 of its 60 landings in view 0 on 0


def test_a_calibration_on_some_features_reads_them_by_name():
    names = ("candidates", "margin", "group_other_share")
    rng = np.random.default_rng(1)
    full = rng.normal(size=(50, len(SUPPORT_FEATURES)))
    picked = full[:, [SUPPORT_FEATURES.index(n) for n in names]]
    calibration = SupportCalibration(names, np.zeros(3), np.ones(3), np.array([-1.0, 2.0, -0.5]), 0.3, 0.5, "t")
    expected = 1.0 / (1.0 + np.exp(-(0.3 + picked @ np.array([-1.0, 2.0, -0.5]))))
    np.testing.assert_allclose(calibration.probability(full), expected)
    np.testing.assert_allclose(calibration.probability(picked), expected)
