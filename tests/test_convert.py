"""Converters: the Unreal sample scene (real data, read sparingly) and reference .npz files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree

from shadowcorr.bundle import SceneBundle, View
from shadowcorr.convert import (
    UE_CAMERAS,
    UE_CLASS_COLOURS,
    convert_reference_npz,
    convert_ue,
    load_ue_scene,
    read_reference_npz,
    ue_pose_opencv,
)
from shadowcorr.errors import BundleError
from shadowcorr.io import images, load_bundle

from .paths import SAMPLE_DIR

UE_DIR = SAMPLE_DIR
needs_ue = pytest.mark.skipif(not (UE_DIR / "cameras_opencv.json").is_file(), reason="UE sample data not available")


# --------------------------------------------------------------------------- poses
@needs_ue
def test_poses_match_cameras_opencv_json_for_all_cameras() -> None:
    expected = json.loads((UE_DIR / "cameras_opencv.json").read_text())
    assert sorted(int(k) for k in expected) == sorted(UE_CAMERAS)
    for cam, c in UE_CAMERAS.items():
        pose = ue_pose_opencv(c.position, c.pitch, c.yaw, c.roll)
        np.testing.assert_allclose(pose, np.array(expected[str(cam)]), atol=1e-5, err_msg=f"camera {cam}")


def test_roll_rotates_about_the_optical_axis() -> None:
    c = UE_CAMERAS[2]
    base = ue_pose_opencv(c.position, c.pitch, c.yaw, 0.0)
    for roll in (10.0, 90.0, -45.0):
        rolled = ue_pose_opencv(c.position, c.pitch, c.yaw, roll)
        r = rolled[:3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)
        np.testing.assert_allclose(rolled[:3, 2], base[:3, 2], atol=1e-12)  # forward unchanged
        # right/down turn by |roll| within the image plane
        cos = float(rolled[:3, 0] @ base[:3, 0])
        assert cos == pytest.approx(np.cos(np.radians(roll)), abs=1e-12)
        np.testing.assert_allclose(rolled[:3, 3], base[:3, 3])


# --------------------------------------------------------------------------- real data
def back_project(view: View, sel: np.ndarray, focal: float) -> np.ndarray:
    v, u = np.nonzero(sel)
    z = view.depth[v, u].astype(np.float64)
    intr = view.intrinsics
    cam = np.stack([(u - intr.cx) * z / focal, (v - intr.cy) * z / focal, z], axis=1)
    return cam @ view.pose[:3, :3].T + view.pose[:3, 3]


@pytest.fixture(scope="module")
def ue01() -> SceneBundle:
    return load_ue_scene(UE_DIR, 2001, (0, 1))


@needs_ue
def test_ue_scene_decodes(ue01: SceneBundle) -> None:
    assert ue01.units == "cm" and ue01.ground_truth == "instance" and ue01.warnings == []
    v = ue01.views[0]
    assert v.name == "cam0" and v.depth.shape == v.mask.shape == (1080, 1920)
    assert (v.intrinsics.fx, v.intrinsics.cx, v.intrinsics.cy) == (1615.0, 960.0, 540.0)
    ids = np.unique(v.mask)
    assert ids[0] == 0 and set(ids.tolist()) <= set(UE_CLASS_COLOURS) and len(ids) > 10
    assert v.depth.dtype == np.float32 and v.depth[v.mask > 0].min() > 0


@needs_ue
def test_neighbouring_views_line_up_only_with_the_measured_focal_length(ue01: SceneBundle) -> None:
    a, b = ue01.views
    # the rock seen best by both cameras
    counts = np.bincount(a.mask.ravel(), minlength=21)[1:] * np.bincount(b.mask.ravel(), minlength=21)[1:]
    rock = int(np.argmax(counts)) + 1
    med = {}
    for focal in (1615.0, 960.0):
        pa = back_project(a, a.mask == rock, focal)
        pb = back_project(b, b.mask == rock, focal)
        med[focal] = float(np.median(cKDTree(pa).query(pb)[0]))
    assert med[1615.0] < 1.0, med
    assert med[960.0] > 10.0, med


@needs_ue
def test_convert_ue_writes_a_bundle_equal_to_the_in_memory_scene(tmp_path: Path, ue01: SceneBundle) -> None:
    out = convert_ue(UE_DIR, 2001, [1], tmp_path / "ue")
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["units"] == "cm" and manifest["ground_truth"] == "instance"
    assert manifest["views"][0]["depth"]["format"] == "exr"
    mask_png = Image.open(out / manifest["views"][0]["mask"]["file"])
    assert mask_png.mode == "P"  # 8-bit single channel (palette indices), value = class id
    loaded = load_bundle(out)
    ref = ue01.views[1]
    got = loaded.views[0]
    assert got.name == "cam1"
    np.testing.assert_array_equal(got.mask, ref.mask)
    np.testing.assert_array_equal(got.depth, ref.depth)
    np.testing.assert_allclose(got.pose, ref.pose, atol=1e-12)
    # values are the original half floats, not re-quantised
    raw = images.read_exr_channel((UE_DIR / "Set2001_Depth_1.exr").read_bytes())
    np.testing.assert_array_equal(got.depth, raw)


@needs_ue
def test_ue_missing_files_are_all_reported(tmp_path: Path) -> None:
    for name in ("Set2001_Depth_2.exr", "Set2001_Segment_2.png"):  # the set exists, with camera 2 only
        (tmp_path / name).symlink_to(UE_DIR / name)
    with pytest.raises(BundleError) as ei:
        load_ue_scene(tmp_path, 2001, (0, 9))
    locs = {p.loc for p in ei.value.problems}
    assert "views[0:cam0].mask.file" in locs and "views[1:cam9].pose" in locs


@needs_ue
def test_ue_mistyped_folder_and_missing_set_are_one_clear_problem(tmp_path: Path) -> None:
    with pytest.raises(BundleError, match=r"^1 problem in bundle: dataset: '.*/no_such_dir': no such directory$"):
        load_ue_scene(tmp_path / "no_such_dir", 2001)
    with pytest.raises(BundleError, match=r"^1 problem in bundle: set: set 2010 is not in .*; sets present: 2001$"):
        load_ue_scene(UE_DIR, 2010)


# --------------------------------------------------------------------------- reference npz
def _ragged(*arrays: np.ndarray) -> np.ndarray:
    out = np.empty(len(arrays), dtype=object)
    for i, a in enumerate(arrays):
        out[i] = a
    return out


def _segments(rng: np.random.Generator, centre: np.ndarray, sizes: list[int]) -> list[np.ndarray]:
    return [centre[i] + rng.normal(scale=5.0, size=(n, 3)) for i, n in enumerate(sizes)]


def test_reference_npz_object_arrays_with_centres(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    centres = np.array([[0, 0, 0], [50, 0, 0], [0, 50, 0], [20, 20, 0]], float)
    segs = _segments(rng, centres, [30, 12, 25, 40])
    segs[1][3, 0] = np.nan  # dropped with a warning
    cams = np.array([2, 2, 6, 6])
    cam_centres = np.array([[300.0, 0, 200], [-300.0, 0, 200]])  # one row per used camera
    path = tmp_path / "ref.npz"
    np.savez(path, points=_ragged(*segs), camera_ids=cams, labels=np.array([5, 7, 5, 9]), camera_centers=cam_centres)

    out = convert_reference_npz(path, tmp_path / "bundle")
    b = load_bundle(out)  # loads without any pickle
    ps = b.point_segments
    assert [v.name for v in b.views] == ["cam2", "cam6"]
    np.testing.assert_array_equal(ps.lengths, [30, 11, 25, 40])
    np.testing.assert_array_equal(ps.view, [0, 0, 1, 1])
    np.testing.assert_array_equal(ps.instance, [5, 7, 5, 9])
    np.testing.assert_array_equal(ps.object, [5, 7, 5, 9])
    assert b.ground_truth == "instance"
    np.testing.assert_allclose(ps.points[:30], segs[0])
    for v, c in zip(b.views, cam_centres):
        np.testing.assert_allclose(v.camera_center, c)
        # synthesised pose looks toward this camera's segments
        mine = ps.points[np.repeat(ps.view, ps.lengths) == b.views.index(v)]
        d = mine.mean(axis=0) - c
        assert float(v.optical_axis @ d / np.linalg.norm(d)) == pytest.approx(1.0)


def test_reference_npz_flat_points_with_poses_by_camera_id(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    segs = _segments(rng, np.zeros((3, 3)), [10, 20, 5])
    poses = np.repeat(np.eye(4)[None], 8, axis=0)
    poses[:, 0, 3] = np.arange(8) * 10.0  # camera id i sits at x = 10 i
    path = tmp_path / "flat.npz"
    np.savez(
        path,
        points=np.concatenate(segs),
        lengths=np.array([10, 20, 5]),
        view=np.array([1, 4, 4]),
        instance=np.array([1, 2, 3]),
        object=np.array([1, 1, 2]),
        poses=poses,
    )
    b = read_reference_npz(path)
    assert [v.camera_center[0] for v in b.views] == [10.0, 40.0]
    assert b.ground_truth == "mapped"
    np.testing.assert_array_equal(b.point_segments.object, [1, 1, 2])


def test_reference_npz_equal_length_segments_and_bad_files(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    stacked = rng.normal(size=(3, 8, 3))  # what np.array makes of equal-length segments
    p = tmp_path / "eq.npz"
    np.savez(p, segments=stacked, camera_ids=np.array([0, 1, 1]), camera_poses=np.repeat(np.eye(4)[None], 2, 0))
    b = read_reference_npz(p)
    np.testing.assert_array_equal(b.point_segments.lengths, [8, 8, 8])
    assert b.ground_truth == "none"

    np.savez(p, segments=stacked)
    with pytest.raises(ValueError, match="no camera id per segment"):
        read_reference_npz(p)
    np.savez(p, segments=stacked, camera_ids=np.array([0, 1, 1]))
    with pytest.raises(ValueError, match="no camera poses or centres"):
        read_reference_npz(p)
    np.savez(p, segments=_ragged(np.ones((4, 2)), np.ones((3, 3))), camera_ids=np.array([0, 1]))
    with pytest.raises(ValueError, match=r"segment 0 must be an \(N, 3\) array"):
        read_reference_npz(p)
