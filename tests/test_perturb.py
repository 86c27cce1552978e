"""Scene perturbations (shadowcorr.synth.perturb): each does what it says, measured on an
analytic sphere scene, returns a new bundle without touching its input, and keeps the
ground truth exact (every pixel's true object is known after the perturbation)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from shadowcorr.bundle import SceneBundle
from shadowcorr.synth import perturb
from tests.scenes import sphere_scene

# Two touching pairs of spheres and two loose ones: masks touch in every view.
CENTRES = [[0.0, 0.0, 40.0], [84.0, 0.0, 45.0], [-40.0, 110.0, 30.0], [-40.0, 170.0, 30.0],
           [150.0, 150.0, 35.0], [120.0, -140.0, 40.0]]
RADII = [40.0, 45.0, 30.0, 30.0, 35.0, 40.0]


@pytest.fixture(scope="module")
def scene() -> SceneBundle:
    return sphere_scene(CENTRES, RADII, cameras=4, width=320, height_px=180)


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def _object_image(bundle: SceneBundle, view_index: int) -> np.ndarray:
    """True object of every pixel (0 = background, -1 = an id without truth), from the bundle's truth."""
    view = bundle.views[view_index]
    if bundle.ground_truth == "instance":
        return view.mask.astype(np.int64)
    table = view.instance_objects or {}
    ids = np.unique(view.mask)
    lookup = {int(i): (0 if i == 0 else table.get(int(i), -1)) for i in ids}
    return np.vectorize(lookup.__getitem__, otypes=[np.int64])(view.mask)


def _snapshot(bundle: SceneBundle) -> list[tuple[bytes, bytes, bytes]]:
    return [(v.depth.tobytes(), v.mask.tobytes(), v.pose.tobytes()) for v in bundle.views]


def _masks(bundle: SceneBundle) -> list[tuple[int, int]]:
    return [(vi, int(i)) for vi, v in enumerate(bundle.views) for i in np.unique(v.mask) if i != 0]


ALL = [
    lambda b, r: perturb.depth_noise(b, r, 0.01),
    lambda b, r: perturb.depth_holes(b, r, 0.1),
    lambda b, r: perturb.pose_error(b, r, rotation_deg=1.0, translation_cm=5.0),
    lambda b, r: perturb.pose_error(b, r, rotation_deg=1.0, translation_cm=5.0, up_to=True),
    lambda b, r: perturb.morph_masks(b, r, -2),
    lambda b, r: perturb.split_masks(b, r, 0.5),
    lambda b, r: perturb.merge_touching(b, r, 0.5),
    lambda b, r: perturb.drop_masks(b, r, 0.2),
    lambda b, r: perturb.spurious_blobs(b, r, 4, radius_px=(2.0, 5.0), on_rocks=0.5),
]


@pytest.mark.parametrize("apply", ALL)
def test_pure_and_seeded(scene, apply):
    before = _snapshot(scene)
    a, b = apply(scene, _rng(3)), apply(scene, _rng(3))
    assert a is not scene and _snapshot(scene) == before, "the input bundle must not change"
    assert _snapshot(a) == _snapshot(b), "same seed, same perturbation"
    assert a.ground_truth in ("instance", "mapped") and len(a.views) == len(scene.views)


