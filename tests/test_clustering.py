"""Tests for shadowcorr.stages (stage 09 clustering): MeanShift parity with scikit-learn, merging, voting."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.cluster import MeanShift
from sklearn.metrics import adjusted_rand_score
from threadpoolctl import threadpool_limits

from shadowcorr.stages import _09_clustering as clustering  # private knobs: block sizes
from shadowcorr.stages import majority_vote, mean_shift, merge_small_clusters


def _unit_blobs(n: int, dim: int, k: int, spread: float, noise: float, seed: int) -> np.ndarray:
    """L2-normalised embeddings: k blobs around random unit directions plus uniform noise."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(k, dim))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    n_noise = int(n * noise)
    pts = centres[rng.integers(0, k, n - n_noise)] + rng.normal(scale=spread, size=(n - n_noise, dim))
    pts = np.vstack([pts, rng.normal(size=(n_noise, dim))])
    return (pts / np.linalg.norm(pts, axis=1, keepdims=True)).astype(np.float32)


def _grid_blobs(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(n, 2)) + 3.0 * rng.integers(0, 4, size=(n, 2))).astype(np.float32)


# Small enough that scikit-learn stays well under a second per case on a shared CPU.
PARITY_CASES = [
    pytest.param(_unit_blobs(300, 32, 12, 0.06, 0.05, seed=0), 0.7, id="32d-tight-seed0"),
    pytest.param(_unit_blobs(300, 32, 6, 0.15, 0.05, seed=1), 0.7, id="32d-wide-seed1"),
    pytest.param(_grid_blobs(250, seed=2), 1.0, id="2d-touching-seed2"),
    pytest.param(np.random.default_rng(3).normal(size=(200, 3)), 0.5, id="3d-float64-seed3"),
    pytest.param(np.repeat(np.random.default_rng(4).normal(size=(60, 8)).astype(np.float32), 3, axis=0), 1.5,
                 id="8d-duplicates-seed4"),
]


@pytest.mark.parametrize(("x", "bw"), PARITY_CASES)
def test_mean_shift_matches_sklearn(x: np.ndarray, bw: float) -> None:
    labels, centers = mean_shift(x, bw)
    # One thread for the reference: its per-seed radius queries open an OpenMP region
    # each, which crawls when the (shared) cores are busy.
    with threadpool_limits(1):
        ref = MeanShift(bandwidth=bw).fit(x)
    assert labels.dtype == np.int64 and labels.shape == (x.shape[0],)
    assert centers.dtype == x.dtype and centers.shape[1] == x.shape[1]
    assert adjusted_rand_score(ref.labels_, labels) >= 0.99
    # The same modes in the same order, and (nearly) every point labelled alike.
    assert centers.shape == ref.cluster_centers_.shape
    np.testing.assert_allclose(centers, ref.cluster_centers_, atol=1e-5)
    assert np.mean(labels == ref.labels_) >= 0.99


def test_mean_shift_blocking_does_not_change_result(monkeypatch: pytest.MonkeyPatch) -> None:
    x = _unit_blobs(500, 32, 10, 0.1, 0.2, seed=5)
    labels, centers = mean_shift(x, 0.7)
    # Tiny blocks force many seed blocks and many suppression blocks (> 100 modes here).
    monkeypatch.setattr(clustering, "_BLOCK_ELEMENTS", 1000)
    monkeypatch.setattr(clustering, "_NMS_BLOCK", 7)
    labels_b, centers_b = mean_shift(x, 0.7)
    assert centers.shape[0] > 50
    np.testing.assert_array_equal(labels, labels_b)
    np.testing.assert_allclose(centers, centers_b, atol=1e-6)


def test_mean_shift_max_iter_and_tol_match_sklearn() -> None:
    x = _grid_blobs(150, seed=7)
    for max_iter, tol in [(0, 1e-3), (2, 1e-3)]:
        labels, centers = mean_shift(x, 1.2, max_iter=max_iter, tol=tol)
        with threadpool_limits(1):
            ref = MeanShift(bandwidth=1.2, max_iter=max_iter).fit(x)
        assert adjusted_rand_score(ref.labels_, labels) >= 0.99
        assert centers.shape == ref.cluster_centers_.shape


def test_greedy_within_block_equals_sequential_greedy() -> None:
    rng = np.random.default_rng(8)
    for _ in range(100):
        b = int(rng.integers(1, 40))
        p = rng.uniform(0, rng.uniform(1, 10), size=(b, 2))
        adjacent = np.linalg.norm(p[:, None] - p[None], axis=-1) <= 1.0
        expected = np.ones(b, dtype=bool)
        for i in range(b):  # the textbook sequential rule, as the reference
            if expected[i]:
                expected[i + 1 :] &= ~adjacent[i, i + 1 :]
        np.testing.assert_array_equal(clustering._greedy_within_block(adjacent), expected)


