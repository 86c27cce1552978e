"""Stage 5: segment shells -> per-segment confidence-weighted shadow voxels (SPEC §2 steps 4-6).

A segment is only the visible shell of an object (stage 4 cleans it up).  Behind that shell lies the
object's interior, so every segment "casts a shadow": its points are pushed in
layers along the viewing direction, deeper near the middle of the silhouette and
not at all at its rim (silhouette-aware erosion), for a depth proportional to the
segment's second error-ellipsoid axis.  The surface and layer points are voxelised,
and each voxel gets a confidence that rises from the surface, peaks at about 30% of
the shadow's depth and falls off towards its far end (a Beta(1.41, 1.94) profile of the
distance to the segment's surface points; ``fused`` measures it to those points averaged per
half voxel, see ``ShadowCorrConfig.surface_distance_cell``).
Segments of one object - even ones that share no visible surface - end up
overlapping inside the object; that overlap is the signal the rest of the pipeline
reads.

All steps run on the ragged batch of all segments at once; grouping is done with
packed integer keys and sorting, and nearest neighbours within a segment are found
with one k-d tree in which segments are moved far apart (``ops.separated``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree

from ..config import ShadowCorrConfig
from ..ops import (pack_cell_keys, resolve_threads, segment_chunks, segment_max, segment_range, separated,
                   separation_gap, thread_map, unique_keys)
from ._02_segments import Segments
from ._04_shells import SegmentShells, voxel_downsample


@dataclass
class ShadowVoxels:
    """Per (segment, voxel) pairs with confidence (steps 5-6), sorted by segment."""

    segment: np.ndarray  # (M,)
    cell: np.ndarray  # (M, 3) int64 voxel index (centre = cell * voxel_size)
    confidence: np.ndarray  # (M,) phi in (min_confidence, 1]

    @classmethod
    def empty(cls) -> "ShadowVoxels":
        return cls(np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros(0))


def cast_shadows(segments: Segments, shells: SegmentShells, config: ShadowCorrConfig) -> ShadowVoxels:
    """Steps 4-6: silhouette-aware erosion layers, voxelisation, confidence per voxel."""
    s = segments.num_segments
    pts, seg, v = shells.points, shells.segment, config.voxel_size
    if pts.shape[0] == 0:
        return ShadowVoxels.empty()
    direction, count = shells.direction, shells.count

    # In-plane principal axes: any orthonormal pair (e1, e2) orthogonal to the direction,
    # rotated onto the eigenvectors of the projected 2x2 covariance.  Per-segment values reach
    # the points by ``np.repeat`` over the sorted runs and coordinates go column by column:
    # several times faster than gathers and einsum on (P, 3) rows.
    ref = np.eye(3)[np.argmin(np.abs(direction), axis=1)]
    e1 = np.cross(direction, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(direction, e1)
    centred = [pts[:, i] - np.repeat(shells.mean[:, i], count) for i in range(3)]
    p1, p2 = (sum(centred[i] * np.repeat(e[:, i], count) for i in range(3)) for e in (e1, e2))
    c11 = np.bincount(seg, weights=p1 * p1, minlength=s)
    c12 = np.bincount(seg, weights=p1 * p2, minlength=s)
    c22 = np.bincount(seg, weights=p2 * p2, minlength=s)
    angle = 0.5 * np.arctan2(2 * c12, c11 - c22)  # rotation onto the principal axes
    cos_a, sin_a = np.repeat(np.cos(angle), count), np.repeat(np.sin(angle), count)
    xi = cos_a * p1 + sin_a * p2
    eta = -sin_a * p1 + cos_a * p2

    # (u0, v0) is the projection of the mean, i.e. (0, 0) here; w, h the bounding box.
    half_w = np.repeat(np.maximum(segment_range(xi, seg, s), 1e-9) / 2, count)
    half_h = np.repeat(np.maximum(segment_range(eta, seg, s), 1e-9) / 2, count)
    rho = np.sqrt((xi / half_w) ** 2 + (eta / half_h) ** 2)
    d_surf = config.projection_factor * shells.axis_lengths[:, 1]
    n_max = np.maximum(np.floor(d_surf / v), 1).astype(np.int64)
    layers = np.where(rho < 1, np.floor(np.repeat(n_max, count) * (1 - rho)), 0).astype(np.int64)

    # Surface points (layer 0) plus layers 1..n of each point, voxelised and weighed chunk by
    # chunk (``num_threads`` chunks at once).
    reps = layers + 1
    threads = resolve_threads(config.num_threads)

    # One separation for the whole scene (voxel centres lie within a shadow's depth plus a voxel
    # of their points), so that every distance is the same to the last bit however it is chunked.
    gap = separation_gap(pts) + 8.0 * (max(float(d_surf.max()), v) + v)

    def shadow(bounds: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lo, hi = bounds
        vox_seg, vox_cell = _voxelise_layers(pts[lo:hi], seg[lo:hi], reps[lo:hi], direction, v,
                                             config.chebyshev_fraction)
        phi = _confidence(pts[lo:hi], seg[lo:hi], vox_seg, vox_cell, v, gap, s, config)
        keep = phi > config.min_confidence
        return vox_seg[keep], vox_cell[keep], phi[keep]

    parts = thread_map(shadow, segment_chunks(seg, _CHUNK_LAYER_POINTS, weight=reps, min_chunks=threads), threads)
    return ShadowVoxels(*(np.concatenate([p[i] for p in parts]) for i in range(3)))


def _confidence(pts: np.ndarray, seg: np.ndarray, vox_seg: np.ndarray, vox_cell: np.ndarray, v: float, gap: float,
                num_segments: int, config: ShadowCorrConfig) -> np.ndarray:
    """Step 6: the Beta profile of each voxel centre's distance to its segment's nearest surface
    point, relative to the segment's farthest voxel.  With ``config.distance_cell`` > 0 the surface
    points are first averaged per cell of that size: the tree holds a few times fewer points (a
    third on the sample scene at half a voxel) and a distance changes by at most the cell's diagonal."""
    centres = vox_cell * v
    if config.distance_cell > 0:
        pts, seg = voxel_downsample(pts, seg, config.distance_cell)
    # Leaves of 32: queries from deep inside a shadow visit many leaves (21 vs 24 ms at 16).
    dist, _ = KDTree(separated(pts, seg, gap), leafsize=32).query(separated(centres, vox_seg, gap), k=1)
    max_d = segment_max(dist, vox_seg, num_segments)
    d_hat = dist / (config.distance_margin * np.maximum(max_d[vox_seg], 1e-12))
    return beta_profile(d_hat, config.beta_alpha, config.beta_beta)