def test_depth_noise_grows_with_depth_squared(scene):
    fraction = 0.01
    noisy = perturb.depth_noise(scene, _rng(), fraction)
    z_ref = perturb.DEPTH_NOISE_REFERENCE_CM
    residuals, near, far = [], [], []
    for clean, out in zip(scene.views, noisy.views):
        valid = clean.depth > 0
        assert np.array_equal(out.depth > 0, valid), "valid stays valid, invalid stays invalid"
        assert np.array_equal(out.mask, clean.mask)
        z = clean.depth[valid].astype(np.float64)
        err = out.depth[valid] - z
        residuals.append(err / (fraction * z * z / z_ref))
        near.append(np.abs(err[z < np.median(z)]).mean())
        far.append(np.abs(err[z >= np.median(z)]).mean())
    r = np.concatenate(residuals)
    assert r.size > 5_000
    assert abs(r.mean()) < 0.03 and abs(r.std() - 1.0) < 0.03, "noise / (fraction z^2 / z_ref) is standard normal"
    assert np.mean(far) > np.mean(near), "farther pixels are noisier"
    assert noisy.ground_truth == "instance"

    # the same relative noise in metres: the reference depth follows the units
    metres = replace(scene, units="m", views=[
        replace(v, depth=(v.depth / 100).astype(np.float32), pose=np.r_[np.c_[v.pose[:3, :3], v.pose[:3, 3] / 100],
                                                                     [[0, 0, 0, 1]]]) for v in scene.views])
    noisy_m = perturb.depth_noise(metres, _rng(), fraction)
    v0, n0 = metres.views[0], noisy_m.views[0]
    z = v0.depth[v0.depth > 0].astype(np.float64)
    assert abs(((n0.depth[v0.depth > 0] - z) / (fraction * z * z / (z_ref / 100))).std() - 1.0) < 0.05


def test_correlated_depth_noise_keeps_sigma_and_makes_neighbours_err_together(scene):
    fraction = 0.01
    z_ref = perturb.DEPTH_NOISE_REFERENCE_CM
    for correlation_px, neighbour_correlation in ((0.0, (-0.05, 0.05)), (4.0, (0.8, 1.0))):
        noisy = perturb.depth_noise(scene, _rng(), fraction, correlation_px=correlation_px)
        residual = []
        pairs = []
        for clean, out in zip(scene.views, noisy.views):
            valid = clean.depth > 0
            assert np.array_equal(out.depth > 0, valid)
            z = clean.depth.astype(np.float64)
            r = np.where(valid, (out.depth - z) / np.maximum(fraction * z * z / z_ref, 1e-12), np.nan)
            residual.append(r[valid])
            both = valid[:, 1:] & valid[:, :-1]
            pairs.append(np.stack([r[:, 1:][both], r[:, :-1][both]]))
        residual, pairs = np.concatenate(residual), np.concatenate(pairs, axis=1)
        assert abs(residual.std() - 1.0) < 0.15, "each pixel keeps its sigma"
        lo, hi = neighbour_correlation
        assert lo < np.corrcoef(pairs)[0, 1] < hi


def test_mixed_pixels_float_only_at_depth_edges_between_near_and_far(scene):
    out = perturb.mixed_pixels(scene, _rng(), 1.0)
    changed_any = 0
    for clean, mixed in zip(scene.views, out.views):
        d = clean.depth.astype(np.float64)
        valid = d > 0
        near = ndimage.minimum_filter(np.where(valid, d, np.inf), size=3)
        far = ndimage.maximum_filter(np.where(valid, d, 0.0), size=3)
        edge = valid & (far - near > 0.05 * d)
        changed = mixed.depth != clean.depth
        assert not (changed & ~edge).any(), "flat surfaces and invalid pixels stay as they were"
        m = mixed.depth[changed].astype(np.float64)
        assert ((m >= near[changed] - 1e-3) & (m <= far[changed] + 1e-3)).all()
        assert np.array_equal(mixed.mask, clean.mask)
        changed_any += int(changed.sum())
    assert changed_any > 100


def test_depth_holes_cut_the_given_share_in_blobs(scene):
    holed = perturb.depth_holes(scene, _rng(1), 0.1, blob_px=12)
    for clean, out in zip(scene.views, holed.views):
        valid = clean.depth > 0
        cut = valid & ~(out.depth > 0)
        assert cut.sum() == round(0.1 * valid.sum()), "exactly the share of valid pixels"
        assert not np.any((out.depth > 0) & ~valid), "no depth invented"
        assert np.array_equal(out.depth[out.depth > 0], clean.depth[out.depth > 0]), "kept depth is untouched"
        _, blobs = ndimage.label(cut)
        assert cut.sum() / blobs >= 15, "holes are blobs, not scattered pixels"
        assert np.array_equal(out.mask, clean.mask)


