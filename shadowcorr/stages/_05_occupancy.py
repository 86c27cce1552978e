"""Stage 5 (occupancy): shadow voxels -> the share of each voxel that is solid, seen from every view.

Shadows (stage 5) say where a segment's object may extend; the depth images say where
it cannot.  Every cell of the shared voxel grid that some shadow reaches is sampled at
``volume_subdivisions``\\ :sup:`3` sub-cell centres, and each sample is projected into every
view.  A sample is *empty* when a view sees past it (the view's depth at its pixel lies
beyond it, or is invalid on the background there: the ray met nothing), and *outside every
object* when a view sees the background (mask value 0) in front of it, such as the ground
hiding the part of a shadow that reaches below a rock's foot.  What no view rules out is
solid: the intersection of the shadows' reach with every view's free space, a visual hull
tightened by the measured depth.

Per cell the stage keeps the solid share, the share that only one view's background rules
out, the samples that are solid (stage 11 spans the oriented boxes over them), and the
segment whose shadow gives the cell the most confidence (the cell belongs to that
segment's object once objects are known, stage 11).  One view's background alone is weak
evidence: a mask drawn a few pixels inside the rock's outline (an eroding segmenter) or
missing in one view puts background in front of the rock there; on synthetic rock fields
with masks eroded by 3 px the rocks lost a fifth of their solid samples that way.  Stage 11
counts that share half, with half of it as uncertainty.  Samples are processed view by view
on flat arrays: the cost is cells x samples x views, with no loop over cells.  Nothing here
reads ground truth.
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
    solid: np.ndarray  # (U,) share of the cell's samples no view rules out
    single_view: np.ndarray  # (U,) share ruled out by one view's background alone (solid + single_view > 0)
    segment: np.ndarray  # (U,) segment whose shadow gives the cell the most confidence
    samples: int  # samples per cell (volume_subdivisions ** 3)
    solid_samples: np.ndarray | None = None  # (U, samples) bool: the cell's samples no view rules out
    offsets: np.ndarray | None = None  # (samples, 3) sample positions within a cell, in voxels from its centre

    @classmethod
    def empty(cls, samples: int = 1) -> "ShadowOccupancy":
        return cls(np.zeros((0, 3), np.int64), np.zeros(0), np.zeros(0), np.zeros(0, np.int64), samples,
                   np.zeros((0, samples), bool), sample_offsets(round(samples ** (1 / 3))))


def sample_offsets(subdivisions: int) -> np.ndarray:
    """The sub-cell centres of a cell split ``subdivisions`` times per edge, in voxels from the cell's centre."""
    step = 1.0 / subdivisions
    grid = np.stack(np.meshgrid(*[np.arange(subdivisions)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    return (grid + 0.5) * step - 0.5


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
    # the most confident member of each cell: members sorted by cell, then by falling confidence (one
    # argsort of cell + a fraction below one half that falls as the confidence rises)
    confidence = shadows.confidence / (2.0 * max(float(shadows.confidence.max()), 1e-300))
    order = np.argsort(member_cell - confidence)
    ordered_cell = member_cell[order]
    first = order[np.r_[True, ordered_cell[1:] != ordered_cell[:-1]]]
    best_segment = shadows.segment[first]

    offsets = sample_offsets(n_sub)
    samples = offsets.shape[0]
    scale = config.voxel_size / unit_scale
    solid = np.zeros((cells.shape[0], samples), dtype=bool)
    single = np.zeros((cells.shape[0], samples), dtype=bool)
    per_chunk = max(1, _CHUNK_SAMPLES // samples)
    for lo in range(0, cells.shape[0], per_chunk):  # chunks of many thousand cells: bounded memory
        block = cells[lo:lo + per_chunk]
        background = _background_counts(usable, block * scale, offsets * scale, config.max_depth / unit_scale)
        solid[lo:lo + per_chunk] = background == 0
        single[lo:lo + per_chunk] = background == 1
    share, single_share = solid.mean(axis=1), single.mean(axis=1)
    kept = (share > 0) | (single_share > 0)
    return ShadowOccupancy(cells[kept], share[kept], single_share[kept], best_segment[kept], samples,
                           solid[kept], offsets)


def _background_counts(views: list[View], centres: np.ndarray, offsets: np.ndarray, max_depth: float) -> np.ndarray:
    """(cells, samples) int8: how many views see the background (mask 0) in front of each sample, or -1 where
    some view sees past it (empty).  Sample ``j`` of cell ``i`` lies at ``centres[i] + offsets[j]`` (bundle units).

    Per view the cell centres are taken into the camera frame once and the samples' rotated
    offsets added by broadcasting; single precision (a sample's position to well under a
    pixel at any depth a bundle allows) halves the memory traffic.
    """
    n, samples = centres.shape[0], offsets.shape[0]
    empty = np.zeros((n, samples), dtype=bool)
    background = np.zeros((n, samples), dtype=np.int8)
    for view in views:
        r, t = view.pose[:3, :3], view.pose[:3, 3]
        # camera coordinates = R^T (p - t): of each cell centre once, plus the samples' rotated offsets
        cam_centre = ((centres - t) @ r).astype(np.float32)
        cam_offset = (offsets @ r).astype(np.float32)
        x, y, z = (cam_centre[:, None, i] + cam_offset[None, :, i] for i in range(3))
        k = view.intrinsics
        height, width = view.depth.shape
        in_front = z > 0
        safe_z = np.where(in_front, z, np.float32(1.0))
        col = np.floor(np.float32(k.fx) * x / safe_z + np.float32(k.cx))
        row = np.floor(np.float32(k.fy) * y / safe_z + np.float32(k.cy))
        inside = np.flatnonzero(in_front & (col >= 0) & (col < width) & (row >= 0) & (row < height))
        pixel = row.reshape(-1)[inside].astype(np.int64) * width + col.reshape(-1)[inside].astype(np.int64)
        measured = view.depth.reshape(-1)[pixel]
        valid = (measured > 0) & (measured <= max_depth)  # False for NaN and infinities too
        depth_here = z.reshape(-1)[inside]
        unlabelled = view.mask.reshape(-1)[pixel] == 0
        # A hole in an object's depth (mask set, no valid depth) says nothing; on the background it is a ray
        # that met nothing in range.
        empty.reshape(-1)[inside] |= (valid & (measured > depth_here)) | (~valid & unlabelled)
        background.reshape(-1)[inside] += valid & unlabelled & (measured < depth_here)
    background[empty] = -1
    return background
