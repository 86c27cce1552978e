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
counts that share half, with half of it as uncertainty; and a background pixel within
``volume_mask_margin`` (3) pixels of a labelled one rules nothing out (with masks eroded by
3 px the field's volumes came out a fifth short, 0.80 of the mesh volume at the median,
and 0.91 with the margin).

Depth noise carves too: a sample just inside a surface is "seen past" wherever the noise
at its pixel reaches behind it, and with every view doing so a layer of about a noise sigma
goes from each seen surface (with 1 % noise at 7.5 m, sigma = a z^2, the volumes came out
0.86 of the mesh volume at the median).  Each view's noise is measured on the image itself
(:func:`shadowcorr.ops.relative_depth_noise`); where it reaches a tenth of a sample's spacing,
the depth a sample near the surface is compared with is the mean of the 3 x 3 pixels two
apart around its pixel that carry the same mask value and lie within three sigmas of it:
a third of the noise, and 1.00 of the mesh volume at the median.  Clean depth images are
read as before.  Samples are processed view by view
on flat arrays: the cost is cells x samples x views, with no loop over cells.  Nothing here
reads ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..bundle import View
from ..config import ShadowCorrConfig
from ..ops import NOISE_ROW_STEP, pack_cell_keys, relative_depth_noise, unique_keys
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
    # Every (cell, segment) pair of the shadows over these cells: which segments' shadows reach each cell.
    member_cell: np.ndarray | None = None  # (M,) int64 index into cell
    member_segment: np.ndarray | None = None  # (M,) int64

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
                     config: ShadowCorrConfig, depth_noise: np.ndarray | None = None) -> ShadowOccupancy:
    """Solid share of every shadow cell, from the views' depth images and masks.

    ``unit_scale`` converts the views' (bundle) units to the configuration's.  Views
    without depth or mask (point-segment bundles) rule nothing out; a bundle with none
    returns an empty occupancy (no volume can be measured).  ``depth_noise`` is each view's
    relative depth noise as stage 02 measured it (``Segments.depth_noise``; measured here when None).
    """
    n_sub = config.volume_subdivisions
    kept = [k for k, v in enumerate(views) if v.depth is not None and v.mask is not None and v.intrinsics is not None]
    usable = [views[k] for k in kept]
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
    # Each view's depth noise (sigma = a z^2, measured on every 16th row: well within a percent of
    # the full image's figure); depth images whose noise stays below a tenth of a sample's spacing
    # everywhere are read as they are.
    noise = (np.asarray(depth_noise, dtype=np.float64)[kept] if depth_noise is not None
             else np.array([relative_depth_noise(v.depth[::NOISE_ROW_STEP]) for v in usable]))
    reach = config.max_depth / unit_scale
    smoothed = noise * reach * reach > _SMOOTH_ABOVE * scale / n_sub
    solid = np.zeros((cells.shape[0], samples), dtype=bool)
    single = np.zeros((cells.shape[0], samples), dtype=bool)
    per_chunk = max(1, _CHUNK_SAMPLES // samples)
    for lo in range(0, cells.shape[0], per_chunk):  # chunks of many thousand cells: bounded memory
        block = cells[lo:lo + per_chunk]
        background = _background_counts(
            usable, block * scale, offsets * scale, reach, noise, smoothed, config.volume_mask_margin)
        solid[lo:lo + per_chunk] = background == 0
        single[lo:lo + per_chunk] = background == 1
    share, single_share = solid.mean(axis=1), single.mean(axis=1)
    kept = (share > 0) | (single_share > 0)
    renumbered = np.cumsum(kept) - 1
    member = kept[member_cell]
    return ShadowOccupancy(cells[kept], share[kept], single_share[kept], best_segment[kept], samples,
                           solid[kept], offsets, renumbered[member_cell[member]], shadows.segment[member])


#: A view's depth is smoothed where its noise at the largest depth exceeds this share of a sample's spacing.
_SMOOTH_ABOVE = 0.1
#: Smoothing averages the depth at the pixels this far apart around a sample's pixel (3 x 3 of them).
_SMOOTH_STEP = 2
#: Neighbours whose depth differs from the sample's pixel's by more than this many noise sigmas lie across
#: a depth edge and are left out of the average.
_SMOOTH_BAND = 3.0


def _background_counts(views: list[View], centres: np.ndarray, offsets: np.ndarray, max_depth: float,
                       noise: np.ndarray, smoothed: np.ndarray, mask_margin: int) -> np.ndarray:
    """(cells, samples) int8: how many views see the background (mask 0) in front of each sample, or -1 where
    some view sees past it (empty).  Sample ``j`` of cell ``i`` lies at ``centres[i] + offsets[j]`` (bundle units).

    Per view the cell centres are taken into the camera frame once and the samples' rotated
    offsets added by broadcasting; single precision (a sample's position to well under a
    pixel at any depth a bundle allows) halves the memory traffic.  ``noise`` is each view's
    relative depth noise (``sigma = a z^2``); where ``smoothed``, the depth a sample is
    compared with is averaged over the 3 x 3 pixels ``_SMOOTH_STEP`` apart around its pixel
    that carry the same mask value and lie within ``_SMOOTH_BAND`` sigmas of it, for the
    samples within reach of that noise of the surface (the others' test cannot flip).  A
    background pixel within ``mask_margin`` pixels of a labelled one says nothing: a mask
    drawn inside the object's outline leaves such pixels on the object.
    """
    n, samples = centres.shape[0], offsets.shape[0]
    empty = np.zeros((n, samples), dtype=bool)
    background = np.zeros((n, samples), dtype=np.int8)
    for view, a, smooth in zip(views, noise, smoothed):
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
        rows, cols = row.reshape(-1)[inside].astype(np.int64), col.reshape(-1)[inside].astype(np.int64)
        pixel = rows * width + cols
        depth, mask = view.depth.reshape(-1), view.mask.reshape(-1)
        measured = depth[pixel]
        valid = (measured > 0) & (measured <= max_depth)  # False for NaN and infinities too
        depth_here = z.reshape(-1)[inside]
        label = mask[pixel]
        if smooth:
            measured = _smoothed(depth, mask, width, height, rows, cols, measured, valid, depth_here, label, a,
                                 max_depth)
        unlabelled = label == 0
        # A hole in an object's depth (mask set, no valid depth) says nothing; on the background it is a ray
        # that met nothing in range.
        empty.reshape(-1)[inside] |= (valid & (measured > depth_here)) | (~valid & unlabelled)
        behind = np.flatnonzero(valid & unlabelled & (measured < depth_here))
        if mask_margin > 0 and behind.size:
            behind = behind[~_near_label(mask, width, height, rows[behind], cols[behind], mask_margin)]
        background.reshape(-1)[inside[behind]] += 1
    background[empty] = -1
    return background


def _smoothed(depth: np.ndarray, mask: np.ndarray, width: int, height: int, rows: np.ndarray, cols: np.ndarray,
              measured: np.ndarray, valid: np.ndarray, depth_here: np.ndarray, label: np.ndarray, a: float,
              max_depth: float) -> np.ndarray:
    """``measured`` with the depth averaged around the pixels whose test the noise could flip (see
    :func:`_background_counts`)."""
    band = _SMOOTH_BAND * a * measured * measured  # float32, like the depth
    near = np.flatnonzero(valid & (np.abs(measured - depth_here) <= 2.0 * band))
    if near.size == 0:
        return measured
    m, lab, b = measured[near].astype(np.float64), label[near], band[near]
    r, c = rows[near], cols[near]
    total, count = m.copy(), np.ones(near.size)
    for dy in (-_SMOOTH_STEP, 0, _SMOOTH_STEP):
        for dx in (-_SMOOTH_STEP, 0, _SMOOTH_STEP):
            if dy == 0 and dx == 0:
                continue
            other = np.clip(r + dy, 0, height - 1) * width + np.clip(c + dx, 0, width - 1)
            d = depth[other].astype(np.float64)
            ok = (d > 0) & (d <= max_depth) & (mask[other] == lab) & (np.abs(d - m) <= b)
            total += np.where(ok, d, 0.0)
            count += ok
    out = measured.copy()
    out[near] = total / count
    return out


def _near_label(mask: np.ndarray, width: int, height: int, rows: np.ndarray, cols: np.ndarray,
                margin: int) -> np.ndarray:
    """Whether a labelled pixel lies ``margin`` pixels from each pixel along a row, a column or a diagonal
    (``margin / sqrt 2`` along each axis)."""
    d = max(1, int(round(margin / np.sqrt(2.0))))
    near = np.zeros(rows.size, dtype=bool)
    for dy, dx in ((0, margin), (0, -margin), (margin, 0), (-margin, 0), (d, d), (d, -d), (-d, d), (-d, -d)):
        other = np.clip(rows + dy, 0, height - 1) * width + np.clip(cols + dx, 0, width - 1)
        near |= mask[other] != 0
    return near
