"""The calibrated support of ``fused``: the packaged calibration, its arithmetic against
scikit-learn's (logistic regression and boosted trees), what it says on the real sample, the
features it reads, and the quality benchmark's calibration error."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from shadowcorr import ShadowCorrConfig, correspond, load_model
from shadowcorr.stages import SUPPORT_FEATURES, SupportCalibration, support_calibration, support_features

from .harness import REPO_ROOT, load_bench_quality
from .paths import SAMPLE_DIR


def _fit_script():
    """``scripts/fit_support.py`` as a module (its node tables and model file are what ships)."""
    spec = importlib.util.spec_from_file_location("fit_support", REPO_ROOT / "scripts" / "fit_support.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_packaged_calibration_reads_this_versions_features():
    calibration = support_calibration()
    assert calibration.features == SUPPORT_FEATURES
    assert calibration.coef.shape == calibration.mean.shape == calibration.scale.shape == (len(SUPPORT_FEATURES),)
    assert (calibration.scale > 0).all() and 0.0 < calibration.check_below < 1.0
    assert "scripts/fit_support.py" in calibration.fitted_on
    trees = calibration.trees
    assert trees is not None and trees.depth >= 1
    assert trees.feature.shape == trees.threshold.shape == trees.left.shape == trees.right.shape == trees.value.shape
    assert 0 <= trees.feature.min() and trees.feature.max() < len(SUPPORT_FEATURES)
    # Two grouped segments that land on each other sit right (one of them with 30 of its 70
    # landings in view 2 on the stray); the stray that its own evidence pulls towards them (alone,
    # 50 of its 60 landings on their group) is worth checking.
    support = calibration.probability(support_features(_two_groups_and_a_stray(), ShadowCorrConfig()))
    assert (support[:2] > calibration.check_below).all()
    assert support[2] < calibration.check_below


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


def test_trees_are_the_boosted_model_that_was_fitted():
    """The node tables the fit writes give scikit-learn's probabilities, also read back from the model file."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    fit = _fit_script()
    rng = np.random.default_rng(2)
    f = len(SUPPORT_FEATURES)
    x = rng.normal(size=(3000, f)) * rng.uniform(0.5, 3.0, f)
    y = (x[:, 0] * x[:, 3] - np.abs(x[:, 5]) + rng.normal(size=3000)) > -1.0
    model = HistGradientBoostingClassifier(max_iter=30, max_leaf_nodes=7, random_state=0).fit(x, y)
    tables, baseline = fit.tree_tables(model)
    calibration = SupportCalibration(SUPPORT_FEATURES, np.zeros(f), np.ones(f), np.zeros(f), baseline, 0.4, "t", tables)
    expected = model.predict_proba(x)[:, 1]
    np.testing.assert_allclose(calibration.probability(x), expected, rtol=1e-10)
    again = SupportCalibration.from_json(json.loads(fit.model_text(calibration.to_json())))
    np.testing.assert_allclose(again.probability(x), expected, rtol=1e-10)
    assert again.check_below == 0.4


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
    source, target, count = np.array([0, 1, 0, 2]), np.array([1, 0, 2, 0]), np.array([80, 80, 30, 50])
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
    # 30 of 0's 70 landings in view 2 fall on the other group there, none of 1's: their group's mean is 3/14.
    np.testing.assert_allclose(column["group_other_share"][:2], [3 / 14, 3 / 14])
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


def _a_group_with_two_masks_of_one_view():
    """Three segments in one group: 0 (view 0, mask 1, 100 sample points) and 1 (view 0, mask 2,
    50 points) both land on 2 (view 1, 100 points), 2 lands mostly on 0."""
    from shadowcorr.stages._03_surface_evidence import SurfaceEvidence
    from shadowcorr.stages._09_grouping import EvidenceGroups, SegmentGraph

    visible, on_mask = np.zeros((3, 2), dtype=np.int64), np.zeros((3, 2), dtype=np.int64)
    visible[0, 1], visible[1, 1], visible[2, 0] = 90, 40, 95
    on_mask[0, 1], on_mask[1, 1], on_mask[2, 0] = 85, 20, 90
    source, target, count = np.array([0, 1, 2, 2]), np.array([2, 2, 0, 1]), np.array([80, 5, 60, 10])
    samples = np.array([100, 50, 100])
    surface = SurfaceEvidence(samples, np.zeros((250, 3), np.float32), visible, on_mask, source, target, count)
    none = np.zeros(0, dtype=np.int64)
    graph = SegmentGraph(np.array([0, 0, 1]), np.array([1, 2, 1]), surface, none, none, np.zeros(0), np.zeros(0))
    return EvidenceGroups(np.array([4, 4, 4]), graph, np.zeros(3, dtype=bool))


def test_support_features_read_two_masks_of_one_view_in_a_group():
    x = support_features(_a_group_with_two_masks_of_one_view(), ShadowCorrConfig())
    column = {name: x[:, i] for i, name in enumerate(SUPPORT_FEATURES)}
    np.testing.assert_array_equal(column["view_rivals"], [1, 1, 0])
    np.testing.assert_allclose(column["view_share"], [100 / 150, 50 / 150, 1.0])
    np.testing.assert_array_equal(column["group_rival_views"], [1, 1, 1])
    # Of its points visible where the rest of the group is, the share landing on the group, and on no mask.
    own_cover = np.array([80 / 90, 5 / 40, 70 / 95])
    np.testing.assert_allclose(column["own_cover"], own_cover)
    np.testing.assert_allclose(column["off_mask"], [1 - 85 / 90, 1 - 20 / 40, 1 - 90 / 95])
    # Of the group's points visible in its view (its own none), the share landing on it; of those on a mask.
    reverse_cover = np.array([60 / 95, 10 / 95, 85 / 130])
    np.testing.assert_allclose(column["reverse_cover"], reverse_cover)
    np.testing.assert_allclose(column["reverse_share"], [60 / 90, 10 / 90, 85 / 105])
    np.testing.assert_allclose(column["group_own_cover"], np.full(3, own_cover.mean()))
    np.testing.assert_allclose(column["group_reverse_cover"], np.full(3, reverse_cover.mean()))


def test_support_features_of_a_group_without_rivals_or_other_views():
    x = support_features(_two_groups_and_a_stray(), ShadowCorrConfig())
    column = {name: x[:, i] for i, name in enumerate(SUPPORT_FEATURES)}
    np.testing.assert_array_equal(column["view_rivals"], [0, 0, 0, 0])
    np.testing.assert_array_equal(column["view_share"], [1, 1, 1, 1])
    # 0 and 1 land on each other (80 of 90 visible points); 2 and 3 are alone: nothing to cover, nothing off.
    np.testing.assert_allclose(column["own_cover"], [80 / 90, 80 / 90, 1, 1])
    np.testing.assert_allclose(column["off_mask"], [0, 0, 0, 0])
    np.testing.assert_allclose(column["reverse_cover"], [80 / 90, 80 / 90, 1, 1])
