"""Stage 2's depth cut: one mask drawn over two rocks, one in front of the other, becomes two segments."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest

from shadowcorr import ShadowCorrConfig, correspond, load_model
from shadowcorr.bundle import Intrinsics, SceneBundle, View
from shadowcorr.ops import relative_depth_noise
from shadowcorr.sitemap import SiteMap
from shadowcorr.sitemap._store import FORMAT_VERSION
from shadowcorr.sitemap._summaries import stored_views
from shadowcorr.stages import cut_at_depth_steps, extract_segments, find_blobs, join_lone_pieces, view_blobs

from .scenes import sphere_scene


def two_planes(step: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
    """A 100 x 200 mask (value 3) whose right half lies ``step`` behind its left half at 500, and a
    small second mask (value 5)."""
    mask = np.zeros((200, 300), np.int32)
    mask[50:150, 50:250] = 3
    mask[10:30, 10:30] = 5
    depth = np.full(mask.shape, 500.0, np.float32)
    depth[:, 150:] += step
    return mask, depth


def test_a_step_across_a_blob_cuts_it_into_pieces_of_its_mask():
    mask, depth = two_planes()
    blobs = find_blobs(mask, True, 50)
    cut = cut_at_depth_steps(blobs, depth, 0.0, 0.02)
    assert cut.instance.tolist() == [3, 3, 5] and cut.component.tolist() == [0, 1, 0]
    assert cut.lengths.tolist() == [10000, 10000, 400]
    assert cut.cut.tolist() == [0, 0, -1]  # both pieces name the blob they came from
    near, far = cut.labels[50:150, 50:150], cut.labels[50:150, 150:250]
    assert len(np.unique(near)) == 1 and len(np.unique(far)) == 1 and near[0, 0] != far[0, 0]
    assert ((cut.labels >= 0) == (blobs.labels >= 0)).all()  # every pixel stays in a segment, none is added


@pytest.mark.parametrize("case", ["small step", "sliver", "crack"])
def test_what_does_not_cut(case):
    mask, depth = two_planes()
    blobs = find_blobs(mask, True, 50)
    if case == "small step":  # 1 % of the depth: one surface's slope, not two rocks
        depth = np.where(depth > 500, 505.0, 500.0).astype(np.float32)
    elif case == "sliver":  # the far part holds 5 % of the blob's pixels
        depth = np.full(mask.shape, 500.0, np.float32)
        depth[:, 240:] = 560.0
    else:  # a step along half the blob only: the rest of the blob holds its two sides together
        depth = np.full(mask.shape, 500.0, np.float32)
        depth[50:100, 150:] = 560.0
        depth[100:150, 150:] = np.linspace(560.0, 500.0, 50)[:, None]  # the far side comes forward to meet the near
    cut = cut_at_depth_steps(blobs, depth, 0.0, 0.02)
    assert cut.cut is None and cut.lengths.tolist() == blobs.lengths.tolist()


def test_the_step_must_stand_out_of_the_depth_noise():
    rng = np.random.default_rng(3)
    mask, depth = two_planes(step=60.0)  # 12 %
    noisy = depth * (1 + 0.01 * rng.standard_normal(depth.shape)).astype(np.float32)
    blobs = find_blobs(mask, True, 50)
    noise = relative_depth_noise(noisy)
    assert cut_at_depth_steps(blobs, noisy, noise, 0.02).lengths.tolist() == [10000, 10000, 400]
    # 3 % under 2 % noise: within 4 standard deviations of a difference, so not a step
    mask, depth = two_planes(step=15.0)
    noisier = depth * (1 + 0.02 * rng.standard_normal(depth.shape)).astype(np.float32)
    assert cut_at_depth_steps(blobs, noisier, relative_depth_noise(noisier), 0.02).cut is None


def test_only_fused_cuts_unless_told():
    mask, depth = two_planes()
    k = Intrinsics(fx=250.0, fy=250.0, cx=150.0, cy=100.0, width=300, height=200)
    view = View("v", np.eye(4), k, depth, mask)
    assert view_blobs(view, ShadowCorrConfig(depth_cut_step=None)).lengths.size == 3  # fused's measured step
    assert view_blobs(view, ShadowCorrConfig(method="shadowcorr", depth_cut_step=None)).lengths.size == 2
    assert view_blobs(view, ShadowCorrConfig(depth_cut_step=0)).lengths.size == 2


def test_a_lone_piece_goes_back_to_its_blob():
    labels = np.array([0, 1, 2, 3, 3, 4, 1])
    view = np.array([0, 0, 0, 0, 1, 1, 1])
    cut = np.array([7, 7, 7, -1, -1, 7, -1])  # pieces of blob 7 in view 0 (0, 1, 2) and in view 1 (5)
    size = np.array([10, 50, 30, 5, 5, 9, 5])
    out = join_lone_pieces(labels, view, cut, size)
    # 0 and 2 stand alone: they join piece 1's group, the largest piece that is grouped.  5 stands alone,
    # but its blob (view 1's blob 7) has no grouped piece; 3 is no piece.
    assert out.tolist() == [1, 1, 1, 3, 3, 4, 1]


def _two_spheres_under_one_mask() -> SceneBundle:
    """Two spheres one behind the other from the first camera, which draws one mask (9) over both."""
    scene = sphere_scene([[0, 0, 40], [-150, -150, 40]], [40, 40], cameras=4, width=480, height_px=270,
                         start_deg=45.0)
    first = scene.views[0]
    both = np.isin(first.mask, [1, 2])
    merged = np.where(both, 9, first.mask).astype(first.mask.dtype)
    views = [View(first.name, first.pose, first.intrinsics, first.depth, merged), *scene.views[1:]]
    return SceneBundle(units=scene.units, views=views, name="merged", ground_truth="none")


def test_a_mask_over_two_spheres_is_labelled_as_the_two_spheres():
    bundle = _two_spheres_under_one_mask()
    first = bundle.views[0]
    config = ShadowCorrConfig(depth_cut_step=None)  # fused's measured step
    segments = extract_segments(bundle, config)
    in_first = segments.view == 0
    assert in_first.sum() == 2 and (segments.instance[in_first] == 9).all()  # one mask, two pieces
    assert segments.cut is not None and (segments.cut[in_first] == 0).all()
    result = correspond(bundle, load_model(), config=config)
    by_mask = {(s.view, s.instance, s.component): s.object for s in result.segments}
    objects = {}
    for s in result.segments:
        if s.view != first.name:
            objects.setdefault(s.instance, set()).add(s.object)
    assert all(len(v) == 1 for v in objects.values()) and len(objects) == 2
    pieces = {by_mask[(first.name, 9, 0)], by_mask[(first.name, 9, 1)]}
    assert pieces == {next(iter(v)) for v in objects.values()}  # each piece with its own sphere


def test_a_site_map_keeps_which_blob_its_pieces_were_cut_from(tmp_path):
    bundle = _two_spheres_under_one_mask()
    config = ShadowCorrConfig(refine_poses=False)
    cut = extract_segments(bundle, config).cut
    path = tmp_path / "site.map"
    with SiteMap(path, config, model=load_model()) as site:
        site.add(bundle)
        ids = [r[0] for r in site._store.db.execute("SELECT view FROM views ORDER BY view")]
        stored = stored_views(site._store.view_rows(ids), site._store.segment_rows(ids))
    assert stored.segments.cut is not None and np.array_equal(stored.segments.cut, cut)
    assert np.array_equal(stored.subset([0]).segments.cut, cut[:np.count_nonzero(stored.segments.view == 0)])
    assert stored.subset([1, 2, 3]).segments.cut is None  # no piece there
    # A format-3 file (no cut column) opens upgraded: its segments were cut from no blob it remembers.
    db = sqlite3.connect(path)
    db.execute("ALTER TABLE segments DROP COLUMN cut")
    db.execute("UPDATE meta SET value = '3' WHERE key = 'format'")
    db.commit()
    db.close()
    with SiteMap(path, config, model=load_model()) as site:
        assert site._store.meta("format") == FORMAT_VERSION
        assert {r["cut"] for r in site._store.segment_rows(ids, with_points=False)} == {-1}