#: Layer points expanded at once (whole segments per chunk): the expansion holds about 80 bytes
#: per layer point, so a large field's shadows are voxelised in bounded memory.  Chunks hold
#: whole segments, so their voxels never collide and concatenate in (segment, cell) order; with
#: ``num_threads`` > 1 chunks are also made small enough for every thread to get one.
_CHUNK_LAYER_POINTS = 1 << 20


def _voxelise_layers(pts: np.ndarray, seg: np.ndarray, reps: np.ndarray, direction: np.ndarray, v: float,
                     chebyshev_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Unique (segment, cell) pairs filled by the surface points (layer 0) and their layers.

    Layer L = 1..reps-1 of a point lies L*v along its segment's direction, in voxel units (one
    layer = one voxel along the direction).  Each point fills the voxel it rounds to if it
    lies within ``chebyshev_fraction`` of its centre on every axis.  Axis by axis on flat
    arrays: about twice as fast as on (N, 3) blocks.
    """
    # Points come sorted by segment, so per-point and per-segment values reach the layer points
    # by ``np.repeat`` (about twice as fast as gathers through a layer -> point index).
    seg_reps = np.bincount(seg, weights=reps, minlength=direction.shape[0]).astype(np.int64)
    level = np.arange(int(reps.sum())) - np.repeat(np.cumsum(reps) - reps, reps)
    inside = np.ones(level.size, dtype=bool)
    cell_axes = []
    for axis in range(3):
        coord = np.repeat(pts[:, axis] / v, reps)
        coord += level * np.repeat(direction[:, axis], seg_reps)
        nearest = np.rint(coord)
        coord -= nearest
        inside &= np.abs(coord, out=coord) <= chebyshev_fraction
        cell_axes.append(nearest)
    all_seg = np.repeat(np.arange(seg_reps.size), seg_reps)
    kept = np.flatnonzero(inside)  # one index for four gathers: cheaper than four boolean selections
    key, unpack = pack_cell_keys(all_seg.take(kept), [c.take(kept).astype(np.int64) for c in cell_axes])
    return unpack(unique_keys(key))


def beta_profile(x: np.ndarray, alpha: float, beta: float) -> np.ndarray:
    """Beta(alpha, beta) density scaled so that its maximum, at the mode, is 1."""
    mode = (alpha - 1) / (alpha + beta - 2)
    x = np.clip(x, 0.0, 1.0)
    log_ratio = (alpha - 1) * (np.log(np.maximum(x, 1e-300)) - np.log(mode)) + (beta - 1) * (
        np.log(np.maximum(1 - x, 1e-300)) - np.log(1 - mode)
    )
    return np.where((x > 0) & (x < 1), np.exp(log_ratio), 0.0)
