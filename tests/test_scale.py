"""Scaling: component-wise segment-id embeddings and the scene size limits."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from shadowcorr import SceneLimitError, ShadowCorrConfig, assign, correspond, embed, load_model, prepare
from shadowcorr.stages import cooccurrence, segment_embedding_loss, train_segment_embeddings
from shadowcorr.stages._06_segment_embedding import _packed_components

from .scenes import sphere_scene


@pytest.fixture(scope="module")
def model():
    return load_model()


def same_partition(a, b) -> bool:
    """Two labelings describe the same grouping (up to renaming)."""
    pairs = set(zip(np.asarray(a).tolist(), np.asarray(b).tolist()))
    return len(pairs) == len(set(np.asarray(a).tolist())) == len(set(np.asarray(b).tolist()))


@pytest.fixture(scope="module")
def two_clusters():
    """Two groups of touching spheres 40 m apart, each seen by its own ring of cameras:
    no shadow of one group reaches the other, so the co-occurrence graph has separate components."""
    near = sphere_scene([[-60, 0, 0], [60, 0, 0], [0, 90, 0]], [50, 45, 40], cameras=4)
    far = sphere_scene([[3940, 0, 0], [4060, 0, 0]], [50, 45], cameras=4)
    for i, v in enumerate(far.views):  # distinct view names and object ids
        v.name = f"far{i}"
        v.mask = np.where(v.mask > 0, v.mask.astype(np.int32) + 10, 0)
    near.views += far.views
    return near


def test_component_embeddings_give_the_whole_scene_partition(two_clusters):
    model = load_model()
    scene = prepare(two_clusters)
    cooc = cooccurrence(scene.member_voxel, scene.member_segment, scene.num_voxels, scene.num_segments)
    assert connected_components(cooc, directed=False)[0] >= 2  # the case the scope changes
    component = correspond(two_clusters, model, ShadowCorrConfig(segment_embedding_scope="component"))
    whole = correspond(two_clusters, model, ShadowCorrConfig(segment_embedding_scope="scene"))
    assert same_partition([s.object for s in component.segments], [s.object for s in whole.segments])
    assert component.metrics["average_purity"] >= whole.metrics["average_purity"]


def block_cooccurrence(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    n, m = first.shape[0], second.shape[0]
    out = np.zeros((n + m, n + m))
    out[:n, :n], out[n:, n:] = first, second
    return out


def test_a_component_is_trained_independently_of_the_others():
    first = np.array([[0, 9, 1], [9, 0, 4], [1, 4, 0]], dtype=float)
    second_a = np.array([[0, 5, 0, 0], [5, 0, 2, 0], [0, 2, 0, 3], [0, 0, 3, 0]], dtype=float)
    second_b = np.array([[0, 1, 1, 1], [1, 0, 8, 1], [1, 8, 0, 1], [1, 1, 1, 0]], dtype=float)
    centroids = np.arange(21, dtype=float).reshape(7, 3)
    cfg = ShadowCorrConfig()
    za = train_segment_embeddings(block_cooccurrence(first, second_a), centroids, cfg)
    zb = train_segment_embeddings(block_cooccurrence(first, second_b), centroids, cfg)
    np.testing.assert_allclose(za[:3], zb[:3], atol=1e-6)  # padding and batching leak nothing
    assert not np.allclose(za[3:], zb[3:], atol=1e-3)
    # Training lowers the component-restricted loss, and listing order does not matter.
    cooc = block_cooccurrence(first, second_a)
    z0 = train_segment_embeddings(cooc, centroids, cfg.with_options(segment_embedding_steps=0))
    assert segment_embedding_loss(za, cooc, cfg) < segment_embedding_loss(z0, cooc, cfg) - 0.1
    perm = np.array([4, 0, 6, 2, 5, 1, 3])
    zp = train_segment_embeddings(cooc[np.ix_(perm, perm)], centroids[perm], cfg)
    np.testing.assert_allclose(zp, za[perm], atol=1e-5)


def test_components_packed_into_one_problem_stay_independent():
    # Sizes 4, 2, 2: the two pairs share one packed problem of width 4.
    big = np.array([[0, 5, 0, 0], [5, 0, 2, 0], [0, 2, 0, 3], [0, 0, 3, 0]], dtype=float)
    pair = np.array([[0, 3], [3, 0]], dtype=float)
    cooc = np.zeros((8, 8))
    cooc[:4, :4], cooc[4:6, 4:6], cooc[6:, 6:] = big, pair, pair
    batches = _packed_components(csr_matrix(cooc))
    assert [m.shape for m, _ in batches] == [(2, 4)]
    packed_row = batches[0][1][1]
    assert np.unique(packed_row[packed_row >= 0]).size == 2  # two components in one problem
    centroids = np.arange(24, dtype=float).reshape(8, 3)
    cfg = ShadowCorrConfig()
    together = train_segment_embeddings(cooc, centroids, cfg)
    alone = cooc.copy()
    alone[6:, 6:] = 0  # the packed partner gone: the pair at 4-5 must not notice
    apart = train_segment_embeddings(alone, centroids, cfg)
    np.testing.assert_allclose(together[:6], apart[:6], atol=1e-6)
    # Each component's loss is its own: the whole-scene loss is their mean.
    z0 = train_segment_embeddings(cooc, centroids, cfg.with_options(segment_embedding_steps=0))
    assert segment_embedding_loss(together, cooc, cfg) < segment_embedding_loss(z0, cooc, cfg) - 0.1


def test_scene_limits_raise_before_heavy_work(two_clusters):
    with pytest.raises(SceneLimitError) as err:
        prepare(two_clusters, ShadowCorrConfig(max_segments=3))
    assert err.value.limit == "max_segments" and err.value.value > 3 and err.value.maximum == 3
    assert "max_segments = 3" in str(err.value) and isinstance(err.value, ValueError)
    with pytest.raises(SceneLimitError) as err:
        prepare(two_clusters, ShadowCorrConfig(max_voxels=10))
    assert err.value.limit == "max_voxels" and err.value.value > 10


def test_a_stage_over_its_time_budget_refuses_the_scene(two_clusters, model):
    # No stage of this tiny scene takes 1 microsecond or less: the first stage to end refuses it.
    with pytest.raises(SceneLimitError) as err:
        prepare(two_clusters, ShadowCorrConfig(max_stage_seconds=1e-6))
    assert err.value.limit == "max_stage_seconds" and err.value.value > 1e-6
    assert "stage 'poses'" in str(err.value) and "max_stage_seconds = 1e-06" in str(err.value)
    # The budget is checked in assign too (grouping), and a generous one changes nothing.
    scene = prepare(two_clusters)
    (emb,) = embed(model, [scene])
    with pytest.raises(SceneLimitError, match="max_stage_seconds"):
        assign(scene, emb, scene.config.with_options(max_stage_seconds=1e-6))
    relaxed = correspond(two_clusters, model, ShadowCorrConfig(max_stage_seconds=60))
    plain = correspond(two_clusters, model)
    assert [s.object for s in relaxed.segments] == [s.object for s in plain.segments]