def _rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a @ b.T) - 1) / 2, -1, 1))))


@pytest.mark.parametrize("deg, cm", [(0.25, 0.0), (2.0, 1.0), (0.0, 5.0)])
def test_pose_error_is_exactly_the_given_size(scene, deg, cm):
    moved = perturb.pose_error(scene, _rng(2), rotation_deg=deg, translation_cm=cm)
    axes = []
    for clean, out in zip(scene.views, moved.views):
        assert _rotation_angle_deg(out.pose[:3, :3], clean.pose[:3, :3]) == pytest.approx(deg, abs=1e-4)
        assert np.linalg.norm(out.pose[:3, 3] - clean.pose[:3, 3]) == pytest.approx(cm, abs=1e-9)
        r = out.pose[:3, :3]
        assert np.allclose(r.T @ r, np.eye(3), atol=1e-12) and np.linalg.det(r) > 0
        assert np.array_equal(out.depth, clean.depth) and np.array_equal(out.mask, clean.mask)
        axes.append(out.pose[:3, 2] - clean.pose[:3, 2])
    if deg > 0:
        assert not np.allclose(axes[0], axes[1]), "each camera has its own random error"


def test_pose_error_up_to_varies_per_camera(scene):
    moved = perturb.pose_error(scene, _rng(2), rotation_deg=2.0, translation_cm=5.0, up_to=True)
    angles = [_rotation_angle_deg(o.pose[:3, :3], c.pose[:3, :3]) for c, o in zip(scene.views, moved.views)]
    shifts = [np.linalg.norm(o.pose[:3, 3] - c.pose[:3, 3]) for c, o in zip(scene.views, moved.views)]
    assert max(angles) <= 2.0 + 1e-9 and max(shifts) <= 5.0 + 1e-9
    assert np.ptp(angles) > 0.1 and np.ptp(shifts) > 0.1, "each camera has its own size of error"


@pytest.mark.parametrize("px", [2, 5, -2, -5])
def test_morph_masks_move_boundaries_by_px(scene, px):
    out = perturb.morph_masks(scene, _rng(), px)
    size = 2 * abs(px) + 1
    for clean, view in zip(scene.views, out.views):
        if px < 0:  # every kept pixel has only its own id within |px| pixels (chebyshev) in the clean mask
            kept = view.mask > 0
            lo = ndimage.minimum_filter(clean.mask, size=size, mode="nearest")
            hi = ndimage.maximum_filter(clean.mask, size=size, mode="nearest")
            assert np.all((lo == hi)[kept]) and np.all(view.mask[kept] == clean.mask[kept])
            assert kept.sum() < (clean.mask > 0).sum()
        else:  # masks only take background, within px pixels of their clean mask
            grown = (view.mask > 0) & (clean.mask == 0)
            assert np.all(view.mask[clean.mask > 0] == clean.mask[clean.mask > 0]) and grown.any()
            dist = ndimage.distance_transform_cdt(clean.mask == 0, metric="chessboard")
            assert dist[grown].max() == px
    assert out.ground_truth == "instance"


def test_split_masks_cut_the_share_by_a_line_and_keep_truth(scene):
    share = 0.5
    out = perturb.split_masks(scene, _rng(4), share)
    assert out.ground_truth == "mapped"
    n_before, n_after = len(_masks(scene)), len(_masks(out))
    assert n_after - n_before == round(share * n_before)
    for vi, (clean, view) in enumerate(zip(scene.views, out.views)):
        assert np.array_equal(_object_image(out, vi), _object_image(scene, vi)), "every pixel keeps its object"
        assert np.array_equal(view.mask > 0, clean.mask > 0)
        top = int(clean.mask.max())
        for new in (i for i in np.unique(view.mask) if i > top):  # a fresh id: one side of one mask
            old = np.unique(clean.mask[view.mask == new])
            assert old.size == 1
            rest, part = (view.mask == old[0]), (view.mask == new)
            c = np.argwhere(clean.mask == old[0]).mean(axis=0)
            assert rest.any() and part.any()
            # the two sides lie on opposite sides of a line through the clean mask's centroid
            assert np.dot(np.argwhere(rest).mean(axis=0) - c, np.argwhere(part).mean(axis=0) - c) < 0


