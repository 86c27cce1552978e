"""Stage 3: segments -> cross-view surface evidence (where each segment lands in the other views).

A segment is a piece of surface seen from one view.  Projected into another view, each of
its points either cannot be checked there - outside the image, behind the camera, hidden
behind nearer surface, or on a pixel without valid depth - or it is *visible*: its depth along
that view's optical axis agrees with the view's own depth image within
``max(projection_depth_tolerance, projection_depth_tolerance_rel * depth)``.  A visible
point lands on the segment that covers its pixel there, or on no segment.

Where pose refinement could not bear out the declared pose of the segment's view or of the
view it is projected into (``unverified``, :func:`~shadowcorr.stages.unverified_poses`), the
relative tolerance is ``projection_depth_tolerance_unverified_rel`` instead: such a pose keeps
the error it was declared with, and a turn of the camera moves a point sideways in proportion
to its distance, and its depth along the other view's ray with it.  Rigs whose cameras share
too little surface to register (80 cm high over grazing ground, two opposite cameras) keep
their declared errors, and within the narrow tolerance those errors split rocks.

Counting the landings of a deterministic subsample of every segment's points gives, for every
segment ``a`` and view ``j`` (never a segment's own view):

* ``visible[a, j]`` - points of ``a`` visible in ``j``;
* ``on_mask[a, j]`` - of those, the points that land on some segment of ``j``;
* ``hits`` - for every pair ``(a, b)`` with ``b`` in ``j``, the points of ``a`` landing on ``b``
  (sparse and directed: only pairs with at least one landing exist).

"Not visible" is no evidence; "visible and on another segment" is evidence against; a
visible point on no segment (an eroded mask border, a mask the segmenter dropped) says
nothing about which object it belongs to.  Nothing here reads ground truth: a segment's
mask id is only used within its own view.

Cost: every segment is tested against every view's frustum with its bounding sphere
(``S x V`` cheap tests); only segments that may appear in a view are projected into it,
so a large field costs what its overlapping views cost, not ``points x views``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from ..bundle import SceneBundle, unit_scale
from ..config import ShadowCorrConfig
from ..ops import segment_max, thread_map, unique_keys
from ._02_segments import SegmentImage, Segments
from ._03_seams import Seams, smooth_seams


@dataclass
class SurfaceEvidence:
    """Landing counts of every segment's sample points in the other views (see the module docstring)."""

    samples: np.ndarray  # (S,) sample points drawn from each segment
    points: np.ndarray  # (sum(samples), 3) float32 the sample points, segment by segment (config units, world)
    visible: np.ndarray  # (S, V) int64 sample points of a visible in view j
    on_mask: np.ndarray  # (S, V) int64 visible points of a landing on some segment of view j
    hit_source: np.ndarray  # (H,) int64 segment a
    hit_target: np.ndarray  # (H,) int64 segment b (another view)
    hit_count: np.ndarray  # (H,) int64 points of a landing on b
    # Pairs of segments of one view that meet on one smooth surface (stage 03 seams).
    seams: Seams = field(default_factory=Seams.empty)

    @property
    def num_segments(self) -> int:
        return int(self.samples.shape[0])

    @classmethod
    def empty(cls, num_segments: int, num_views: int) -> "SurfaceEvidence":
        none = np.zeros(0, dtype=np.int64)
        grid = np.zeros((num_segments, num_views), dtype=np.int64)
        return cls(np.zeros(num_segments, np.int64), np.zeros((0, 3), np.float32), grid, grid.copy(), none, none,
                   none)


def sample_segment_points(points: np.ndarray, lengths: np.ndarray, per_segment: int) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``per_segment`` points of each segment, evenly spread over its (raster-ordered) points.

    Returns the indices into ``points`` (sorted by segment) and the number drawn per segment.
    Deterministic: the same segment always gives the same sample.
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    take = np.minimum(lengths, per_segment)
    seg = np.repeat(np.arange(lengths.size), take)
    local = np.arange(seg.size) - np.repeat(np.cumsum(take) - take, take)
    starts = np.cumsum(lengths) - lengths
    offset = ((2 * local + 1) * lengths[seg]) // (2 * np.maximum(take[seg], 1))
    return starts[seg] + offset, take


