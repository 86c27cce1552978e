"""The authors' Unreal Engine lunar-rock dataset -> ShadowCorr bundles.

Per set and camera ``C`` the dataset has ``Set{set}_Depth_{C}.exr`` (z-depth in cm,
RGBA half floats with R = G = B) and ``Set{set}_Segment_{C}.png`` (colour-coded masks
whose colour is the rock's identity in every view, SPEC §4).  Camera poses are not in
the files; they come from the dataset's documentation table (``UE_CAMERAS``).

Facts this module encodes (SPEC §4, checked by the tests):

* The documented focal length (960 px, 90° FOV) is wrong for these files; views only
  line up with ``fx = fy = 1615`` px and the principal point at the image centre.
* Pose rule (matches ``data/ue_sample/cameras_opencv.json`` to < 1e-6): the documented
  positions are already in the right-handed world frame the bundle uses, while the
  pitch / yaw / roll angles are Unreal's (left-handed, X forward, Y right, Z up).  The
  world is Unreal's with y negated, so each Unreal camera axis is mapped through
  ``diag(1, -1, 1)``: forward ``f = (cos p cos(-y), cos p sin(-y), sin p)``; with roll 0,
  ``right = normalize(f x (0, 0, 1))`` and ``down = f x right``.
* Depth ``<= 0`` or ``> 2000`` is invalid in this dataset; the loader here only applies
  the generic rule (``<= 0`` / non-finite -> 0) -- the far cut belongs to the segmenter's
  configuration (``UE_DEPTH_MAX`` is exported for it).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from ..bundle import Intrinsics, SceneBundle, View
from ..errors import BundleError, Problem, view_loc
from ..io import images
from ..io import write_bundle

__all__ = [
    "UE_CLASS_COLOURS",
    "UECamera",
    "UE_CAMERAS",
    "UE_PAPER_CAMERAS",
    "UE_FOCAL_PX",
    "UE_DEPTH_MAX",
    "UE_UNITS",
    "ue_pose_opencv",
    "ue_file_names",
    "ue_sets",
    "load_ue_scene",
    "convert_ue",
]

log = logging.getLogger(__name__)

#: Rock id -> mask colour (SPEC §4).  0 is background.
UE_CLASS_COLOURS: dict[int, tuple[int, int, int]] = {
    0: (0, 0, 0),
    1: (255, 255, 0),
    2: (255, 255, 127),
    3: (255, 0, 0),
    4: (255, 0, 255),
    5: (0, 255, 0),
    6: (127, 254, 255),
    7: (0, 0, 255),
    8: (255, 191, 0),
    9: (255, 255, 191),
    10: (255, 127, 0),
    11: (255, 191, 127),
    12: (255, 127, 255),
    13: (191, 255, 255),
    14: (255, 63, 255),
    15: (63, 191, 0),
    16: (255, 63, 0),
    17: (255, 191, 254),
    18: (0, 255, 255),
    19: (255, 255, 63),
    20: (63, 255, 255),
}


@dataclass(frozen=True)
class UECamera:
    """One camera of the dataset's documentation table (cm, degrees, Unreal angles)."""

    position: tuple[float, float, float]
    pitch: float
    yaw: float
    roll: float = 0.0


#: The dataset's camera table (SPEC §4).
UE_CAMERAS: dict[int, UECamera] = {
    0: UECamera((345.03, 1015.59, 329.10), -26.71, 91.44, 0.0),
    1: UECamera((1076.78, 755.59, 329.10), -23.74, -211.70, 0.0),
    2: UECamera((1343.34, 267.84, 329.10), -21.76, -178.34, 0.0),
    3: UECamera((1065.47, -248.91, 329.10), -21.50, -142.46, 0.0),
    4: UECamera((302.47, -499.34, 329.10), -25.13, -87.01, 0.0),
    5: UECamera((-280.62, -174.59, 329.10), -24.27, -37.38, 0.0),
    6: UECamera((-439.22, 306.06, 329.10), -26.05, 1.03, 0.0),
    7: UECamera((-260.75, 710.91, 329.10), -25.67, 31.12, 0.0),
}