def test_merge_touching_fuses_the_share_of_touching_pairs(scene):
    out = perturb.merge_touching(scene, _rng(5), 1.0)
    assert out.ground_truth == "mapped"
    fused_any = False
    for vi, (clean, view) in enumerate(zip(scene.views, out.views)):
        assert np.array_equal(view.mask > 0, clean.mask > 0)
        truth_before, truth_after = _object_image(scene, vi), _object_image(out, vi)
        top = int(clean.mask.max())
        for new in (i for i in np.unique(view.mask) if i > top):
            fused_any = True
            old, pixels = np.unique(clean.mask[view.mask == new], return_counts=True)
            assert old.size >= 2, "a fused mask joins at least two masks"
            majority = old[np.argmax(pixels)]
            assert np.all(truth_after[view.mask == new] == truth_before[clean.mask == majority][0])
            grown = ndimage.binary_dilation(view.mask == new, structure=np.ones((3, 3)))
            assert set(np.unique(clean.mask[view.mask == new])) <= set(np.unique(clean.mask[grown]))
        untouched = view.mask <= top
        assert np.array_equal(truth_after[untouched], truth_before[untouched])
    assert fused_any
    # with share 1 no two different ids of a view touch any more
    for view in out.views:
        assert perturb._touching_pairs(view.mask, 8).shape[0] == 0


def test_merge_touching_leaves_a_lone_blob_of_a_fused_mask_its_own_id_and_object(scene):
    """A mask with a second blob elsewhere: only the part that touches the other mask is fused."""
    view = scene.views[0]
    mask = np.zeros_like(view.mask)
    mask[20:60, 20:60], mask[20:60, 60:100] = 1, 2  # touching
    mask[120:140, 200:230] = 2  # mask 2's lone blob, touching nothing
    bundle = replace(scene, views=[replace(view, mask=mask)], ground_truth="instance")
    out = perturb.merge_touching(bundle, _rng(0), 1.0)
    fused = out.views[0].mask
    assert np.all(fused[20:60, 20:100] == fused[20, 20]) and fused[20, 20] > 2
    assert np.all(fused[120:140, 200:230] == 2), "the lone blob keeps its id"
    table = out.views[0].instance_objects
    assert table[2] == 2 and table[int(fused[20, 20])] in (1, 2)


def test_merge_share_counts_pairs(scene):
    pairs = sum(perturb._touching_pairs(v.mask, 8).shape[0] for v in scene.views)
    assert pairs >= 4
    out = perturb.merge_touching(scene, _rng(6), 0.5)
    fused = sum(len([i for i in np.unique(o.mask) if i > c.mask.max()]) for c, o in zip(scene.views, out.views))
    assert 1 <= fused <= round(0.5 * pairs)


def test_drop_masks_removes_the_share(scene):
    out = perturb.drop_masks(scene, _rng(7), 0.25)
    before, after = set(_masks(scene)), set(_masks(out))
    assert after < before and len(before - after) == round(0.25 * len(before))
    for vi, (clean, view) in enumerate(zip(scene.views, out.views)):
        gone = [i for (v, i) in before - after if v == vi]
        assert not np.any(np.isin(view.mask, gone))
        keep = ~np.isin(clean.mask, gone)
        assert np.array_equal(view.mask[keep], clean.mask[keep])
    assert out.ground_truth == "instance"


def test_truth_survives_chains_of_id_changes(scene):
    """split then merge: mapped truth in, mapped truth out, pixels keep their objects except
    where a merge decided by majority."""
    out = perturb.split_masks(scene, _rng(9), 0.5)
    for vi in range(len(scene.views)):
        assert np.array_equal(_object_image(out, vi), _object_image(scene, vi))
    merged = perturb.merge_touching(out, _rng(11), 0.5)
    for vi in range(len(scene.views)):
        assert np.all(_object_image(merged, vi) >= 0), "every id of a mapped bundle keeps an object"