def _frustum_candidates(centre: np.ndarray, radius: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                        k, width: int, height: int) -> np.ndarray:
    """Segments whose bounding sphere may meet the view's frustum (camera-to-world pose, OpenCV)."""
    c = (centre - translation) @ rotation  # camera frame
    planes = np.array([
        [k.fx, 0.0, k.cx + 0.5],
        [-k.fx, 0.0, width - 0.5 - k.cx],
        [0.0, k.fy, k.cy + 0.5],
        [0.0, -k.fy, height - 0.5 - k.cy],
        [0.0, 0.0, 1.0],
    ])
    planes /= np.linalg.norm(planes, axis=1, keepdims=True)
    return np.all(c @ planes.T >= -radius[:, None], axis=1)


@functools.lru_cache(maxsize=8)
def _ring_offsets(radius: int) -> np.ndarray:
    """(K, 2) pixel offsets within ``radius`` (Euclidean), nearest first, the centre left out
    (cached: the same few radii for every view; read-only)."""
    r = np.arange(-radius, radius + 1)
    dy, dx = np.meshgrid(r, r, indexing="ij")
    d2 = (dy * dy + dx * dx).ravel()
    keep = (d2 > 0) & (d2 <= radius * radius)
    order = np.argsort(d2[keep], kind="stable")
    offsets = np.stack([dy.ravel()[keep][order], dx.ravel()[keep][order]], axis=1)
    offsets.flags.writeable = False
    return offsets


def _nearest_label(image: SegmentImage, row: np.ndarray, col: np.ndarray, target: np.ndarray, radius: int
                   ) -> np.ndarray:
    """Points on a pixel of no segment take the nearest segment within ``radius`` pixels, if any.

    A 2D segmenter's masks stop short of the object's outline (eroded masks): a point
    that lands just outside a mask, with depth that agrees, is on that object.
    """
    off = np.flatnonzero(target < 0)
    if off.size == 0:
        return target
    height, width = image.shape
    offsets = _ring_offsets(radius)
    rr = np.clip(row[off, None] + offsets[None, :, 0], 0, height - 1)
    cc = np.clip(col[off, None] + offsets[None, :, 1], 0, width - 1)
    near = image.at(rr, cc)
    found = near >= 0
    first = np.argmax(found, axis=1)
    hit = found[np.arange(off.size), first]
    out = target.copy()
    out[off[hit]] = near[hit, first[hit]]
    return out