def test_mean_shift_modes_far_apart_and_labels_nearest() -> None:
    x = _unit_blobs(600, 32, 8, 0.08, 0.0, seed=6)
    labels, centers = mean_shift(x, 0.7)
    d = np.linalg.norm(centers[:, None] - centers[None], axis=-1)
    assert np.all(d[np.triu_indices(len(centers), 1)] > 0.7)
    to_centre = np.linalg.norm(x[:, None] - centers[None], axis=-1)
    np.testing.assert_array_equal(labels, to_centre.argmin(1))
    assert len(centers) == 8  # one mode per blob


def test_mean_shift_edge_cases() -> None:
    labels, centers = mean_shift(np.zeros((0, 4), np.float32), 1.0)
    assert labels.shape == (0,) and centers.shape == (0, 4)
    labels, centers = mean_shift(np.ones((5, 3), np.float32), 0.1)  # all equal points
    assert np.all(labels == 0) and centers.shape == (1, 3)
    labels, _ = mean_shift(np.array([[0.0], [10.0], [20.0]]), 1.0)  # isolated points
    assert sorted(labels.tolist()) == [0, 1, 2]
    with pytest.raises(ValueError):
        mean_shift(np.ones((3, 2)), 0.0)
    with pytest.raises(ValueError):
        mean_shift(np.array([[np.nan, 0.0]]), 1.0)
    with pytest.raises(ValueError):
        mean_shift(np.ones(3), 1.0)


def test_merge_small_clusters_into_nearest_large() -> None:
    x = np.array([[0.0], [0.1], [0.2], [10.0], [10.1], [10.2], [10.3], [1.0], [9.0], [50.0]])
    labels = np.array([5, 5, 5, 2, 2, 2, 2, 7, 8, 9])
    out = merge_small_clusters(x, labels, min_size=3)
    # 7 (at 1.0) -> cluster 5, 8 (at 9.0) and 9 (at 50) -> cluster 2; renumbered by size:
    # cluster 2 (7 points) -> 0, cluster 5 (4 points) -> 1.
    np.testing.assert_array_equal(out, [1, 1, 1, 0, 0, 0, 0, 1, 0, 0])


def test_merge_small_clusters_keeps_labels_when_none_is_large() -> None:
    x = np.array([[0.0], [1.0], [2.0], [3.0]])
    out = merge_small_clusters(x, np.array([4, 4, 9, 1]), min_size=5)
    # nothing merges; renumbered by size desc, ties by original label asc: 4 -> 0, 1 -> 1, 9 -> 2
    np.testing.assert_array_equal(out, [0, 0, 2, 1])


def test_merge_small_clusters_ignores_negative_and_is_order_free() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, 3))
    labels = rng.integers(-1, 6, size=40)
    out = merge_small_clusters(x, labels, min_size=8)
    assert np.all(out[labels < 0] == -1)
    assert set(out[labels >= 0].tolist()) == set(range(out.max() + 1))
    perm = rng.permutation(40)
    np.testing.assert_array_equal(merge_small_clusters(x[perm], labels[perm], min_size=8), out[perm])


def test_majority_vote_ties_empty_groups_and_weights() -> None:
    labels = np.array([3, 3, 1, 2, 2, 1, 1, 0, -1, -1])
    groups = np.array([0, 0, 0, 1, 1, 1, 1, 2, 2, 4])
    lab, sup = majority_vote(labels, groups, num_groups=5)
    # group 0: 3 wins 2/3; group 1: tie 2 vs 1 -> smallest label 1; group 2: only label 0
    # (the unlabelled point casts no vote); group 3: no points; group 4: only unlabelled.
    np.testing.assert_array_equal(lab, [3, 1, 0, -1, -1])
    np.testing.assert_allclose(sup, [2 / 3, 0.5, 1.0, 0.0, 0.0])

    w = np.array([1.0, 1.0, 5.0, 1, 1, 1, 1, 1, 1, 1])
    lab, sup = majority_vote(labels, groups, num_groups=5, weights=w)
    assert lab[0] == 1 and sup[0] == pytest.approx(5 / 7)

    lab, sup = majority_vote(np.array([4, 5]), np.array([0, 0]), 1, weights=np.zeros(2))
    assert lab[0] == -1 and sup[0] == 0.0


def test_majority_vote_matches_dense_reference() -> None:
    rng = np.random.default_rng(1)
    labels = rng.integers(0, 7, size=3000)
    groups = rng.integers(0, 50, size=3000)
    lab, sup = majority_vote(labels, groups, 52)
    table = np.zeros((52, 7))
    np.add.at(table, (groups, labels), 1.0)
    expected = np.where(table.sum(1) > 0, table.argmax(1), -1)  # argmax takes the first (smallest) on ties
    np.testing.assert_array_equal(lab, expected)
    with np.errstate(invalid="ignore"):
        np.testing.assert_allclose(sup, np.nan_to_num(table.max(1) / table.sum(1)))


def test_majority_vote_rejects_bad_input() -> None:
    with pytest.raises(ValueError):
        majority_vote(np.array([0, 1]), np.array([0, 3]), 2)
    with pytest.raises(ValueError):
        majority_vote(np.array([0, 1]), np.array([0, 1]), 2, weights=np.array([1.0, -1.0]))