def _with_ground(bundle: SceneBundle, depth: float = 900.0) -> SceneBundle:
    """The sphere scene with valid depth on the background too (like synth's terrain)."""
    return replace(bundle, views=[replace(v, depth=np.where(v.depth > 0, v.depth, depth).astype(np.float32))
                                  for v in bundle.views])


@pytest.mark.parametrize("on_rocks", [0.0, 1.0])
def test_spurious_blobs_are_small_new_ids_with_exact_truth(scene, on_rocks):
    base = _with_ground(scene)
    count, (lo, hi) = 5, (2.0, 4.0)
    out = perturb.spurious_blobs(base, _rng(13), count, radius_px=(lo, hi), on_rocks=on_rocks)
    assert out.ground_truth == "mapped"
    objects = []
    for vi, (clean, view) in enumerate(zip(base.views, out.views)):
        top = int(clean.mask.max())
        new = [int(i) for i in np.unique(view.mask) if i > top]
        assert 1 <= len(new) <= count
        truth_before, truth_after = _object_image(base, vi), _object_image(out, vi)
        for i in new:
            blob = view.mask == i
            assert 1 <= blob.sum() <= np.pi * hi * hi + 1, "a blob fits in its ellipse"
            under = np.unique(clean.mask[blob])
            assert under.size == 1, "a blob never crosses a mask boundary"
            if on_rocks:
                assert under[0] > 0 and np.all(truth_after[blob] == under[0]), "a blob on a rock is that rock"
            else:
                assert under[0] == 0 and np.all(base.views[vi].depth[blob] > 0), "on the ground, where depth is"
                objects.append(int(truth_after[blob][0]))
        old = view.mask <= top
        assert np.array_equal(truth_after[old], truth_before[old]), "other pixels keep their object"
        assert np.all(truth_after[view.mask > 0] >= 0), "every id has ground truth"
    if not on_rocks:
        assert min(objects) >= perturb.SPURIOUS_OBJECT_BASE and len(set(objects)) == len(objects), \
            "each background blob is an object of its own, unlike any rock"


def test_spurious_blobs_stack_with_other_id_changes(scene):
    """Blobs on a mapped bundle: new objects above every existing one; rock blobs follow the table."""
    split = perturb.split_masks(_with_ground(scene), _rng(14), 0.5)
    once = perturb.spurious_blobs(split, _rng(15), 3, on_rocks=0.5)
    twice = perturb.spurious_blobs(once, _rng(16), 3, on_rocks=0.0)
    seen = [o for v in once.views for o in v.instance_objects.values()]
    later = {o for v in twice.views for o in v.instance_objects.values()} - set(seen)
    assert later and min(later) > max(seen)
    for vi in range(len(scene.views)):
        keep = np.isin(twice.views[vi].mask, list(once.views[vi].instance_objects))
        assert np.array_equal(_object_image(twice, vi)[keep], _object_image(once, vi)[keep])


def test_spurious_blobs_check_their_arguments(scene):
    for kwargs in (dict(count=-1), dict(count=2, radius_px=(0.0, 3.0)), dict(count=2, radius_px=(4.0, 3.0)),
                   dict(count=2, on_rocks=1.5)):
        with pytest.raises(ValueError):
            perturb.spurious_blobs(scene, _rng(), **kwargs)
    assert _snapshot(perturb.spurious_blobs(scene, _rng(), 0)) == _snapshot(scene)


def test_without_ground_truth_nothing_is_invented(scene):
    blind = replace(scene, ground_truth="none")
    for apply in ALL:
        out = apply(blind, _rng(12))
        assert out.ground_truth == "none" and all(v.instance_objects is None for v in out.views)


def test_point_segment_bundles_are_refused(scene):
    from shadowcorr.bundle import PointSegments

    points = PointSegments(np.zeros((1, 3)), np.array([1]), np.array([0]), np.array([1]))
    with pytest.raises(ValueError, match="depth \\+ mask"):
        perturb.split_masks(replace(scene, point_segments=points), _rng(), 0.5)
