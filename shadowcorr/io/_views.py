"""One view of a manifest decoded into a :class:`~shadowcorr.bundle.View`: pose to OpenCV, depth and mask images.

Depth given as distance along the ray (``kind: "range"``) becomes z-depth; every problem
is collected with its ``loc`` (``views[1:cam2].mask.file``) rather than raised at the first.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from ..bundle import Intrinsics, View, ViewSpec, pose_to_opencv
from ..errors import BundleError, Problem, view_loc
from . import images
from ._limits import BundleLimits
from ._sources import FileSource

def range_to_z(rng: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Distance along each pixel's ray -> z-depth along the optical axis (pixel centres at integer u, v)."""
    h, w = rng.shape
    x = (np.arange(w, dtype=np.float32) - np.float32(cx)) / np.float32(fx)
    y = (np.arange(h, dtype=np.float32) - np.float32(cy)) / np.float32(fy)
    norm = np.sqrt(x[None, :] ** 2 + y[:, None] ** 2 + np.float32(1.0))
    return (rng / norm).astype(np.float32)


def decode_view(
    i: int, spec: ViewSpec, paths: dict[str, str], source: FileSource, limits: BundleLimits, warnings: list[str]
) -> tuple[View | None, list[Problem]]:
    vloc = view_loc(i, spec.name)
    problems: list[Problem] = []
    pose = pose_to_opencv(np.asarray(spec.pose.matrix, dtype=np.float64), spec.pose.convention)
    intr = spec.intrinsics
    shape = (intr.height, intr.width) if intr is not None else None
    if intr is not None and intr.width * intr.height > limits.max_pixels_per_view:
        problems.append(
            Problem(
                loc=f"{vloc}.intrinsics",
                msg=f"{intr.width}x{intr.height} pixels exceeds the limit of {limits.max_pixels_per_view} per view",
            )
        )
        return None, problems
    read = functools.partial(_read_image, vloc, intr, paths, source, problems)
    depth = mask = None
    if spec.depth is not None:
        depth = read("depth", "depth", lambda data, loc: images.read_depth(
            data, spec.depth.format, scale=spec.depth.scale, channel=spec.depth.channel, shape=shape,
            max_pixels=limits.max_pixels_per_view, loc=loc))
        if depth is not None:
            if spec.depth.kind == "range":
                depth = range_to_z(depth, intr.fx, intr.fy, intr.cx, intr.cy)
            if not images.has_valid_depth(depth):
                warnings.append(f"{vloc}: depth has no valid pixel (all <= 0 or non-finite)")
    if spec.mask is not None:
        mask = read("mask", "a mask", lambda data, loc: images.read_mask(
            data, spec.mask.format, palette=spec.mask.palette, shape=shape, max_pixels=limits.max_pixels_per_view,
            loc=loc, warnings=warnings))
        if mask is not None and not mask.any():
            warnings.append(f"{vloc}: mask has no instances (all background)")
    if mask is not None and spec.instance_objects is not None:
        ids = _mask_ids(mask)
        unmapped = sorted(set(ids.tolist()) - set(spec.instance_objects) - {0})
        if unmapped:
            warnings.append(f"{vloc}: instance ids {unmapped[:10]} have no entry in instance_objects (no ground truth)")
    if problems:
        return None, problems
    view = View(
        name=spec.name,
        pose=pose,
        intrinsics=intr,
        depth=depth,
        mask=mask,
        instance_objects=dict(spec.instance_objects) if spec.instance_objects is not None else None,
    )
    return view, problems


def _read_image(vloc: str, intr: Intrinsics | None, paths: dict[str, str], source: FileSource, problems: list[Problem], field: str,
                what: str, decode: Callable[[bytes, str], np.ndarray]) -> np.ndarray | None:
    """The depth or mask image (``field``) of one view, ``decode(bytes, loc)``-ed; None when the
    view has no intrinsics, the file is missing (already reported) or unreadable (``problems`` say why)."""
    loc = f"{vloc}.{field}.file"
    if intr is None:
        problems.append(Problem(loc=f"{vloc}.intrinsics", msg=f"a view with {what} needs intrinsics"))
        return None
    if loc not in paths:
        return None
    try:
        return decode(source.read(paths[loc], loc), loc)
    except BundleError as e:
        problems += e.problems
        return None


def _mask_ids(mask: np.ndarray) -> np.ndarray:
    """Distinct ids of a mask; bincount is ~10x faster than unique for the usual small ids."""
    hi = int(mask.max(initial=0))
    if hi < 1 << 20:
        return np.flatnonzero(np.bincount(mask.ravel(), minlength=1))
    return np.unique(mask)
