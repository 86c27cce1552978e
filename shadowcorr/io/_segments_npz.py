"""The point flavour of a bundle: a segments ``.npz`` parsed member by member, never unpickled."""

from __future__ import annotations

import io
import zipfile
import zlib

import numpy as np

from ..bundle import PointSegments
from ..errors import BundleError, Problem, SceneLimitError
from . import images
from ._limits import MEMBER_RATIO_MIN_BYTES, BundleLimits

_SEG_REQUIRED = ("points", "lengths", "view", "instance")
_SEG_OPTIONAL = ("object",)


def read_segments_npz(data: bytes, n_views: int, limits: BundleLimits, warnings: list[str]) -> PointSegments:
    """Parse a point-segment ``.npz`` member by member (never ``np.load`` on the zip: no pickles, bounded sizes)."""
    base = "segments"
    problems: list[Problem] = []
    arrays: dict[str, np.ndarray] = {}
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except (zipfile.BadZipFile, ValueError) as e:
        raise BundleError(f"not an .npz file: {e}", loc=f"{base}.file") from None
    with zf:
        infos = [i for i in zf.infolist() if not i.is_dir()]
        if len(infos) > 16:
            raise BundleError(f".npz has {len(infos)} members; expected {_SEG_REQUIRED + _SEG_OPTIONAL}", loc=f"{base}.file")
        declared = sum(i.file_size for i in infos)
        if declared > limits.max_total_bytes:
            raise BundleError(f".npz expands to {declared} bytes; the limit is {limits.max_total_bytes}", loc=f"{base}.file")
        for info in infos:
            key = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            if key not in _SEG_REQUIRED + _SEG_OPTIONAL:
                warnings.append(f"{base}: ignored unknown array {key!r}")
                continue
            loc = f"{base}.{key}"
            ratio = info.file_size / max(info.compress_size, 1)
            try:
                with zf.open(info) as m:
                    # The header says what the array costs: refuse before decompressing the rest.
                    head = m.read(min(info.file_size, images.NPY_HEADER_BYTES))
                    shape, _, _ = images.npy_header(head, loc=loc)
                    if key == "points" and len(shape) == 2 and shape[0] > limits.max_scene_points:
                        raise SceneLimitError("max_scene_points", shape[0], limits.max_scene_points,
                                              "points in the segments .npz")
                    if info.file_size > MEMBER_RATIO_MIN_BYTES and ratio > limits.max_compression_ratio:
                        problems.append(Problem(loc=loc, msg=f"compression ratio {ratio:.0f}:1 exceeds "
                                                f"{limits.max_compression_ratio:.0f}:1 (zip bomb?)"))
                        continue
                    raw = head + m.read(info.file_size + 1 - len(head))
            except SceneLimitError:
                raise
            except BundleError as e:
                problems += e.problems
                continue
            except (zipfile.BadZipFile, OSError, NotImplementedError, RuntimeError, ValueError, EOFError,
                    zlib.error) as e:
                problems.append(Problem(loc=loc, msg=f"cannot extract: {e}"))
                continue
            try:
                arrays[key] = images.read_npy(raw, max_elements=3 * limits.max_scene_points, loc=loc)
            except BundleError as e:
                problems += e.problems
    for key in _SEG_REQUIRED:
        if key not in arrays and not any(p.loc == f"{base}.{key}" for p in problems):
            problems.append(Problem(loc=f"{base}.{key}", msg="required array missing"))
    if problems:
        raise BundleError(problems)

    pts = arrays["points"]
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.dtype.kind not in "fiu":
        problems.append(Problem(loc=f"{base}.points", msg=f"must be a numeric (P, 3) array, got {pts.dtype} {pts.shape}"))
    elif not np.isfinite(pts).all():
        problems.append(Problem(loc=f"{base}.points", msg="points must be finite (found NaN or inf)"))
    ints: dict[str, np.ndarray] = {}
    for key in ("lengths", "view", "instance", "object"):
        if key not in arrays:
            continue
        a = arrays[key]
        if a.ndim != 1 or a.dtype.kind not in "iu":
            problems.append(Problem(loc=f"{base}.{key}", msg=f"must be a 1-D integer array, got {a.dtype} {a.shape}"))
            continue
        ints[key] = a.astype(np.int64)
    if "lengths" in ints:
        n_seg = len(ints["lengths"])
        if n_seg > limits.max_segments:
            problems.append(Problem(loc=f"{base}.lengths", msg=f"{n_seg} segments; the limit is {limits.max_segments}"))
        if (ints["lengths"] < 0).any():
            problems.append(Problem(loc=f"{base}.lengths", msg="lengths must be >= 0"))
        elif pts.ndim == 2 and int(ints["lengths"].sum()) != pts.shape[0]:
            problems.append(
                Problem(loc=f"{base}.lengths", msg=f"lengths sum to {int(ints['lengths'].sum())} but there are {pts.shape[0]} points")
            )
        for key in ("view", "instance", "object"):
            if key in ints and len(ints[key]) != n_seg:
                problems.append(Problem(loc=f"{base}.{key}", msg=f"has {len(ints[key])} entries for {n_seg} segments"))
        if "view" in ints and len(ints["view"]) == n_seg and n_seg:
            bad = (ints["view"] < 0) | (ints["view"] >= n_views)
            if bad.any():
                problems.append(
                    Problem(loc=f"{base}.view", msg=f"view indices must be in 0..{n_views - 1}; found {int(ints['view'][bad][0])}")
                )
        if n_seg and (ints["lengths"] == 0).any():
            warnings.append(f"{base}: {int((ints['lengths'] == 0).sum())} segments have no points")
    if problems:
        raise BundleError(problems)
    return PointSegments(
        points=np.ascontiguousarray(pts, dtype=np.float64),
        lengths=ints["lengths"],
        view=ints["view"],
        instance=ints["instance"],
        object=ints.get("object"),
    )
