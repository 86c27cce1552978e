"""The reference implementation's stacked-segment ``.npz`` -> a point-segment bundle.

SAFETY: the reference stores segments as *object arrays* (pickled Python lists), and
unpickling executes code.  This module is the ONLY place in ShadowCorr that calls
``np.load(..., allow_pickle=True)``, and only as a local, explicit action (the CLI's
convert command or a direct call) on a file the user names and trusts.  It accepts a
local path only -- never bytes, never an upload -- and the service never imports it.
The bundle it writes holds plain numeric arrays that ``load_bundle`` reads without
pickles.

We have no sample of the reference file, so the reader is deliberately tolerant about
layout and strict about content.  Recognised keys (first match wins):

* points: ``points``, ``segments``, ``segment_points``, ``point_clouds``, ``pcds``,
  ``xyz`` -- an object array of S (Ni, >=3) arrays, an (S, N, 3) array (what
  ``np.array`` makes of equal-length segments), or a concatenated (P, 3) array plus
  ``lengths`` / ``counts`` or per-point ``segment_ids``;
* camera per segment: ``view``, ``views``, ``camera_ids``, ``camera_id``, ``cam_ids``;
* instance per segment: ``instance``, ``instances``, ``instance_ids``, ``mask_ids``,
  else ``labels`` / ``label``;
* ground truth per segment: ``object``, ``objects``, ``object_ids``, ``gt_labels``,
  ``rock_ids``; when absent and the instance ids came from ``labels`` they are taken as
  rock identities (the Unreal convention, ``labels_are_objects=True``);
* cameras: 4x4 / 3x4 camera-to-world ``poses`` (``camera_poses``, ``extrinsics``,
  ``cam2world``, ``c2w``) or centres (``camera_centers`` / ``camera_centres`` /
  ``camera_positions``), as arrays or dicts keyed by camera id.  An array is indexed
  by rank among the cameras used when it has one row per used camera, else by camera
  id, else (centres only) per segment.  A centre without orientation gets a look-at
  pose toward its segments' centroid: the method needs only the camera position and
  the direction toward the segment (SPEC §2 step 3).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..bundle import PointSegments, SceneBundle, View, pose_to_opencv
from ..io import write_bundle
from ..poses import look_at_pose

__all__ = ["read_reference_npz", "convert_reference_npz"]

log = logging.getLogger(__name__)

POINT_KEYS = ("points", "segments", "segment_points", "point_clouds", "pcds", "xyz")
VIEW_KEYS = ("view", "views", "camera_ids", "camera_id", "cam_ids", "cam_id")
INSTANCE_KEYS = ("instance", "instances", "instance_ids", "mask_ids")
LABEL_KEYS = ("labels", "label")
OBJECT_KEYS = ("object", "objects", "object_ids", "gt_labels", "rock_ids")
LENGTH_KEYS = ("lengths", "counts", "sizes")
POINT_SEGMENT_KEYS = ("segment_ids", "point_segment", "seg_ids")
POSE_KEYS = ("poses", "camera_poses", "cam_poses", "extrinsics", "cam2world", "camera_to_world", "c2w")
CENTRE_KEYS = ("camera_centers", "camera_centres", "cam_centers", "cam_centres", "camera_positions", "cam_positions")


def _first(z: Mapping[str, Any], keys: Sequence[str]) -> tuple[str | None, Any]:
    for k in keys:
        if k in z:
            return k, z[k]
    return None, None


def _unwrap(a: Any) -> Any:
    """0-d object arrays hold a pickled Python object (list / dict): take it out."""
    if isinstance(a, np.ndarray) and a.dtype == object and a.ndim == 0:
        return a.item()
    return a


def _int_vector(a: Any, key: str, n: int) -> np.ndarray:
    v = np.asarray(_unwrap(a))
    if v.dtype == object:
        v = np.asarray(v.tolist())
    if v.ndim != 1 or len(v) != n:
        raise ValueError(f"{key!r} must hold one value per segment ({n}), got shape {v.shape}")
    if v.dtype.kind == "f":
        if not np.all(np.isfinite(v)) or not np.all(v == np.round(v)):
            raise ValueError(f"{key!r} must hold integers")
    elif v.dtype.kind not in "iu":
        raise ValueError(f"{key!r} must hold integers, got dtype {v.dtype}")
    return v.astype(np.int64)


def _segment_list(z: Mapping[str, Any]) -> list[np.ndarray]:
    key, raw = _first(z, POINT_KEYS)
    if key is None:
        raise ValueError(f"no point array found; expected one of {POINT_KEYS}, file has {sorted(z)}")
    raw = _unwrap(raw)
    if isinstance(raw, np.ndarray) and raw.dtype != object:
        if raw.ndim == 3:  # equal-length segments stacked by np.array
            return list(raw)
        if raw.ndim == 2:  # concatenated points: split by lengths or by per-point ids
            lkey, lengths = _first(z, LENGTH_KEYS)
            if lkey is not None:
                lengths = np.asarray(_unwrap(lengths)).astype(np.int64).ravel()
                if lengths.min(initial=0) < 0 or lengths.sum() != len(raw):
                    raise ValueError(f"{lkey!r} must be >= 0 and sum to the {len(raw)} points")
                return np.split(raw, np.cumsum(lengths)[:-1])
            skey, seg = _first(z, POINT_SEGMENT_KEYS)
            if skey is not None:
                seg = np.asarray(_unwrap(seg)).astype(np.int64).ravel()
                if len(seg) != len(raw):
                    raise ValueError(f"{skey!r} must have one entry per point")
                if len(seg) and seg.min() < 0:
                    raise ValueError(f"{skey!r} must be >= 0")
                order = np.argsort(seg, kind="stable")
                counts = np.bincount(seg, minlength=int(seg.max(initial=-1)) + 1)
                return np.split(raw[order], np.cumsum(counts)[:-1])
            raise ValueError(f"{key!r} is a flat (P, 3) array but no {LENGTH_KEYS} or {POINT_SEGMENT_KEYS} says how to split it")
        raise ValueError(f"{key!r} has shape {raw.shape}; expected segments of (N, 3) points")
    return list(raw)  # object array or Python list of per-segment arrays


def _clean_segment(i: int, seg: Any, warnings: list[str]) -> np.ndarray:
    a = np.asarray(seg)
    if a.dtype == object:
        a = np.asarray(a.tolist())
    if a.dtype.kind not in "fiu":
        raise ValueError(f"segment {i} is not numeric (dtype {a.dtype})")
    if a.ndim == 1 and a.size == 0:
        a = a.reshape(0, 3)
    if a.ndim != 2 or a.shape[1] < 3:
        raise ValueError(f"segment {i} must be an (N, 3) array, got shape {a.shape}")
    if a.shape[1] > 3:
        warnings.append(f"segment {i}: {a.shape[1]} columns, using the first 3 as x, y, z")
        a = a[:, :3]
    a = a.astype(np.float64)
    finite = np.isfinite(a).all(axis=1)
    if not finite.all():
        warnings.append(f"segment {i}: dropped {int((~finite).sum())} non-finite points")
        a = a[finite]
    return a


def _per_camera(
    value: Any, key: str, cam_ids: np.ndarray, seg_cam: np.ndarray, row_shape: tuple[int, ...]
) -> dict[int, np.ndarray]:
    """Map a per-camera table (dict or array, see module doc) to {camera id: row}."""
    value = _unwrap(value)
    if isinstance(value, dict):
        out = {}
        for cid in cam_ids:
            hit = value.get(int(cid), value.get(str(int(cid))))
            if hit is None:
                raise ValueError(f"{key!r} has no entry for camera {int(cid)}")
            out[int(cid)] = np.asarray(hit, dtype=np.float64)
        return out
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 1 + len(row_shape) and not (row_shape == (4, 4) and arr.ndim == 3 and arr.shape[1:] == (3, 4)):
        raise ValueError(f"{key!r} has shape {arr.shape}; expected (n, {', '.join(map(str, row_shape))})")
    n, n_seg = len(arr), len(seg_cam)
    if n == len(cam_ids):
        return {int(c): arr[i] for i, c in enumerate(cam_ids)}
    per_segment = None
    if n == n_seg and row_shape == (3,):
        # Per-segment centres are usable only if each camera's rows agree.
        per_segment = {}
        for c in cam_ids:
            rows = arr[seg_cam == c]
            if np.ptp(rows, axis=0).max() > 1e-6 * max(1.0, float(np.abs(rows).max())):
                per_segment = None
                break
            per_segment[int(c)] = rows.mean(axis=0)
        if per_segment is not None:
            return per_segment
    if n > int(cam_ids.max()):
        return {int(c): arr[int(c)] for c in cam_ids}
    raise ValueError(
        f"cannot match the {n} rows of {key!r} to the {len(cam_ids)} cameras {cam_ids.tolist()} "
        f"(nor to {n_seg} segments)"
    )


def read_reference_npz(
    path: str | Path,
    *,
    units: str = "cm",
    name: str | None = None,
    camera_poses: Mapping[int, Any] | None = None,
    camera_centres: Mapping[int, Sequence[float]] | None = None,
    pose_convention: str = "opencv",
    labels_are_objects: bool = True,
) -> SceneBundle:
    """Read a reference ``.npz`` (trusted, local: see the module's SAFETY note) into a point-segment ``SceneBundle``.

    ``camera_poses`` / ``camera_centres`` (keyed by camera id) override what the file
    holds, e.g. poses from ``convert.ue.UE_CAMERAS``.  Raises ``ValueError`` with the
    reason when the file cannot be understood.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"no such file: {str(p)!r}")
    warnings: list[str] = []
    # Deliberate, documented exception to "never unpickle": local file named by the user.
    with np.load(p, allow_pickle=True) as npz:
        z = {k: npz[k] for k in npz.files}

    segs = [_clean_segment(i, s, warnings) for i, s in enumerate(_segment_list(z))]
    n = len(segs)
    if n == 0:
        raise ValueError("the file holds no segments")
    vkey, vraw = _first(z, VIEW_KEYS)
    if vkey is None:
        raise ValueError(f"no camera id per segment; expected one of {VIEW_KEYS}, file has {sorted(z)}")
    seg_cam = _int_vector(vraw, vkey, n)
    ikey, iraw = _first(z, INSTANCE_KEYS)
    from_labels = False
    if ikey is None:
        ikey, iraw = _first(z, LABEL_KEYS)
        from_labels = ikey is not None
    if ikey is not None:
        instance = _int_vector(iraw, ikey, n)
    else:
        warnings.append("no instance ids in the file; numbering segments 1..S")
        instance = np.arange(1, n + 1, dtype=np.int64)
    okey, oraw = _first(z, OBJECT_KEYS)
    if okey is None and ikey in INSTANCE_KEYS:  # labels next to explicit instances are the ground truth
        okey, oraw = _first(z, LABEL_KEYS)
    obj: np.ndarray | None = _int_vector(oraw, okey, n) if okey is not None else None
    ground_truth = "none"
    if obj is not None:
        ground_truth = "mapped"
    elif from_labels and labels_are_objects:
        obj, ground_truth = instance.copy(), "instance"

    cam_ids = np.unique(seg_cam)
    poses: dict[int, np.ndarray] = {}
    if camera_poses is not None:
        poses = {int(c): np.asarray(camera_poses[int(c)], dtype=np.float64) for c in cam_ids}
    else:
        pkey, praw = _first(z, POSE_KEYS)
        if pkey is not None:
            poses = _per_camera(praw, pkey, cam_ids, seg_cam, (4, 4))
    poses = {c: (np.vstack([m, [0.0, 0.0, 0.0, 1.0]]) if m.shape == (3, 4) else m) for c, m in poses.items()}
    if not poses:
        if camera_centres is not None:
            centres = {int(c): np.asarray(camera_centres[int(c)], dtype=np.float64) for c in cam_ids}
        else:
            ckey, craw = _first(z, CENTRE_KEYS)
            if ckey is None:
                raise ValueError(
                    f"no camera poses or centres; expected one of {POSE_KEYS + CENTRE_KEYS}, file has {sorted(z)} "
                    "(or pass camera_poses= / camera_centres=)"
                )
            centres = _per_camera(craw, ckey, cam_ids, seg_cam, (3,))
        all_pts = [s for s in segs if len(s)]
        for c in cam_ids:
            mine = [segs[i] for i in np.flatnonzero(seg_cam == c) if len(segs[i])]
            target = np.concatenate(mine or all_pts).mean(axis=0)
            poses[int(c)] = look_at_pose(centres[int(c)], target)
        warnings.append("camera orientation not in the file: poses look from each camera centre at its segments")
    for c, m in poses.items():
        if m.shape != (4, 4):
            raise ValueError(f"pose of camera {c} has shape {m.shape}; expected 4x4 or 3x4")

    index = {int(c): i for i, c in enumerate(cam_ids)}
    views = [View(name=f"cam{int(c)}", pose=pose_to_opencv(poses[int(c)], pose_convention)) for c in cam_ids]
    lengths = np.array([len(s) for s in segs], dtype=np.int64)
    points = np.concatenate(segs, axis=0) if lengths.sum() else np.zeros((0, 3))
    ps = PointSegments(
        points=points,
        lengths=lengths,
        view=np.array([index[int(c)] for c in seg_cam], dtype=np.int64),
        instance=instance,
        object=obj,
    )
    return SceneBundle(
        units=units,
        views=views,
        name=name or p.stem,
        ground_truth=ground_truth,
        point_segments=ps,
        warnings=warnings,
    )


def convert_reference_npz(path: str | Path, out_dir: str | Path, **kwargs: Any) -> Path:
    """Convert a trusted local reference ``.npz`` into a point-segment bundle directory; returns ``out_dir``.

    Keyword arguments are those of ``read_reference_npz``.  Warnings (dropped points,
    synthesised poses, ...) are logged.
    """
    bundle = read_reference_npz(path, **kwargs)
    for w in bundle.warnings:
        log.warning("%s", w)
    return write_bundle(bundle, out_dir)
