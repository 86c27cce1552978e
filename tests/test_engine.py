"""The correspondence engine, stage by stage, on analytic sphere scenes and the real sample."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from shadowcorr import ShadowCorrConfig, correspond, load_model, prepare
from shadowcorr.bundle import SceneBundle, View
from shadowcorr.errors import DepthRangeError
from shadowcorr.stages import (
    SegmentImage, beta_profile, cast_shadows, cooccurrence, extract_segments, find_blobs, segment_embedding_loss,
    segment_shells, surface_evidence, train_segment_embeddings, voxel_downsample,
)

from shadowcorr.ops import argsort_keys, resolve_threads, segment_chunks, sort_keys, thread_map, unique_keys

from .paths import REFERENCE_CHECKPOINT as REFERENCE
from .paths import SAMPLE_DIR as SAMPLE
from .scenes import sphere_scene



@pytest.fixture(scope="module")
def model():
    return load_model()


def same_partition(a, b) -> bool:
    """Two labelings describe the same grouping (up to renaming)."""
    a, b = np.asarray(a), np.asarray(b)
    pairs = set(zip(a.tolist(), b.tolist()))
    return len(pairs) == len(set(a.tolist())) == len(set(b.tolist()))


def test_beta_profile_peaks_at_mode():
    x = np.linspace(0, 1, 100001)
    phi = beta_profile(x, 1.41, 1.94)
    assert phi.max() == pytest.approx(1.0, abs=1e-6)
    assert x[np.argmax(phi)] == pytest.approx(0.41 / 1.35, abs=1e-4)
    assert phi[0] == 0 and phi[-1] == 0


def test_voxel_downsample_averages_per_cell_and_segment():
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [0.1, 0.1, 0.1], [5.0, 5.0, 5.0]])
    seg = np.array([0, 0, 1, 1])
    out, out_seg = voxel_downsample(pts, seg, 2.0)
    assert out_seg.tolist() == [0, 1, 1]
    np.testing.assert_allclose(out[0], [0.2, 0.2, 0.2])


def test_segments_split_components_and_ignore_small_blobs():
    k = sphere_scene([[0, 0, 0]], [40]).views[0].intrinsics
    depth = np.full((k.height, k.width), 700.0, np.float32)
    mask = np.zeros((k.height, k.width), np.int32)
    mask[10:40, 10:40] = 3  # blob A (900 px)
    mask[100:130, 200:240] = 3  # blob B of the same instance (1200 px)
    mask[150:155, 5:10] = 3  # 25 px: ignored
    mask[60:80, 60:80] = 5
    depth[60:70, 60:80] = 0  # half of instance 5 has no valid depth
    pose = np.eye(4)
    bundle = SceneBundle(units="cm", views=[View("v", pose, k, depth, mask)])
    exact = ShadowCorrConfig(subsample_pixels=False)
    seg = extract_segments(bundle, exact)
    assert seg.instance.tolist() == [3, 3, 5]
    assert seg.component.tolist() == [0, 1, 0]
    assert seg.num_pixels.tolist() == [1200, 900, 400]
    assert seg.lengths.tolist() == [1200, 900, 200]
    merged = extract_segments(bundle, exact.with_options(split_components=False))
    assert merged.instance.tolist() == [3, 5] and merged.lengths[0] == 1200 + 900 + 25


@pytest.mark.parametrize("id_scale", [1, 1 << 24])  # small ids, and sparse large ones (renumbered)
def test_blob_image_matches_labelling_each_instance_over_the_whole_frame(id_scale):
    rng = np.random.default_rng(5)
    mask = np.zeros((60, 90), np.int64)
    for value in range(1, 9):  # random rectangles, some on the frame's edges, overlapping
        r, c = rng.integers(0, 55), rng.integers(0, 85)
        mask[r : r + rng.integers(3, 20), c : c + rng.integers(3, 25)] = value
    mask[:, 0] = 9  # a column on the left edge, a row on the bottom edge
    mask[-1, 30:] = 9
    mask = (mask * id_scale).astype(np.int64)
    blobs = find_blobs(mask, True, 5)
    # Reference: every instance labelled over the whole frame, blobs largest first.
    expected = np.full(mask.shape, -1)
    index, lengths = 0, []
    for value in np.unique(mask[mask > 0]):
        labels, n = ndimage.label(mask == value, structure=np.ones((3, 3), bool))
        counts = np.bincount(labels.ravel())[1:]
        for lab in np.argsort(-counts, kind="stable"):
            if counts[lab] >= 5:
                expected[labels == lab + 1] = index
                index, lengths = index + 1, lengths + [counts[lab]]
    np.testing.assert_array_equal(blobs.labels, expected)
    assert blobs.labels.dtype == np.int16 and blobs.lengths.tolist() == lengths
    r0, r1, c0, c1 = blobs.bounds
    inside = np.zeros(mask.shape, bool)
    inside[r0:r1, c0:c1] = True
    assert (blobs.labels[~inside] == -1).all() and (r0, r1, c0, c1) == (0, 60, 0, 90)
    empty = find_blobs(np.zeros((4, 5), np.int32))
    assert empty.lengths.size == 0 and (empty.labels == -1).all() and empty.labels.shape == (4, 5)


@pytest.mark.parametrize("seed", range(4))
def test_blobs_of_speckled_masks_match_labelling_each_instance(seed):
    """Speckle: many tiny blobs, blobs touching only at a corner, values next to each other and
    equal-sized blobs of one value (ordered by scan order)."""
    rng = np.random.default_rng(seed)
    mask = rng.integers(0, 5, size=(rng.integers(20, 50), rng.integers(20, 50))).astype(np.int32)
    mask[rng.random(mask.shape) < 0.3] = 0
    mask[:4, :4] = [[7, 0, 7, 0], [0, 7, 0, 7], [7, 0, 7, 0], [0, 7, 0, 7]]  # one blob through its corners
    for split, min_pixels in ((True, 1), (True, 3), (False, 4)):
        blobs = find_blobs(mask, split, min_pixels)
        expected = np.full(mask.shape, -1)
        instances, components, index = [], [], 0
        for value in np.unique(mask[mask > 0]):
            labels, n = ndimage.label(mask == value, structure=np.ones((3, 3), bool)) if split else (
                (mask == value).astype(int), 1)
            counts = np.bincount(labels.ravel(), minlength=n + 1)[1:]
            kept = [lab for lab in np.argsort(-counts, kind="stable") if counts[lab] >= min_pixels]
            for component, lab in enumerate(kept):
                expected[labels == lab + 1] = index
                index += 1
                instances.append(int(value))
                components.append(component)
        np.testing.assert_array_equal(blobs.labels, expected)
        assert blobs.instance.tolist() == instances and blobs.component.tolist() == components
        assert blobs.lengths.tolist() == [int((expected == b).sum()) for b in range(index)]
    assert (find_blobs(mask, True, 1).labels[:4, :4] >= 0).sum() == 8  # the corner-touching blob is one
    assert len(set(find_blobs(mask, True, 1).labels[:4, :4][mask[:4, :4] == 7].tolist())) == 1


def test_blobs_of_a_checkerboard_mask_take_memory_linear_in_runs():
    """A checkerboard of one id is all one-pixel runs joined through their corners: one blob.
    Comparing each run with every run of the row above would pair 300 x 300 runs per row
    (about 1 GB of pair indices here); touching runs are a contiguous stretch, so the pairs
    stay about two per run."""
    import tracemalloc

    h, w = 300, 600
    mask = ((np.arange(h)[:, None] + np.arange(w)[None, :]) % 2).astype(np.uint8) * 5
    tracemalloc.start()
    try:
        blobs = find_blobs(mask, True, 1)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert blobs.lengths.tolist() == [h * w // 2] and blobs.instance.tolist() == [5]
    np.testing.assert_array_equal(blobs.labels == 0, mask > 0)
    runs = h * w // 2
    assert peak < 400 * runs, f"{peak / 1e6:.0f} MB for {runs} runs"


def test_segment_image_shifted_moves_indices_to_the_scene_numbering_and_widens_when_needed():
    mask = np.zeros((6, 8), np.int32)
    mask[1:3, 1:3], mask[4:6, 5:8] = 3, 4
    image = SegmentImage.from_blobs(find_blobs(mask, True, 1))
    rows, cols = np.array([0, 1, 4, 5]), np.array([0, 1, 6, 7])
    assert image.at(rows, cols).tolist() == [-1, 0, 1, 1]
    assert image.shifted(10).at(rows, cols).tolist() == [-1, 10, 11, 11]
    assert image.at(rows, cols).tolist() == [-1, 0, 1, 1]  # the original is left as it was
    far = image.shifted(32_766)  # beyond int16
    assert far.window.dtype == np.int32 and far.at(rows, cols).tolist() == [-1, 32_766, 32_767, 32_767]


def test_pixel_subsampling_keeps_the_downsample_cells_of_nearly_every_point():
    bundle = sphere_scene([[0, 0, 0]], [50], cameras=2, width=1920, height_px=1080)  # 0.5 cm per pixel
    exact = ShadowCorrConfig(subsample_pixels=False)
    full, strided = extract_segments(bundle, exact), extract_segments(bundle, ShadowCorrConfig())
    assert strided.points.shape[0] < full.points.shape[0] / 3  # stride 2 at this range
    cell = lambda p: [tuple(c) for c in np.floor(p / exact.downsample_size).astype(int).tolist()]  # noqa: E731
    kept = set(cell(strided.points))
    # Only cells the surface grazes at the silhouette (a few points each) can go empty.
    assert np.mean([c in kept for c in cell(full.points)]) > 0.9


def test_back_projection_lies_on_the_sphere():
    bundle = sphere_scene([[0, 0, 0]], [50])
    seg = extract_segments(bundle, ShadowCorrConfig())
    r = np.linalg.norm(seg.points, axis=1)
    assert seg.num_segments == 4
    assert np.abs(r - 50).max() < 0.05


def test_shadows_fill_the_interior():
    bundle = sphere_scene([[0, 0, 0]], [60])
    cfg = ShadowCorrConfig()
    seg = extract_segments(bundle, cfg)
    shells = segment_shells(seg, cfg)
    shadows = cast_shadows(seg, shells, cfg)
    centres = shadows.cell * cfg.voxel_size
    # Voxels reach well behind the visible shell, into the sphere's interior.
    assert np.linalg.norm(centres, axis=1).min() < 30
    assert np.all(shadows.confidence > cfg.min_confidence)


def test_outlier_removal_is_the_papers_step_and_fused_leaves_it_out():
    methods = ("shadowcorr", "meanshift", "fused")
    assert [ShadowCorrConfig(method=m).outlier_removal for m in methods] == [True, True, False]
    assert ShadowCorrConfig(method="fused", remove_outliers=True).outlier_removal
    assert not ShadowCorrConfig(method="shadowcorr", remove_outliers=False).outlier_removal
    # A far stray point among a sphere's shell points: kept without the filter, gone with it.
    bundle = sphere_scene(FIELD_CENTRES[:2], FIELD_RADII[:2])
    cfg = ShadowCorrConfig(remove_outliers=False)
    seg = extract_segments(bundle, cfg)
    first = slice(0, int(seg.lengths[0]))
    stray = seg.points[first].mean(axis=0) + 500.0
    seg.points[int(seg.lengths[0]) - 1] = stray
    kept = segment_shells(seg, cfg)
    filtered = segment_shells(seg, cfg.with_options(remove_outliers=True))
    assert np.any(np.all(kept.points == stray, axis=1))
    assert not np.any(np.all(filtered.points == stray, axis=1))
    assert filtered.points.shape[0] < kept.points.shape[0]


@pytest.mark.parametrize("high", [1, 7, 300, 40_000, 1 << 40])  # counted in a table up to 4 keys a row, else sorted
def test_unique_keys_equal_numpys_unique_by_counting_and_by_sorting(high):
    keys = np.random.default_rng(high).integers(0, high, size=5_000).astype(np.int64)
    for option in ({}, {"return_counts": True}, {"return_inverse": True}):
        ours, reference = unique_keys(keys, **option), np.unique(keys, **option)
        for a, b in zip(*((x,) if isinstance(x, np.ndarray) else x for x in (ours, reference))):
            np.testing.assert_array_equal(a, b)
            assert a.dtype == np.int64
    with pytest.raises(ValueError, match="not both"):
        unique_keys(keys, return_inverse=True, return_counts=True)


@pytest.mark.parametrize("case", ["random narrow", "random wide", "negative", "runs", "too wide", "many",
                                  "ties", "empty", "one"])
def test_sort_keys_and_argsort_keys_equal_numpys_stable_sort_on_every_path(case, monkeypatch):
    import shadowcorr.ops._sort_keys as sort_mod

    rng = np.random.default_rng(len(case))
    keys = {
        "random narrow": rng.integers(0, 1 << 20, 20_000),  # 16-bit digits: two passes
        "random wide": rng.integers(0, 1 << 47, 20_000),  # three passes
        "negative": rng.integers(-(1 << 30), 1 << 30, 20_000),
        "runs": np.concatenate([np.sort(rng.integers(0, 1 << 40, 5_000)) for _ in range(4)]),  # merged by timsort
        "too wide": rng.integers(-(1 << 62), 1 << 62, 20_000),  # the default sort
        "many": rng.integers(0, 1 << 30, 20_000),  # above the limit set below: the default sort
        "ties": rng.integers(0, 50, 20_000) << 30,  # stable order of equal keys
        "empty": np.zeros(0, np.int64),
        "one": np.array([7]),
    }[case].astype(np.int64)
    if case == "many":
        monkeypatch.setattr(sort_mod, "_RADIX_MAX_KEYS", 10_000)
    expected_passes = {"random narrow": 2, "random wide": 3, "negative": 2, "runs": 0, "too wide": None,
                       "many": None, "ties": 3, "empty": None, "one": None}[case]
    assert sort_mod._radix_passes(keys) == expected_passes
    np.testing.assert_array_equal(sort_keys(keys), np.sort(keys))
    np.testing.assert_array_equal(argsort_keys(keys), np.argsort(keys, kind="stable"))


def test_shadows_and_outliers_in_small_chunks_equal_one_pass(monkeypatch):
    import shadowcorr.stages._04_shells as shells_mod
    import shadowcorr.stages._05_shadows as shadows_mod

    bundle = sphere_scene(FIELD_CENTRES, FIELD_RADII)
    cfg = ShadowCorrConfig(remove_outliers=True)
    seg = extract_segments(bundle, cfg)
    shells = segment_shells(seg, cfg)
    whole = cast_shadows(seg, shells, cfg)
    # Chunks of about one segment's worth of rows: many chunks, whole segments each.
    monkeypatch.setattr(shadows_mod, "_CHUNK_LAYER_POINTS", 500)
    monkeypatch.setattr(shells_mod, "_CHUNK_POINTS", 100)
    assert len(segment_chunks(shells.segment, 500, weight=np.full(shells.segment.size, 3))) > 5
    chunked_shells = segment_shells(seg, cfg)
    np.testing.assert_array_equal(chunked_shells.points, shells.points)
    chunked = cast_shadows(seg, chunked_shells, cfg)
    for name in ("segment", "cell", "confidence"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name))


@pytest.mark.parametrize("num_threads", [2, 0])
def test_threads_change_nothing_but_the_time(monkeypatch, num_threads):
    import shadowcorr.stages._04_shells as shells_mod

    bundle = sphere_scene(FIELD_CENTRES, FIELD_RADII, cameras=3)
    one, many = ShadowCorrConfig(remove_outliers=True), ShadowCorrConfig(remove_outliers=True, num_threads=num_threads)
    seg1, seg2 = extract_segments(bundle, one), extract_segments(bundle, many)
    np.testing.assert_array_equal(seg2.points, seg1.points)
    np.testing.assert_array_equal(seg2.lengths, seg1.lengths)
    for a, b in zip(seg1.pixel_segment, seg2.pixel_segment):  # later views' indices shifted alike
        np.testing.assert_array_equal(b.window, a.window)
        assert (b.top, b.left) == (a.top, a.left)
    evidence1, evidence2 = surface_evidence(bundle, seg1, one), surface_evidence(bundle, seg2, many)
    for name in ("visible", "on_mask", "hit_source", "hit_target", "hit_count"):
        np.testing.assert_array_equal(getattr(evidence2, name), getattr(evidence1, name))
    monkeypatch.setattr(shells_mod, "_CHUNK_RAW_POINTS", 3000)  # many chunks: they run on the threads
    shells1, shells2 = segment_shells(seg1, one), segment_shells(seg2, many)
    np.testing.assert_array_equal(shells2.points, shells1.points)
    np.testing.assert_array_equal(shells2.axis_lengths, shells1.axis_lengths)
    shadows1, shadows2 = cast_shadows(seg1, shells1, one), cast_shadows(seg2, shells2, many)
    for name in ("segment", "cell", "confidence"):
        np.testing.assert_array_equal(getattr(shadows2, name), getattr(shadows1, name))


def test_thread_map_keeps_the_order_and_raises_what_the_function_raises():
    import threading

    seen = set()

    def work(i: int) -> int:
        seen.add(threading.get_ident())
        return i * i

    assert thread_map(work, range(40), 3) == [i * i for i in range(40)]
    assert thread_map(work, [], 0) == [] and resolve_threads(0) >= 1 and resolve_threads(3) == 3
    seen.clear()
    assert thread_map(work, range(5), 1) == [0, 1, 4, 9, 16] and seen == {threading.get_ident()}  # no pool

    def fail(i: int) -> int:
        if i == 3:
            raise ValueError("item 3")
        return i

    with pytest.raises(ValueError, match="item 3"):
        thread_map(fail, range(6), 2)


def test_segment_chunks_hold_whole_segments_of_about_the_asked_weight():
    segment = np.repeat(np.arange(6), [3, 1, 4, 2, 5, 1])
    weight = np.arange(segment.size) % 3 + 1
    chunks = segment_chunks(segment, 6, weight=weight)
    assert chunks[0][0] == 0 and chunks[-1][1] == segment.size
    assert all(a[1] == b[0] for a, b in zip(chunks, chunks[1:]))
    for lo, hi in chunks:  # never splits a segment
        assert (lo == 0 or segment[lo] != segment[lo - 1]) and (hi == segment.size or segment[hi] != segment[hi - 1])
    assert len(chunks) >= 3 and segment_chunks(segment[:0], 6) == []
    assert len(segment_chunks(segment, 100, min_chunks=4)) >= 4  # smaller chunks for a pool of 4
    assert len(segment_chunks(segment, 100, min_chunks=100)) == 6  # never more than the segments


# A small "rock field" of spheres in the reference data's size range; spheres 1 and 2 touch.
FIELD_CENTRES = [[-50, 0, 0], [50, 0, 0], [-250, 150, 0], [200, -200, 10], [0, 250, 0], [250, 150, 0],
                 [-200, -200, 0], [-40, -150, 0]]
FIELD_RADII = [50, 50, 40, 60, 45, 35, 55, 30]


def test_spheres_seen_from_opposite_sides_become_one_object_each(model):
    # Two cameras 180 degrees apart: their visible shells of one sphere share no surface.
    bundle = sphere_scene(FIELD_CENTRES, FIELD_RADII, cameras=2, width=480, height_px=270)
    result = correspond(bundle, model)
    truth = [s.instance for s in result.segments]
    assert len(result.labels) == 16
    assert same_partition(result.labels, truth), (result.labels, truth)
    assert result.metrics["average_purity"] == 100.0


def test_touching_spheres_stay_apart(model):
    bundle = sphere_scene(FIELD_CENTRES, FIELD_RADII, cameras=4, width=480, height_px=270)
    result = correspond(bundle, model)
    labels = np.array(result.labels)
    truth = np.array([s.instance for s in result.segments])
    assert same_partition(labels, truth), (labels.tolist(), truth.tolist())
    touching = {s.object for s in result.segments if s.instance in (1, 2)}
    assert len(touching) == 2


def test_result_is_independent_of_units_and_view_order(model):
    centres, radii = FIELD_CENTRES, FIELD_RADII
    cm = sphere_scene(centres, radii, cameras=3)
    base = correspond(cm, model)
    metres = sphere_scene(np.array(centres) / 100, np.array(radii) / 100, cameras=3, radius=7.5, height=3.0, units="m")
    in_m = correspond(metres, model)
    assert same_partition(base.labels, in_m.labels)
    assert in_m.units == "m"
    assert in_m.objects[0].centroid is not None and max(abs(c) for c in in_m.objects[0].centroid) < 3
    views = list(reversed(cm.views))
    reordered = correspond(SceneBundle(units="cm", views=views, name="r", ground_truth="instance"), model)
    key = lambda r: {(s.view, s.instance): s.object for s in r.segments}  # noqa: E731
    a, b = key(base), key(reordered)
    assert same_partition([a[k] for k in sorted(a)], [b[k] for k in sorted(a)])


def test_narrow_arrays_as_loaded_give_the_result_of_float32_depth_and_int32_masks(model):
    """Half-float EXR depth loads as float16 and PNG masks as uint8/uint16 (see read_depth_exr,
    read_mask_png); every stage reads them as the values they hold, so only the dtypes differ."""
    bundle = sphere_scene(FIELD_CENTRES, FIELD_RADII, cameras=3, width=480, height_px=270)
    narrow = [replace(v, depth=v.depth.astype(np.float16), mask=v.mask.astype(np.uint8)) for v in bundle.views]
    wide = [replace(v, depth=n.depth.astype(np.float32), mask=n.mask.astype(np.int32))
            for v, n in zip(bundle.views, narrow)]
    a, b = (correspond(replace(bundle, views=views), model, ShadowCorrConfig(refine_poses=True))
            for views in (wide, narrow))
    assert a.labels == b.labels and len(set(a.labels)) > 1
    assert [s.model_dump() for s in a.segments] == [s.model_dump() for s in b.segments]
    assert a.poses == b.poses


def _same_scene(a, b, path: str = "scene") -> None:
    """Every field of two prepared scenes equal (nested dataclasses, arrays, lists, dicts), the
    ground truth and the timings left out."""
    import dataclasses

    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            if f.name not in ("segment_truth", "timings_ms"):
                _same_scene(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), path
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _same_scene(x, y, f"{path}[{i}]")
    else:
        assert a == b, path


@pytest.mark.parametrize("method", ["fused", "shadowcorr"])
def test_ground_truth_never_reaches_the_features(model, method):
    # The same pixels three times: the truth is the mask id ('instance'), a table that
    # contradicts the mask ids across views ('mapped': the two spheres swapped in every other
    # view), or absent ('none').  Everything inference computes must be the same.
    bundle = sphere_scene([[-100, 0, 0], [100, 0, 0]], [50, 50])
    swapped = [replace(v, instance_objects={int(i): int(3 - i if k % 2 else i) for i in np.unique(v.mask) if i})
               for k, v in enumerate(bundle.views)]
    mapped = SceneBundle(units="cm", views=swapped, ground_truth="mapped", name=bundle.name)
    truthless = SceneBundle(units="cm", views=bundle.views, ground_truth="none", name=bundle.name)
    config = ShadowCorrConfig(method=method)
    scenes = [prepare(b, config) for b in (bundle, mapped, truthless)]
    assert not np.array_equal(scenes[0].segment_truth, scenes[1].segment_truth)  # the truth really differs
    assert scenes[2].segment_truth is None
    for other in scenes[1:]:
        _same_scene(scenes[0], other)
    results = [correspond(b, model, config, metrics=False) for b in (bundle, mapped, truthless)]
    for r in results[1:]:
        assert [s.model_dump() for s in r.segments] == [s.model_dump() for s in results[0].segments]
        assert [o.model_dump() for o in r.objects] == [o.model_dump() for o in results[0].objects]


def test_segment_embedding_training_lowers_its_loss():
    cooc = np.array([[0, 9, 0, 0], [9, 0, 1, 0], [0, 1, 0, 7], [0, 0, 7, 0]], dtype=float)
    centroids = np.arange(12, dtype=float).reshape(4, 3)
    cfg = ShadowCorrConfig()
    z0 = train_segment_embeddings(cooc, centroids, cfg.with_options(segment_embedding_steps=0))
    z = train_segment_embeddings(cooc, centroids, cfg)
    assert segment_embedding_loss(z, cooc, cfg) < segment_embedding_loss(z0, cooc, cfg) - 0.1
    # Listing order does not matter: permuting the segments permutes the vectors.
    perm = np.array([2, 0, 3, 1])
    zp = train_segment_embeddings(cooc[np.ix_(perm, perm)], centroids[perm], cfg)
    np.testing.assert_allclose(zp, z[perm], atol=1e-5)


def test_cooccurrence_counts_shared_voxels():
    voxel = np.array([0, 0, 1, 1, 1, 2])
    segment = np.array([0, 1, 0, 1, 2, 2])
    o = cooccurrence(voxel, segment, 3, 3)
    assert o.toarray().tolist() == [[0, 2, 1], [2, 0, 1], [1, 1, 0]]


def test_every_segment_is_labelled_even_without_voxels(model):
    # A harsh consensus filter leaves many segments without a single kept voxel.
    bundle = sphere_scene(FIELD_CENTRES, FIELD_RADII, cameras=3)
    config = ShadowCorrConfig(method="shadowcorr", gamma_percentile=97)
    scene = prepare(bundle, config)
    orphans = set(range(scene.num_segments)) - set(scene.member_segment.tolist())
    assert orphans, "the test needs segments without kept voxels"
    result = correspond(bundle, model, config)
    assert len(result.segments) == scene.num_segments
    assert all(s.object >= 0 for s in result.segments)
    assert {s.segment for s in result.segments if s.assignment != "vote"} == orphans
    assert result.metrics["coverage"] == 100.0
    assert any(w.startswith("segment ") and "no surviving voxel" in w for w in result.warnings)


def test_baseline_method_runs_without_a_model():
    bundle = sphere_scene([[-150, 0, 0], [150, 0, 0]], [50, 50])
    result = correspond(bundle, None, ShadowCorrConfig(method="meanshift"))
    assert result.method == "meanshift" and result.model is None
    assert len(result.segments) == 8
    # It finds the two spheres (in the sphere scenes a mask id is its sphere) ...
    assert same_partition(result.labels, [s.instance for s in result.segments]) and len(result.objects) == 2
    # ... and a model, when one is given, changes nothing.
    with_model = correspond(bundle, load_model(), ShadowCorrConfig(method="meanshift"))
    assert [s.model_dump() for s in with_model.segments] == [s.model_dump() for s in result.segments]


def test_real_sample_scene_with_reference_checkpoint():
    from shadowcorr.convert import load_ue_scene

    bundle = load_ue_scene(SAMPLE, 2001, [0, 2, 4, 6])
    result = correspond(bundle, load_model(REFERENCE), ShadowCorrConfig(method="shadowcorr"))
    m = result.metrics
    assert len(result.segments) == 77 and m["num_rocks"] == 20
    assert m["coverage"] == 100.0
    assert sum(s.assignment == "unfiltered_voxels" for s in result.segments) >= 1
    assert m["average_purity"] >= 97.5
    assert m["voxel_ari"] >= 0.94


def test_scene_without_segments_is_a_clear_error():
    bundle = sphere_scene([[0, 0, 0]], [40], cameras=2)
    for v in bundle.views:
        v.mask[:] = 0
    with pytest.raises(ValueError, match="no segments"):
        prepare(bundle)


def test_segments_without_valid_depth_still_get_labels(model):
    bundle = sphere_scene([[0, 0, 0]], [40], cameras=3)
    bundle.views[0].depth[:] = 0  # one of three segments has no valid depth: labelled, and flagged first
    result = correspond(bundle, model)
    assert result.segments[0].assignment == "own_object" and result.segments[0].num_points == 0
    assert "1 of 3 segments have no valid depth point" in result.warnings[0], result.warnings
    assert "no valid 3D point" in result.warnings[-1]
    # with every segment empty there is nothing to match: refused, naming units and max_depth
    for v in bundle.views:
        v.depth[:] = 0
    with pytest.raises(DepthRangeError, match="units.*max_depth"):
        correspond(bundle, model)


def test_confidence_is_the_beta_profile_of_the_distance_to_the_averaged_shell():
    from shadowcorr.stages._05_shadows import _confidence

    assert [ShadowCorrConfig(method=m).distance_cell for m in ("shadowcorr", "meanshift", "fused")] == [0.0, 0.0, 4.0]
    assert ShadowCorrConfig(method="fused", surface_distance_cell=0).distance_cell == 0.0
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 40, (300, 3))
    seg = np.repeat([0, 1], 150)
    pts[150:] += 500.0  # segment 1 far from segment 0: distances stay within a segment
    vox_seg = np.repeat([0, 1], 20)
    vox_cell = np.floor(np.concatenate([rng.uniform(-2, 7, (20, 3)), rng.uniform(60, 70, (20, 3))])).astype(np.int64)
    got = {}
    for cell in (0.0, 4.0):
        config = ShadowCorrConfig(surface_distance_cell=cell)
        surface, surface_seg = voxel_downsample(pts, seg, cell) if cell else (pts, seg)
        assert surface.shape[0] < pts.shape[0] or not cell
        centres = vox_cell * config.voxel_size
        dist = np.array([np.linalg.norm(surface[surface_seg == s] - c, axis=1).min() for s, c in zip(vox_seg, centres)])
        farthest = np.array([dist[vox_seg == s].max() for s in vox_seg])
        want = beta_profile(dist / (config.distance_margin * farthest), config.beta_alpha, config.beta_beta)
        got[cell] = _confidence(pts, seg, vox_seg, vox_cell, config.voxel_size, 1e4, 2, config)
        np.testing.assert_allclose(got[cell], want, rtol=1e-12)
    assert not np.allclose(got[0.0], got[4.0])  # the averaging moved the distances


def test_the_engine_benchmark_compares_this_checkout_with_a_revision_in_one_process():
    """``bench_engine.py --against REV`` imports the revision's library beside this one and times both on the
    sample scene, one after the other; an unknown revision is a clear error."""
    import shutil
    import subprocess
    import sys

    from .harness import REPO_ROOT

    if shutil.which("git") is None or not (REPO_ROOT / ".git").exists():
        pytest.skip("needs git and a git checkout")
    if not SAMPLE.exists():
        pytest.skip("the sample scene is not here")
    script = str(REPO_ROOT / "benchmarks" / "bench_engine.py")
    run = subprocess.run([sys.executable, script, "--against", "HEAD", "--repeats", "1"], cwd=REPO_ROOT,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    header, rows = run.stdout.splitlines()[1], run.stdout.splitlines()[2:]
    assert header.split() == ["stage", "this", "checkout", "HEAD", "difference"]
    total = next(row for row in rows if row.startswith("in memory -> labels")).split()
    assert float(total[4]) > 0 and float(total[5]) > 0  # both versions labelled the scene
    network = next(row for row in rows if row.startswith("network")).split()
    assert float(network[1]) > 0 and float(network[2]) > 0
    bad = subprocess.run([sys.executable, script, "--against", "no-such-revision"], cwd=REPO_ROOT,
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "no-such-revision" in bad.stderr
