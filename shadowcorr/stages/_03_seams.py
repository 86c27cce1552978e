"""Stage 3 (beside the surface evidence): which neighbouring segments of one view meet on one smooth surface.

A 2D segmenter that cuts one rock in two draws the cut across a continuous surface: on
either side of the cut the depth goes on as if there were no cut.  Two different rocks
meet in the image along an occlusion contour, where the nearer rock's silhouette hides the
farther one and the depth jumps.  Where other views see a cut rock whole, its halves land
together on one segment there (``split_mask_ids``); this is the evidence that needs no
other view at all, which is what a rock seen by one view only, or seen elsewhere under a
merged mask, has.

For every pixel on the border of a segment, the image is walked away from it along the
rows and the columns across at most ``fusion_seam_gap`` unlabelled pixels (eroded masks
leave such a gap between neighbours).  Where the walk reaches another segment, the pair is
sampled: with ``p`` and ``q`` the pixels :data:`INSET` inside either side (a depth sensor
mixes the two surfaces on the contour pixel itself), ``d`` the pixels between them and the
depth slope of each side read over :data:`SLOPE_PIXELS` pixels further in, the step
``z_q - z_p - slope * d`` (the depth the surface does not explain), relative to ``z_p``.  A
pair's seam is *smooth* when it has at least ``fusion_seam_min_pixels`` samples and the
median step (signed: noise cancels, an occlusion's jump does not) is within
``fusion_seam_tolerance`` of zero.

In noisy depth a short seam between two rocks passes that test by chance.  So the median is
also required to be sure enough: its standard error, ``1.25 * 2 a z / sqrt(n)`` for ``n``
samples at the seam's median depth ``z`` (each step spans about two noise widths; ``a z`` is
the view's relative depth noise, ``a`` estimated from the depth image itself,
:func:`shadowcorr.ops.relative_depth_noise`), times ``fusion_seam_noise`` must be within the
tolerance too.  In clean depth every seam of ``fusion_seam_min_pixels`` counts; at 1 % noise
at 7.5 m a seam needs about 60 samples, at 2 % about 250.

What the step cannot tell apart: two rocks that touch along a contour with continuous depth
(side by side at one distance, the contact facing the camera).  Such a pair is a
*candidate* only: the grouping reads it as one mask id for its per-view constraints (as the
blobs of one mask), and the surface and volumetric evidence still decide whether the two
join.  Mask ids are only compared within their own view; nothing here reads ground truth.

Cost: the walks start from border pixels only (a few per cent of the mask) and take
``2 * (fusion_seam_gap + 1)`` vectorised steps per view, fewer walkers each step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..bundle import SceneBundle
from ..config import ShadowCorrConfig
from ..ops import relative_depth_noise, thread_map
from ._02_segments import SegmentImage, Segments

#: Pixels over which each side's depth slope across the seam is read.
SLOPE_PIXELS = 3
#: Pixels inside each side where its depth is read (not the contour pixel itself).
INSET = 1
#: Walk directions (row step, column step): along the rows and the columns (a straight cut at
#: any angle crosses one of them; the diagonals only add samples, at twice the cost).
DIRECTIONS = ((0, 1), (1, 0))


@dataclass
class Seams:
    """Pairs of segments of one view (``first < second``) whose shared border is one smooth
    surface, with the measured median step and its allowed bound (both relative to depth)."""

    first: np.ndarray  # (K,) int64 segment index
    second: np.ndarray  # (K,) int64 segment index, same view as first
    samples: np.ndarray  # (K,) int64 pixel pairs sampled along the seam
    step: np.ndarray  # (K,) float64 median relative depth step across the seam (signed)
    uncertainty: np.ndarray  # (K,) float64 its standard error under the view's estimated depth noise

    @classmethod
    def empty(cls) -> "Seams":
        none = np.zeros(0, dtype=np.int64)
        return cls(none, none.copy(), none.copy(), np.zeros(0), np.zeros(0))


def smooth_seams(bundle: SceneBundle, segments: Segments, config: ShadowCorrConfig) -> Seams:
    """The smooth seams of every view (see the module docstring); views run on ``num_threads``."""
    if config.fusion_seam_gap == 0 or segments.pixel_segment is None or segments.num_segments == 0:
        return Seams.empty()

    def view_seams(j: int) -> Seams:
        image, depth = segments.pixel_segment[j], bundle.views[j].depth
        if image is None or depth is None:
            return Seams.empty()
        return _view_seams(image, depth, config)

    found = thread_map(view_seams, range(len(bundle.views)), config.num_threads)
    return Seams(*(np.concatenate([getattr(f, name) for f in found]) for name in
                   ("first", "second", "samples", "step", "uncertainty")))


def _view_seams(image: SegmentImage, depth: np.ndarray, config: ShadowCorrConfig) -> Seams:
    labels = np.asarray(image.window)
    if labels.size == 0:
        return Seams.empty()
    h, w = labels.shape
    d = image.view_stride
    if d > 1:  # depth coarser than the labels (a site map's stored view): each pixel reads the depth pixel it lies in
        rows = np.minimum((image.top + np.arange(h)) // d, depth.shape[0] - 1)
        cols = np.minimum((image.left + np.arange(w)) // d, depth.shape[1] - 1)
        z = np.asarray(depth)[np.ix_(rows, cols)]
    else:
        z = depth[image.top:image.top + h, image.left:image.left + w]  # a view: read only where sampled
    a_parts, b_parts, step_parts, z_parts = [], [], [], []
    for dy, dx in DIRECTIONS:
        found = _walk(labels, z, dy, dx, config.fusion_seam_gap)
        if found is not None:
            for part, value in zip((a_parts, b_parts, step_parts, z_parts), found):
                part.append(value)
    if not a_parts:
        return Seams.empty()
    a, b, step, zp = (np.concatenate(p) for p in (a_parts, b_parts, step_parts, z_parts))
    # One orientation per pair: the step is measured from the smaller index to the larger.
    flip = a > b
    a, b = np.where(flip, b, a), np.where(flip, a, b)
    step = np.where(flip, -step, step)
    span = int(labels.max()) + 1
    key = a * span + b
    by_step, by_depth = np.lexsort((step, key)), np.lexsort((zp, key))  # the same runs, sorted two ways
    key, step, zp = key[by_step], step[by_step], zp[by_depth]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    counts = np.diff(np.r_[starts, key.size])
    keep = counts >= config.fusion_seam_min_pixels
    starts, counts = starts[keep], counts[keep]
    if starts.size == 0:
        return Seams.empty()
    # Median of each run: the steps are sorted within their key.
    lower, upper = starts + (counts - 1) // 2, starts + counts // 2
    median_step = 0.5 * (step[lower] + step[upper])
    median_depth = 0.5 * (zp[lower] + zp[upper])
    smooth = np.abs(median_step) <= config.fusion_seam_tolerance
    uncertainty = np.zeros(starts.size)
    if config.fusion_seam_noise > 0 and smooth.any():
        # The median of n steps, each about 2 sigma of depth noise wide, is uncertain by
        # 1.25 * 2 sigma / sqrt(n) (sigma = a z, relative): in noisy depth a short seam between
        # two rocks passes for smooth by chance, so a seam counts only where that uncertainty
        # is within the tolerance.  Every fourth row is plenty for the view's noise figure.
        noise = relative_depth_noise(z[::2])
        uncertainty = 2.5 * noise * median_depth / np.sqrt(counts)
        smooth &= config.fusion_seam_noise * uncertainty <= config.fusion_seam_tolerance
    k = key[starts][smooth]
    return Seams(k // span, k % span, counts[smooth].astype(np.int64), median_step[smooth], uncertainty[smooth])


def _walk(labels: np.ndarray, z: np.ndarray, dy: int, dx: int, gap: int
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Seam samples found walking from border pixels along ``(dy, dx)``: (first segment, second
    segment, relative depth step, depth at the start)."""
    h, w = labels.shape
    # Border pixels: labelled, and the next pixel along the direction is not the same segment
    # (compared on two shifted views of the image: no index arrays for the whole window).
    # DIRECTIONS step down (dy >= 0) and either way along the row.
    here = labels[:h - dy, max(0, -dx):w - max(0, dx)]
    ahead = labels[dy:, max(0, dx):w - max(0, -dx)]
    border = (here >= 0) & (here != ahead)
    rows, cols = np.divmod(np.flatnonzero(border), border.shape[1])  # ten times faster than a 2D np.nonzero
    cols = cols + max(0, -dx)
    flat_labels = np.ascontiguousarray(labels).reshape(-1)
    start = rows * w + cols
    own = flat_labels.take(start).astype(np.int64)
    # Steps each border pixel can take before it leaves the window along the direction.
    room = np.full(rows.size, gap + 1, dtype=np.int64)
    for offset, position, size in ((dy, rows, h), (dx, cols, w)):
        if offset:
            room = np.minimum(room, (size - 1 - position) if offset > 0 else position)
    # Walk all border pixels in step (on flat pixel indices); the ones that reach a segment (or the
    # window's edge) drop out.
    walkers = np.arange(rows.size)
    found_at, found_other, found_d = [], [], []
    for d in range(1, gap + 2):  # up to `gap` unlabelled pixels, then the other segment
        walkers = walkers[room.take(walkers) >= d]
        value = flat_labels.take(start.take(walkers) + d * (dy * w + dx))
        reached = value >= 0
        other = reached & (value != own.take(walkers))  # the own segment again: a concave border, no seam
        found_at.append(walkers[other])
        found_other.append(value[other])
        found_d.append(np.full(int(other.sum()), d))
        walkers = walkers[~reached]
        if walkers.size == 0:
            break
    hit = np.concatenate(found_at)
    if hit.size == 0:
        return None
    rows, cols, a = rows[hit], cols[hit], own[hit]
    b, d = np.concatenate(found_other).astype(np.int64), np.concatenate(found_d)
    # The depth is read INSET pixels inside each side (a depth sensor mixes the two surfaces on
    # the contour pixel itself), and each side's slope SLOPE_PIXELS further in.
    rows, cols, d = rows - INSET * dy, cols - INSET * dx, d + 2 * INSET
    ra, ca = rows - SLOPE_PIXELS * dy, cols - SLOPE_PIXELS * dx
    rq, cq = rows + d * dy, cols + d * dx
    rb, cb = rq + SLOPE_PIXELS * dy, cq + SLOPE_PIXELS * dx
    ok = np.flatnonzero((ra >= 0) & (ra < h) & (ca >= 0) & (ca < w) & (rb >= 0) & (rb < h) & (cb >= 0) & (cb < w))
    a, b, d = a[ok], b[ok], d[ok]
    p, q, pa, qb = (r[ok] * w + c[ok] for r, c in ((rows, cols), (rq, cq), (ra, ca), (rb, cb)))
    same = ((flat_labels.take(pa) == a) & (flat_labels.take(qb) == b)
            & (flat_labels.take(p) == a) & (flat_labels.take(q) == b))
    a, b, d, p, q, pa, qb = a[same], b[same], d[same], p[same], q[same], pa[same], qb[same]
    # z is a window of the frame's depth (not contiguous): read by (row, column)
    zp, zq, za, zb = (z[np.divmod(pixel, w)].astype(np.float64) for pixel in (p, q, pa, qb))
    # Holes (no depth: 0, NaN or infinite) on any of the four pixels leave no step.
    good = np.flatnonzero((zp > 0) & (zq > 0) & (za > 0) & (zb > 0) & np.isfinite(zp + zq + za + zb))
    a, b, d, zp, zq, za, zb = a[good], b[good], d[good], zp[good], zq[good], za[good], zb[good]
    slope = 0.5 * ((zp - za) + (zb - zq)) / SLOPE_PIXELS
    step = (zq - zp - slope * d) / zp
    return a, b, step, zp