UE_PAPER_CAMERAS: tuple[int, ...] = (0, 2, 4, 6)  # the paper's 4 views, 90° apart
UE_FOCAL_PX = 1615.0  # measured; the documented 960 does not make views line up
UE_DEPTH_MAX = 2000.0  # cm; deeper values are invalid in this dataset (segmenter option)
UE_UNITS = "cm"

# Unreal world (left-handed, y flipped relative to ours) -> bundle world.
_FLIP_Y = np.diag([1.0, -1.0, 1.0])


def ue_pose_opencv(
    position: Sequence[float], pitch: float, yaw: float, roll: float = 0.0
) -> np.ndarray:
    """Camera-to-world 4x4 in the OpenCV optical convention for an Unreal camera.

    The rotation is Unreal's ``FRotationMatrix(pitch, yaw, roll)`` -- rows are the
    camera's forward (X), right (Y) and up (Z) axes in Unreal world coordinates --
    mapped into the bundle world by negating y.  OpenCV columns are then
    ``[right, -up, forward]``.  With ``roll = 0`` this is exactly the rule checked
    against ``cameras_opencv.json``; roll follows Unreal's formula for consistency
    (a rotation of right/down about the forward axis) but the dataset never uses it.
    The translation is ``position`` as given: the documented positions are already
    in the bundle's world frame (verified against the data: views line up).
    """
    p, y, r = np.radians([pitch, yaw, roll])
    cp, sp, cy, sy, cr, sr = np.cos(p), np.sin(p), np.cos(y), np.sin(y), np.cos(r), np.sin(r)
    forward = np.array([cp * cy, cp * sy, sp])
    right = np.array([sr * sp * cy - cr * sy, sr * sp * sy + cr * cy, -sr * cp])
    up = np.array([-(cr * sp * cy + sr * sy), cy * sr - cr * sp * sy, cr * cp])
    rot = _FLIP_Y @ np.stack([right, -up, forward], axis=1)
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = np.asarray(position, dtype=np.float64)
    return pose


def ue_file_names(set_id: int | str, camera: int) -> tuple[str, str]:
    """(depth file, mask file) names of one camera of one set."""
    return f"Set{set_id}_Depth_{camera}.exr", f"Set{set_id}_Segment_{camera}.png"


_UE_DEPTH = re.compile(r"^Set(\d+)_Depth_(\d+)\.exr$")


def ue_sets(directory: str | Path) -> dict[str, list[int]]:
    """Sets of an Unreal-layout dataset directory: set id -> cameras with both depth and mask files."""
    root = Path(directory)
    sets: dict[str, list[int]] = {}
    for f in root.iterdir():
        m = _UE_DEPTH.match(f.name)
        if m and (root / ue_file_names(m.group(1), int(m.group(2)))[1]).exists():
            sets.setdefault(m.group(1), []).append(int(m.group(2)))
    return {k: sorted(v) for k, v in sorted(sets.items())}


def load_ue_scene(
    dataset_dir: str | Path,
    set_id: int | str,
    cameras: Sequence[int] = UE_PAPER_CAMERAS,
    *,
    focal_px: float = UE_FOCAL_PX,
    camera_table: Mapping[int, UECamera] | None = None,
) -> SceneBundle:
    """Decode one set of the dataset straight into a ``SceneBundle`` (no disk writes).

    Views are named ``cam{C}``; masks become rock ids via ``UE_CLASS_COLOURS``
    (``ground_truth = "instance"``: the id is the rock's identity in every view).
    Depth keeps the stored values (half -> float32 is exact), with the generic invalid
    rule applied exactly as ``load_bundle`` would, so that
    ``load_bundle(convert_ue(...))`` gives the same arrays.
    """
    views, warnings = _read_ue_views(dataset_dir, set_id, cameras, focal_px, camera_table)
    for v in views:
        v.depth = images.clean_depth(v.depth, inplace=True)
    return SceneBundle(units=UE_UNITS, views=views, name=f"ue_set{set_id}", ground_truth="instance", warnings=warnings)