def surface_evidence(bundle: SceneBundle, segments: Segments, config: ShadowCorrConfig,
                     unverified: np.ndarray | None = None) -> SurfaceEvidence:
    """Project every segment's sample points into every other view (see the module docstring).

    ``pixel_tolerance`` counts pixels of the camera's full image: on a downsampled view (a site
    map's stored view, :attr:`SegmentImage.pixel_scale` > 1) it spans fewer of the view's pixels.
    Where the segment image is finer than the view's depth (:attr:`SegmentImage.view_stride` > 1:
    a site map's stored view), points land in the segment image's pixels and read the depth of the
    depth pixel those lie in."""
    s, num_views = segments.num_segments, len(bundle.views)
    if segments.pixel_segment is None or s == 0:
        return SurfaceEvidence.empty(s, num_views)
    scale = unit_scale(bundle.units, config.units)
    index, samples = sample_segment_points(segments.points, segments.lengths, config.projection_samples)
    # The sample as three coordinate columns: gathers, masks and the rotation below run on
    # contiguous 1-D arrays, several times faster than on (N, 3) rows.
    xyz = [segments.points[index, i] for i in range(3)]
    seg = np.repeat(np.arange(s), samples)
    first = np.cumsum(samples) - samples

    # Bounding sphere of each segment's sample, for the frustum test.
    safe = np.maximum(samples, 1)
    centre = np.stack([np.bincount(seg, weights=c, minlength=s) / safe for c in xyz], axis=1)
    radius = segment_max(np.sqrt(sum((c - np.repeat(centre[:, i], samples)) ** 2 for i, c in enumerate(xyz))), seg, s)

    # Per segment: whether its own view's pose stands unverified (None: every pose verified or none judged).
    from_unverified = unverified[segments.view] if unverified is not None and unverified.any() else None
    wide = max(config.projection_depth_tolerance_rel, config.projection_depth_tolerance_unverified_rel)

    def land(j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """Visible and on-mask counts of every segment in view j, and the (a, b) landing pairs."""
        view, image = bundle.views[j], segments.pixel_segment[j]
        if image is None or view.depth is None:
            return None
        k = view.intrinsics
        height, width = image.shape
        d = image.view_stride
        if d > 1:  # the segment image is finer than the depth: land in the segment image's pixels
            k = k.model_copy(update={"fx": k.fx * d, "fy": k.fy * d, "cx": k.cx * d + d // 2,
                                     "cy": k.cy * d + d // 2, "width": width, "height": height})
        rotation, translation = view.pose[:3, :3], view.pose[:3, 3] * scale
        cand = _frustum_candidates(centre, radius, rotation, translation, k, width, height)
        cand &= (segments.view != j) & (samples > 0)
        cs = np.flatnonzero(cand)
        if cs.size == 0:
            return None
        take = samples[cs]
        rows = np.repeat(first[cs], take) + (np.arange(take.sum()) - np.repeat(np.cumsum(take) - take, take))
        # World -> camera: cam_i = sum_j (p_j - t_j) R_ji, column by column.
        rel = [c[rows] - translation[i] for i, c in enumerate(xyz)]
        x, y, z = (rel[0] * rotation[0, i] + rel[1] * rotation[1, i] + rel[2] * rotation[2, i] for i in range(3))
        # Pixel of every point (meaningless behind the camera, where z <= 0), then one selection of
        # the points in front of the camera and inside the frame.
        with np.errstate(divide="ignore", invalid="ignore"):
            col_f = np.rint(k.fx * x / z + k.cx)
            row_f = np.rint(k.fy * y / z + k.cy)
        inside = np.flatnonzero((z > 1e-9) & (col_f >= 0) & (col_f < width) & (row_f >= 0) & (row_f < height))
        rows, z = rows[inside], z[inside]
        col, row = col_f[inside].astype(np.int64), row_f[inside].astype(np.int64)
        if d > 1:  # the depth pixel each landing pixel lies in
            depth_h, depth_w = view.depth.shape
            at = np.minimum(row // d, depth_h - 1) * depth_w + np.minimum(col // d, depth_w - 1)
        else:
            at = row * width + col
        depth = view.depth.ravel()[at].astype(np.float64) * scale  # flat: 2x a 2-D gather
        rel = config.projection_depth_tolerance_rel
        if from_unverified is not None:  # all wide into an unverified view, else per segment's own view
            rel = wide if unverified[j] else np.where(from_unverified[seg[rows]], wide, rel)
        tolerance = np.maximum(config.projection_depth_tolerance, rel * z)
        agree = np.flatnonzero(np.isfinite(depth) & (depth > 0) & (np.abs(depth - z) <= tolerance))
        rows, row, col = rows[agree], row[agree], col[agree]
        src = seg[rows]
        target = image.at(row, col)
        if config.pixel_tolerance > 0:
            tolerance_px = config.pixel_tolerance if image.pixel_scale == 1 else max(
                1, int(round(config.pixel_tolerance / image.pixel_scale)))
            target = _nearest_label(image, row, col, target, tolerance_px)
        landed = target >= 0
        key, count = unique_keys(src[landed] * s + target[landed], return_counts=True)
        return np.bincount(src, minlength=s), np.bincount(src[landed], minlength=s), key, count

    # Views are independent: num_threads of them at once.
    landings = thread_map(land, range(num_views), config.num_threads)
    visible = np.zeros((s, num_views), dtype=np.int64)
    on_mask = np.zeros((s, num_views), dtype=np.int64)
    keys, counts = [], []
    for j, found in enumerate(landings):
        if found is not None:
            visible[:, j], on_mask[:, j], key, count = found
            keys.append(key)
            counts.append(count)

    key = np.concatenate(keys) if keys else np.zeros(0, np.int64)
    count = np.concatenate(counts) if counts else np.zeros(0, np.int64)
    # A pair (a, b) appears in one view only (b's own view), so keys never repeat.
    points = np.stack(xyz, axis=1).astype(np.float32)
    return SurfaceEvidence(samples, points, visible, on_mask, key // s, key % s, count.astype(np.int64),
                           smooth_seams(bundle, segments, config))
