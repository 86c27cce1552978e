"""Mask alignment (``pose_mask_alignment``): views that registration leaves unverified turn to the other views' masks."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from shadowcorr import ShadowCorrConfig
from shadowcorr.stages import align_to_masks, refine_poses
from shadowcorr.synth.spheres import sphere_scene

CENTRES = [[-120, -60, 30], [-30, 90, 45], [60, -20, 35], [140, 70, 25], [20, 20, 60], [-90, 40, 20],
           [100, -110, 40], [-40, -140, 30]]
RADII = [30, 45, 35, 25, 60, 20, 40, 30]


@pytest.fixture(scope="module")
def scene():
    return sphere_scene(CENTRES, RADII, cameras=4, radius=700.0, height=250.0, width=640, height_px=360)


def turned(pose: np.ndarray, degrees: float, axis) -> np.ndarray:
    """The pose turned about its own camera centre by ``degrees`` about the world ``axis``."""
    out = pose.copy()
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    out[:3, :3] = Rotation.from_rotvec(np.deg2rad(degrees) * axis).as_matrix() @ pose[:3, :3]
    return out


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    r = a[:3, :3].T @ b[:3, :3]
    return float(np.rad2deg(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def with_pose(bundle, k: int, pose: np.ndarray):
    views = list(bundle.views)
    views[k] = dataclasses.replace(views[k], pose=pose)
    return dataclasses.replace(bundle, views=views)


@pytest.mark.parametrize("axis", [(0, 0, 1), (1, -1, 0.3)])
def test_a_turned_view_turns_back_onto_the_other_views_masks(scene, axis):
    off = with_pose(scene, 2, turned(scene.views[2].pose, 1.0, axis))
    poses = align_to_masks(off.views, [2], max_depth=5000.0)
    assert angle_deg(off.views[2].pose, scene.views[2].pose) == pytest.approx(1.0, abs=1e-6)
    assert angle_deg(poses[2], scene.views[2].pose) < 0.25
    # The camera turns about its own centre; the held views do not move.
    np.testing.assert_allclose(poses[2][:3, 3], off.views[2].pose[:3, 3])
    for k in (0, 1, 3):
        np.testing.assert_array_equal(poses[k], off.views[k].pose)


@pytest.mark.parametrize("free", [[1, 2], [0, 1, 2, 3]])
def test_exact_poses_stay_exact(scene, free):
    # With exact poses the landings off the masks are the sampled outlines' own (under a pixel, and
    # all on the side facing the view they come from): they must not turn anything.
    poses = align_to_masks(scene.views, free, max_depth=5000.0)
    assert max(angle_deg(p, v.pose) for p, v in zip(poses, scene.views)) < 0.01


def test_nothing_to_move_or_nothing_to_land_on_changes_nothing(scene):
    for free in ([], [7]):
        assert all(np.array_equal(p, v.pose) for p, v in zip(align_to_masks(scene.views, free, 5000.0), scene.views))
    # The other views carry no masks: nothing to land on, so nothing moves.
    alone = dataclasses.replace(scene, views=[scene.views[0]] + [dataclasses.replace(v, mask=None)
                                                                 for v in scene.views[1:]])
    off = turned(alone.views[0].pose, 1.0, (0, 0, 1))
    poses = align_to_masks(with_pose(alone, 0, off).views, [0], 5000.0)
    np.testing.assert_array_equal(poses[0], off)


def relative_errors(bundle, truth) -> list[float]:
    """Degrees between each view's pose relative to view 0 and the true one."""
    return [angle_deg(np.linalg.inv(bundle.views[0].pose) @ bundle.views[k].pose,
                      np.linalg.inv(truth.views[0].pose) @ truth.views[k].pose) for k in range(1, len(truth.views))]


def test_refinement_turns_the_views_it_cannot_register_and_says_so(scene, monkeypatch):
    from shadowcorr.stages import _01_poses as pose_refinement

    # No pair registers (too little overlap, not even on grazing surfaces): every view moves, their
    # mean turn held at zero.
    monkeypatch.setattr(pose_refinement, "_grazing_pairs", lambda *args, **kwargs: [])
    unregistered = ShadowCorrConfig(pose_min_overlap=1.0)
    off = with_pose(scene, 1, turned(scene.views[1].pose, 1.0, (0.2, 1, 0)))
    kept, kept_reports = refine_poses(off, unregistered.with_options(pose_mask_alignment=False))
    assert [r.status for r in kept_reports] == ["not_registered"] * 4
    assert all(np.array_equal(a.pose, b.pose) for a, b in zip(kept.views, off.views))

    refined, reports = refine_poses(off, unregistered.with_options(pose_mask_alignment=True))
    assert [r.status for r in reports] == ["not_registered"] * 4  # still not borne out by registration
    # Eight floating spheres pin the views' relative turns less well than a rock field:
    # the turned view's error falls from 1 degree to under half of it.
    assert max(relative_errors(off, scene)) == pytest.approx(1.0, abs=1e-6)
    assert max(relative_errors(refined, scene)) < 0.5, relative_errors(refined, scene)
    for view, after, r in zip(off.views, refined.views, reports):
        np.testing.assert_allclose(np.asarray(r.correction) @ view.pose, after.pose, atol=1e-6)
        assert r.translation == 0.0 and "pose_mask_alignment" in r.message
    assert reports[1].rotation_deg > 0.5
