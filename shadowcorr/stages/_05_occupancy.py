"""Stage 5 (occupancy): shadow voxels -> the share of each voxel that is solid, seen from every view.

Shadows (stage 5) say where a segment's object may extend; the depth images say where
it cannot.  Every cell of the shared voxel grid that some shadow reaches is sampled at
``volume_subdivisions``\\ :sup:`3` sub-cell centres, and each sample is projected into every
view.  A sample is *empty* when a view sees past it (the view's depth at its pixel lies
beyond it, or is invalid on the background there: the ray met nothing), and *outside every object* when a
view sees the background (mask value 0) in front of it, such as the ground hiding the part
of a shadow that reaches below a rock's foot.  What no view rules out is solid: the
intersection of the shadows' reach with every view's free space, a visual hull tightened by
the measured depth.

Per cell the stage keeps the solid share, the share ruled out by the background of one view
alone (a segmenter that missed an object in one view would carve it wrongly there, so
that part counts as uncertain), and the segment whose shadow gives the cell the most
confidence (the cell belongs to that segment's object once objects are known, stage 11).
Samples are processed view by view on flat arrays: the cost is cells x samples x views,
with no loop over cells.  Nothing here reads ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..bundle import View
from ..config import ShadowCorrConfig
from ..ops import pack_cell_keys, unique_keys
from ._05_shadows import ShadowVoxels


@dataclass
class ShadowOccupancy:
    """The cells of the shared voxel grid that some shadow reaches and some sample of which is solid."""

    cell: np.ndarray  # (U, 3) int64 voxel index (centre = cell * voxel_size, config units)
    solid: np.ndarray  # (U,) share of the cell's samples no view rules out, in (0, 1]
    single_view: np.ndarray  # (U,) share ruled out only by one view's background
    segment: np.ndarray  # (U,) segment whose shadow gives the cell the most confidence
    samples: int  # samples per cell (volume_subdivisions ** 3)

    @classmethod
    def empty(cls, samples: int = 1) -> "ShadowOccupancy":
        return cls(np.zeros((0, 3), np.int64), np.zeros(0), np.zeros(0), np.zeros(0, np.int64), samples)


#: Sub-cell samples projected at once (bounds the memory of the per-view arrays).
_CHUNK_SAMPLES = 1 << 20


def shadow_occupancy(views: list[View], shadows: ShadowVoxels, unit_scale: float,
                     config: ShadowCorrConfig) -> ShadowOccupancy:
    """Solid share of every shadow cell, from the views' depth images and masks.

    ``unit_scale`` converts the views' (bundle) units to the configuration's.  Views
    without depth or mask (point-segment bundles) rule nothing out; a bundle with none
    returns an empty occupancy (no volume can be measured).
    """
    n_sub = config.volume_subdivisions
    usable = [v for v in views if v.depth is not None and v.mask is not None and v.intrinsics is not None]
    if shadows.segment.size == 0 or not usable:
        return ShadowOccupancy.empty(n_sub ** 3)
    key, unpack = pack_cell_keys(np.zeros_like(shadows.segment), shadows.cell)
    cells_key, member_cell = unique_keys(key, return_inverse=True)
    cells = unpack(cells_key)[1]
    # the most confident member of each cell: members sorted by cell, then by falling confidence
    order = np.lexsort((-shadows.confidence, member_cell))
    first = order[np.r_[True, member_cell[order][1:] != member_cell[order][:-1]]]
    best_segment = shadows.segment[first]

    step = 1.0 / n_sub
    offsets = (np.stack(np.meshgrid(*[np.arange(n_sub)] * 3, indexing="ij"), axis=-1).reshape(-1, 3) + 0.5) * step - 0.5
    samples = offsets.shape[0]
    solid = np.zeros(cells.shape[0])
    single = np.zeros(cells.shape[0])
    per_chunk = max(1, _CHUNK_SAMPLES // samples)
    for lo in range(0, cells.shape[0], per_chunk):  # chunks of many thousand cells: bounded memory
        block = cells[lo:lo + per_chunk]
        centres = ((block[:, None, :] + offsets[None]) * (config.voxel_size / unit_scale)).reshape(-1, 3)
        empty, background = _ruled_out(usable, centres, config.max_depth / unit_scale)
        keep = ~empty & (background == 0)
        solid[lo:lo + per_chunk] = keep.reshape(-1, samples).mean(axis=1)
        single[lo:lo + per_chunk] = (~empty & (background == 1)).reshape(-1, samples).mean(axis=1)
    kept = solid > 0
    return ShadowOccupancy(cells[kept], solid[kept], single[kept], best_segment[kept], samples)


def _ruled_out(views: list[View], points: np.ndarray, max_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Per world point (bundle units): whether some view sees past it, and how many views see
    the background (mask 0) in front of it."""
    empty = np.zeros(points.shape[0], dtype=bool)
    background = np.zeros(points.shape[0], dtype=np.int32)
    for view in views:
        r, t = view.pose[:3, :3], view.pose[:3, 3]
        # camera coordinates = R^T (p - t), written out per axis (see stage 02's back_project)
        d = [points[:, i] - t[i] for i in range(3)]
        x, y, z = (r[0, j] * d[0] + r[1, j] * d[1] + r[2, j] * d[2] for j in range(3))
        k = view.intrinsics
        in_front = z > 0
        safe_z = np.where(in_front, z, 1.0)
        col = np.floor(k.fx * x / safe_z + k.cx)
        row = np.floor(k.fy * y / safe_z + k.cy)
        height, width = view.depth.shape
        inside = np.flatnonzero(in_front & (col >= 0) & (col < width) & (row >= 0) & (row < height))
        rows, cols = row[inside].astype(np.int64), col[inside].astype(np.int64)
        measured = np.asarray(view.depth[rows, cols], dtype=np.float64)
        valid = np.isfinite(measured) & (measured > 0) & (measured <= max_depth)
        depth_here = z[inside]
        unlabelled = view.mask[rows, cols] == 0
        # A hole in an object's depth (mask set, no valid depth) says nothing; on the background it is a ray
        # that met nothing in range.
        empty[inside] |= (valid & (measured > depth_here)) | (~valid & unlabelled)
        background[inside] += (valid & unlabelled & (measured < depth_here)).astype(np.int32)
    return empty, background
