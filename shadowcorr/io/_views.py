"""One view of a manifest decoded into a :class:`~shadowcorr.bundle.View`: pose to OpenCV, depth and mask images.

Depth given as distance along the ray (``kind: "range"``) becomes z-depth; every problem
is collected with its ``loc`` (``views[1:cam2].mask.file``) rather than raised at the first.
"""

from __future__ import annotations

import numpy as np

from ..bundle import View, ViewSpec, pose_to_opencv
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
    depth = mask = None
    if spec.depth is not None:
        loc = f"{vloc}.depth.file"
        if intr is None:
            problems.append(Problem(loc=f"{vloc}.intrinsics", msg="a view with depth needs intrinsics"))
        elif loc in paths:
            try:
                depth = images.read_depth(
                    source.read(paths[loc], loc),
                    spec.depth.format,
                    scale=spec.depth.scale,
                    channel=spec.depth.channel,
                    shape=shape,
                    max_pixels=limits.max_pixels_per_view,
                    loc=loc,
                )
                if spec.depth.kind == "range":
                    depth = range_to_z(depth, intr.fx, intr.fy, intr.cx, intr.cy)
                if not images.has_valid_depth(depth):
                    warnings.append(f"{vloc}: depth has no valid pixel (all <= 0 or non-finite)")
            except BundleError as e:
                problems += e.problems
    if spec.mask is not None:
        loc = f"{vloc}.mask.file"
        if intr is None:
            problems.append(Problem(loc=f"{vloc}.intrinsics", msg="a view with a mask needs intrinsics"))
        elif loc in paths:
            try:
                mask = images.read_mask(
                    source.read(paths[loc], loc),
                    spec.mask.format,
                    palette=spec.mask.palette,
                    shape=shape,
                    max_pixels=limits.max_pixels_per_view,
                    loc=loc,
                    warnings=warnings,
                )
                if not mask.any():
                    warnings.append(f"{vloc}: mask has no instances (all background)")
            except BundleError as e:
                problems += e.problems
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


def _mask_ids(mask: np.ndarray) -> np.ndarray:
    """Distinct ids of a mask; bincount is ~10x faster than unique for the usual small ids."""
    hi = int(mask.max(initial=0))
    if hi < 1 << 20:
        return np.flatnonzero(np.bincount(mask.ravel(), minlength=1))
    return np.unique(mask)