def convert_ue(
    dataset_dir: str | Path,
    set_id: int | str,
    cameras: Sequence[int],
    out_dir: str | Path,
    *,
    focal_px: float = UE_FOCAL_PX,
    depth_format: Literal["exr", "npy"] = "exr",
    camera_table: Mapping[int, UECamera] | None = None,
) -> Path:
    """Write one set of the dataset as a bundle directory; returns ``out_dir``.

    Units ``cm``, ``ground_truth = "instance"``; depth as EXR (or ``.npy``) holding the
    original values (half floats, as the dataset stores them); masks as 8-bit single-channel
    PNGs (palette indices, grey palette: see ``encode_mask_png``) whose value is the rock
    (class) id.
    """
    views, warnings = _read_ue_views(dataset_dir, set_id, cameras, focal_px, camera_table)
    for w in warnings:
        log.warning("%s", w)
    bundle = SceneBundle(units=UE_UNITS, views=views, name=f"ue_set{set_id}", ground_truth="instance")
    return write_bundle(bundle, out_dir, depth_format=depth_format, mask_format="png")


def _read_ue_views(
    dataset_dir: str | Path,
    set_id: int | str,
    cameras: Sequence[int],
    focal_px: float,
    camera_table: Mapping[int, UECamera] | None,
) -> tuple[list[View], list[str]]:
    """Read the raw views; every missing / bad file is reported together."""
    root = Path(dataset_dir)
    table = UE_CAMERAS if camera_table is None else camera_table
    if not cameras:
        raise BundleError("no cameras selected", loc="cameras")
    # A mistyped folder or set is one problem, not one "missing file" per camera.
    if not root.is_dir():
        raise BundleError(f"{str(root)!r}: no such directory", loc="dataset")
    sets = ue_sets(root)
    if str(set_id) not in sets:
        present = ", ".join(sets) or "none (no SetNNNN_Depth_C.exr with its SetNNNN_Segment_C.png)"
        raise BundleError(f"set {set_id} is not in {str(root)!r}; sets present: {present}", loc="set")
    if len(set(cameras)) != len(cameras):
        raise BundleError(f"cameras listed twice: {list(cameras)}", loc="cameras")
    problems: list[Problem] = []
    warnings: list[str] = []
    views: list[View] = []
    for i, cam in enumerate(cameras):
        vloc = view_loc(i, f"cam{cam}")
        if cam not in table:
            problems.append(Problem(loc=f"{vloc}.pose", msg=f"camera {cam} is not in the camera table {sorted(table)}"))
            continue
        depth_name, mask_name = ue_file_names(set_id, cam)
        try:
            # Mask first: its size fixes the intrinsics the depth is checked against.
            mask_bytes = _read_file(root / mask_name, f"{vloc}.mask.file")
            try:
                width, height = images.png_size(mask_bytes)
            except ValueError as e:
                raise BundleError(str(e), loc=f"{vloc}.mask.file") from None
            mask = images.read_mask_png_rgb(
                mask_bytes, UE_CLASS_COLOURS, shape=(height, width), loc=f"{vloc}.mask.file", warnings=warnings
            )
            depth = images.read_exr_channel(
                _read_file(root / depth_name, f"{vloc}.depth.file"), shape=(height, width), loc=f"{vloc}.depth.file"
            )
        except BundleError as e:
            problems += e.problems
            continue
        c = table[cam]
        views.append(
            View(
                name=f"cam{cam}",
                pose=ue_pose_opencv(c.position, c.pitch, c.yaw, c.roll),
                intrinsics=Intrinsics(fx=focal_px, fy=focal_px, cx=width / 2.0, cy=height / 2.0, width=width, height=height),
                depth=depth,
                mask=mask,
            )
        )
    if problems:
        raise BundleError(problems)
    return views, warnings


def _read_file(path: Path, loc: str) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise BundleError(f"missing file {str(path)!r}", loc=loc) from None
    except OSError as e:
        raise BundleError(f"cannot read {str(path)!r}: {e}", loc=loc) from None
