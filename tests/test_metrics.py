"""Tests for shadowcorr.evaluation: hand-checked purities, coverage, ARI and summaries."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shadowcorr.evaluation import segment_metrics, summarize, voxel_ari


def test_perfect_prediction_with_permuted_ids() -> None:
    m = segment_metrics(np.array([0, 0, 1, 1, 1, 2]), np.array([7, 7, 3, 3, 3, 0]))
    assert m["rock_purity"] == m["cluster_purity"] == m["average_purity"] == 100.0
    assert m["perfect_one_to_one"] == 3 and m["perfect_one_to_one_share"] == 100.0
    assert (m["num_rocks"], m["num_objects"], m["num_segments"]) == (3, 3, 6)
    assert m["coverage"] == 100.0 and m["num_unlabelled"] == 0


def test_one_rock_split_in_two_objects() -> None:
    # rock 0 has 4 segments split 3 + 1; rock 1 is perfect
    m = segment_metrics(np.array([0, 0, 0, 0, 1, 1]), np.array([0, 0, 0, 1, 2, 2]))
    assert m["rock_purity"] == pytest.approx(100 * (3 / 4 + 1) / 2)  # 87.5
    assert m["cluster_purity"] == 100.0
    assert m["average_purity"] == pytest.approx((87.5 + 100) / 2)
    assert m["perfect_one_to_one"] == 1 and m["perfect_one_to_one_share"] == 50.0
    assert m["num_objects"] == 3


def test_two_rocks_merged_into_one_object() -> None:
    # rocks 0 (2 segments) and 1 (1 segment) in object 5; rock 2 alone in object 6
    m = segment_metrics(np.array([0, 0, 1, 2]), np.array([5, 5, 5, 6]))
    assert m["rock_purity"] == 100.0
    assert m["cluster_purity"] == pytest.approx(100 * (2 / 3 + 1) / 2)
    assert m["perfect_one_to_one"] == 1  # only rock 2
    assert m["perfect_one_to_one_share"] == pytest.approx(100 / 3)


def test_unlabelled_segments_are_singletons() -> None:
    # rock 0: segments in object 0, object 0, unlabelled -> rock purity 2/3
    # rock 1: its only segment unlabelled -> rock purity 1, but not perfect
    # objects: {0: rock0 x2}, two singletons -> cluster purity 1
    m = segment_metrics(np.array([0, 0, 0, 1]), np.array([0, 0, -1, -1]))
    assert m["rock_purity"] == pytest.approx(100 * (2 / 3 + 1) / 2)
    assert m["cluster_purity"] == 100.0
    assert m["coverage"] == 50.0
    assert m["perfect_one_to_one"] == 0
    assert m["num_objects"] == 1 and m["num_unlabelled"] == 2
    # two unlabelled segments of one rock are not put together
    m = segment_metrics(np.array([0, 0]), np.array([-1, -1]))
    assert m["rock_purity"] == 50.0 and m["coverage"] == 0.0


def test_segments_without_truth_only_count_for_coverage() -> None:
    m = segment_metrics(np.array([0, 0, -1]), np.array([1, 1, 2]))
    assert m["rock_purity"] == m["cluster_purity"] == 100.0
    assert m["num_segments"] == 3 and m["coverage"] == 100.0 and m["num_objects"] == 1
    empty = segment_metrics(np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert math.isnan(empty["rock_purity"]) and empty["num_rocks"] == 0


def test_segment_metrics_rejects_bad_input() -> None:
    with pytest.raises(ValueError):
        segment_metrics(np.array([0, 1]), np.array([0]))
    with pytest.raises(ValueError):
        segment_metrics(np.array([0.5]), np.array([0]))


def test_voxel_ari() -> None:
    assert voxel_ari(np.array([0, 0, 1, 1]), np.array([5, 5, 9, 9])) == pytest.approx(1.0)
    # hand-computed: contingency [[2,0],[1,1]] -> sum C(n_ij,2)=1, rows 1+1=2, cols 3+0=3,
    # expected 2*3/6 = 1, max (2+3)/2 = 2.5 -> ARI (1-1)/(2.5-1) = 0
    assert voxel_ari(np.array([0, 0, 1, 1]), np.array([0, 0, 0, 1])) == pytest.approx(0.0)
    # -1 truth is ignored; -1 predictions are singletons, not one shared cluster
    assert voxel_ari(np.array([0, 0, 1, 1, -1]), np.array([3, 3, 4, 4, 3])) == pytest.approx(1.0)
    assert voxel_ari(np.array([0, 1, 2]), np.array([-1, -1, -1])) == pytest.approx(1.0)
    assert math.isnan(voxel_ari(np.array([-1]), np.array([0])))


def test_summarize() -> None:
    out = summarize(
        [
            {"rock_purity": 100.0, "num_rocks": 3, "name": "a", "flag": True},
            {"rock_purity": 90.0, "num_rocks": 5, "voxel_ari": math.nan},
            {"rock_purity": 95.0, "voxel_ari": 0.9},
        ]
    )
    assert out["rock_purity"]["mean"] == pytest.approx(95.0)
    assert out["rock_purity"]["std"] == pytest.approx(np.std([100.0, 90.0, 95.0]))
    assert out["rock_purity"]["n"] == 3
    assert out["num_rocks"] == {"mean": 4.0, "std": 1.0, "n": 2}
    assert out["voxel_ari"]["n"] == 1 and out["voxel_ari"]["std"] == 0.0
    assert "name" not in out and "flag" not in out
    assert summarize([]) == {}
