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
leave such a gap between neighbours: 3 px of erosion on either side of a cut leave 6-9 px
across it, and a walk crosses a slanted cut at up to 1.4 times that).  Where the walk
reaches another segment, the pair is sampled: on each side up to :data:`SIDE_PIXELS`
pixels along the walk are read, from :data:`INSET` inside (a depth sensor mixes the two
surfaces on the contour pixel itself) as far as the side's segment and valid depth go, and
one line with a common slope and an intercept per side is fitted to both (least squares).
The step is the depth the line's slope does not explain between the two sides' centroids,
relative to the first side's depth.  A pair's seam is *smooth* when it has at least
``fusion_seam_min_pixels`` samples and the median step (signed: noise cancels, an
occlusion's jump does not) is within ``fusion_seam_tolerance`` of zero.

In noisy depth a short seam between two rocks passes that test by chance.  So the median is
also required to be sure enough: its standard error, ``1.25 w a z / sqrt(n)`` for ``n``
samples at the seam's median depth ``z`` (``a z`` is the view's relative depth noise, ``a``
estimated from the depth image itself, :func:`shadowcorr.ops.relative_depth_noise`; ``w``
the RMS over the samples of one step's noise in units of it, from the fit: ``_step_noise``),
times ``fusion_seam_noise`` must be within the tolerance too.  Fitted lines rather than
single pixels matter because the gap multiplies the slope's noise: across a 6-pixel gap,
single pixels with a slope read 3 pixels further in leave 4.1 sigma per step, lines over 10
pixels a side 1.5.  In clean depth every seam of ``fusion_seam_min_pixels`` (30) counts, and
at 1 % noise at 7.5 m too; at 2 % a seam across a 6-pixel gap needs about 60 samples.

The defaults (a 16-pixel gap, a tolerance of 0.6 %, 1.25 standard errors, 30 samples) were
chosen on the quality benchmark's rows together (10 scenes per cell, every rig, clean,
single and combined errors; ``benchmarks/bench_quality.py``): against single pixels across
at most 8 pixels (0.4 %, 1, 20) they raise the mean over the rigs under the ``field`` errors
from 98.19 to 98.50 (``syn:4v-low`` 95.00 to 96.45, ``syn:2v-opposite`` 97.49 to 98.16) and
under ``harsh`` from 94.25 to 94.40, and lose 0.07 in one row (``syn:4v+split20%``).  A
shorter minimum or a lower noise factor let two touching rocks pass for one surface (once in
clean depth, once under 2 % noise).

A seam too short or too noisy to pass for smooth is not an occlusion contour either when its
median step lies within ``fusion_seam_unsure`` standard errors of the tolerance (and it has
at least :data:`UNSURE_MIN_PIXELS` samples): such a pair is *unsure*, and its view then
neither joins nor parts it (the grouping's loose mask ids, ``split_mask_ids``).  That is the
small piece a split leaves of a small rock: its seam with the rest has a dozen samples, too
few for the test above in clean depth and, under noise, for any test; read as two masks, the
cannot-link of its view kept it alone although the other views saw it with the rest.

A seam of at least ``fusion_seam_min_pixels`` samples whose median step lies more than
``fusion_seam_apart`` standard errors beyond the tolerance shows two surfaces: an occlusion
contour or a crease.  Such a pair is *apart*.  It vetoes the one join that needs other views:
two masks that co-land there (``split_mask_ids``) are two rocks that another view's segmenter
merged, not one rock cut in two, when their own view shows the depth step between them.

What the step cannot tell apart: two rocks that touch along a contour with continuous depth
(side by side at one distance, the contact facing the camera).  They meet in a valley: on
either side the surface falls away from the camera towards the contact, so one common slope
explains both sides and the step is nil.  The slope itself tells: a line is also fitted to
each side alone, and the *bend* is the second side's slope minus the first's along the walk,
as a change of the surface's depth gradient (depth per unit of sideways distance: per pixel,
relative to depth, times the focal length in pixels along the walk).  A cut over one
(convex) rock leaves the gradient going on or rising; a seam whose median bend falls below
``-fusion_seam_crease``, by ``fusion_seam_noise`` standard errors of that median under the
view's depth noise, is a *crease* and counts as apart, not as smooth or unsure.  Measured
on the quality benchmark's scenes (15 scenes or seeds per row), of the pairs that read as
smooth or unsure, the crease takes 51 of the 61 pairs of two different rocks on the real scene
under the ``mild`` errors and none of its 46 pairs of one rock cut in two; 13 of 21 and none
of 26 on ``syn:2v-opposite``; 39 of 40 and 2 of 215 on ``syn:4v`` under 20 % splits (31 of 41
and 2 of 207 on ``syn:4v-720p``); 29 of 111 and 3 of 164 on ``syn:6v-uneven`` under
``harsh``.  A tolerance of 0.2 took more pairs of one rock (a rock's own hollows: 4 and 10 of
them on those two rigs under 20 % splits) for one more pair of two rocks on each.  A pair
that passes is a *candidate* only: the grouping reads it as one mask id for its per-view
constraints (as the blobs of one mask), and the surface and volumetric evidence still decide
whether the two join.  Mask ids are only compared within their own view; nothing here reads ground truth.

Cost: one comparison of each view's window with itself shifted by a pixel per direction;
everything else runs on the border pixels (a few per cent of the mask), and the sides are
read only for pairs with enough samples to make a seam.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..bundle import SceneBundle
from ..config import ShadowCorrConfig
from ..ops import NOISE_ROW_STEP, relative_depth_noise, thread_map
from ._02_segments import SegmentImage, Segments

#: Most pixels read on each side of a seam along a walk, to which lines are fitted.
SIDE_PIXELS = 10
#: Fewest: a side narrower than that along the walk gives no step.
MIN_SIDE_PIXELS = 3
#: Fewest pixel pairs along a seam for it to be read as unsure (``fusion_seam_unsure``).
UNSURE_MIN_PIXELS = 4
#: Pixels inside each side where its reading starts (not the contour pixel itself).
INSET = 1
#: Walk directions (row step, column step): along the rows and the columns (a straight cut at
#: any angle crosses one of them; the diagonals only add samples, at twice the cost).
DIRECTIONS = ((0, 1), (1, 0))
#: Two masks touch (``Seams.touching_first`` / ``touching_second``) across up to this many times
#: ``fusion_seam_gap`` unlabelled pixels along a row or a column.  A rock's mask cut in two and
#: eroded leaves its halves that far apart: under the quality benchmark's ``harsh`` errors (5 px
#: erosion, 20 % line splits) the halves of one rock lay 14 px apart in a 1080p view, across a
#: slanted cut, so more along a row or a column; within one gap (16 px) the benchmark's
#: ``harsh`` rows lost up to 0.21 points, within two at most 0.09.
TOUCH_REACH = 2


@dataclass
class Seams:
    """Pairs of segments of one view (``first < second``) whose shared border is one smooth
    surface, with the measured median step and its allowed bound (both relative to depth)."""

    first: np.ndarray  # (K,) int64 segment index
    second: np.ndarray  # (K,) int64 segment index, same view as first
    samples: np.ndarray  # (K,) int64 pixel pairs sampled along the seam
    step: np.ndarray  # (K,) float64 median relative depth step across the seam (signed)
    uncertainty: np.ndarray  # (K,) float64 its standard error under the view's estimated depth noise
    # Pairs whose seam decides nothing (``first < second``): too short or too noisy to pass
    # for smooth, yet its step is not an occlusion's either (see ``fusion_seam_unsure``).
    unsure_first: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    unsure_second: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    # Pairs whose seam shows two surfaces (``first < second``): long enough, and a step surely
    # beyond the tolerance (``fusion_seam_apart`` standard errors): an occlusion or a crease.
    apart_first: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    apart_second: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    # Every pair that meets at all (``first < second``): some pixel of one follows a pixel of the
    # other along a row or a column across at most ``TOUCH_REACH * fusion_seam_gap`` unlabelled pixels.
    touching_first: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    touching_second: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    # The views whose masks were read (a view without depth or pixel labels is not): of two
    # segments of such a view, not touching says they do not meet; of another view, nothing.
    views_read: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

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
        intrinsics = bundle.views[j].intrinsics
        focal = None if intrinsics is None else (intrinsics.fx * image.view_stride, intrinsics.fy * image.view_stride)
        seams = _view_seams(image, depth, config, None if segments.depth_noise is None else segments.depth_noise[j],
                            focal)
        return replace(seams, views_read=np.array([j], dtype=np.int64))

    found = thread_map(view_seams, range(len(bundle.views)), config.num_threads)
    seams = Seams(*(np.concatenate([getattr(f, name) for f in found]) for name in
                    ("first", "second", "samples", "step", "uncertainty", "unsure_first", "unsure_second",
                     "apart_first", "apart_second", "touching_first", "touching_second", "views_read")))
    return seams if segments.cut is None else _cut_seams_unsure(seams, segments.cut)


def _cut_seams_unsure(seams: Seams, cut: np.ndarray) -> Seams:
    """``seams`` with every seam between two pieces of one blob cut at a depth step (stage 02) made unsure.

    Their seam runs along the step that cut them, so it reads as two surfaces; but what the cut
    found is a step, which one rock's overhang shows as well as two rocks: the other views decide."""
    def same_cut(first: np.ndarray, second: np.ndarray) -> np.ndarray:
        return (cut[first] >= 0) & (cut[first] == cut[second])

    pieces = [same_cut(seams.first, seams.second), same_cut(seams.unsure_first, seams.unsure_second),
              same_cut(seams.apart_first, seams.apart_second)]
    if not any(p.any() for p in pieces):
        return seams
    smooth, unsure, apart = (~p for p in pieces)
    return replace(
        seams, first=seams.first[smooth], second=seams.second[smooth], samples=seams.samples[smooth],
        step=seams.step[smooth], uncertainty=seams.uncertainty[smooth],
        unsure_first=np.r_[seams.unsure_first, seams.first[~smooth], seams.apart_first[~apart]],
        unsure_second=np.r_[seams.unsure_second, seams.second[~smooth], seams.apart_second[~apart]],
        apart_first=seams.apart_first[apart], apart_second=seams.apart_second[apart])


def _view_seams(image: SegmentImage, depth: np.ndarray, config: ShadowCorrConfig, noise: float | None = None,
                focal: tuple[float, float] | None = None) -> Seams:
    """One view's smooth, unsure and apart seams; ``noise`` is the view's relative depth noise (measured here when None),
    ``focal`` its focal lengths (x, y) in pixels of ``image`` (None: creases are not read)."""
    labels = np.asarray(image.window)
    if labels.size == 0:
        return Seams.empty()
    h, w = labels.shape
    stride = image.view_stride
    if stride > 1:  # depth coarser than the labels (a site map's stored view): each pixel reads the depth pixel it lies in
        depth_rows = np.minimum((image.top + np.arange(h)) // stride, depth.shape[0] - 1)
        depth_cols = np.minimum((image.left + np.arange(w)) // stride, depth.shape[1] - 1)
        z = np.asarray(depth)[np.ix_(depth_rows, depth_cols)]
    else:
        z = depth[image.top:image.top + h, image.left:image.left + w]  # a view: read only where sampled
    found = [_neighbours(labels, dy, dx, TOUCH_REACH * config.fusion_seam_gap) for dy, dx in DIRECTIONS]
    rows, cols, a, b, d = (np.concatenate([f[i] for f in found]) for i in range(5))
    dy, dx = (np.repeat([direction[i] for direction in DIRECTIONS], [f[0].size for f in found]) for i in (0, 1))
    span = int(labels.max()) + 1
    key = np.minimum(a, b) * span + np.maximum(a, b)
    pairs, inverse = np.unique(key, return_inverse=True)
    none = np.zeros(0, dtype=np.int64)
    touching = Seams(none, none, none, np.zeros(0), np.zeros(0), touching_first=pairs // span,
                     touching_second=pairs % span)
    # Seams are read only across one fusion_seam_gap.  A pair with fewer such samples than a seam
    # (or an unsure one) needs is dropped before its sides are read (reading only ever removes
    # samples): most border pairs are corners where three masks meet.
    seam = d <= config.fusion_seam_gap + 1
    counts = np.bincount(inverse[seam], minlength=pairs.size)
    fewest = min(config.fusion_seam_min_pixels, UNSURE_MIN_PIXELS) if config.fusion_seam_unsure > 0 else \
        config.fusion_seam_min_pixels
    enough = np.flatnonzero(seam & (counts[inverse] >= fewest))
    if enough.size == 0:
        return touching
    # Pixels of this image per unit of depth slope along each walk (fx along the rows, fy along the columns).
    reads_crease = config.fusion_seam_crease > 0 and focal is not None
    walk_focal = np.where(dx > 0, focal[0], focal[1]) if reads_crease else np.zeros(dx.size)
    a, b, step, zp, width, bend, bend_noise = _steps(labels, z, *(x[enough] for x in
                                                                  (rows, cols, a, b, d, dy, dx, walk_focal)))
    if a.size == 0:
        return touching
    # One orientation per pair: the step is measured from the smaller index to the larger.
    flip = a > b
    a, b = np.where(flip, b, a), np.where(flip, a, b)
    step = np.where(flip, -step, step)
    key = a * span + b
    # The same runs sorted two ways, three where creases are read (the bend needs no flip: walked the
    # other way, both slopes change sign and sides, and their difference stays).
    by_step, by_depth = np.lexsort((step, key)), np.lexsort((zp, key))
    by_bend = np.lexsort((bend, key)) if reads_crease else by_step
    key, step, zp, width = key[by_step], step[by_step], zp[by_depth], width[by_step]
    bend_noise, bend = bend_noise[by_step], bend[by_bend]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    counts = np.diff(np.r_[starts, key.size])
    square_width = np.add.reduceat(width**2, starts)  # per run, before runs are dropped (reduceat sums up to the next start)
    square_bend = np.add.reduceat(bend_noise**2, starts)
    keep = counts >= fewest
    starts, counts, square_width, square_bend = starts[keep], counts[keep], square_width[keep], square_bend[keep]
    if starts.size == 0:
        return touching
    # Median of each run: the steps are sorted within their key.
    lower, upper = starts + (counts - 1) // 2, starts + counts // 2
    median_step = 0.5 * (step[lower] + step[upper])
    median_depth = 0.5 * (zp[lower] + zp[upper])
    median_bend = 0.5 * (bend[lower] + bend[upper])
    # The median of n steps, each _step_noise(...) sigma of depth noise wide, is uncertain by
    # 1.25 times their RMS width / sqrt(n) (sigma = a z, relative): in noisy depth a short seam
    # between two rocks passes for smooth by chance, so a seam counts only where that
    # uncertainty is within the tolerance.  The noise figure is the whole view's
    # (Segments.depth_noise), read as the occupancy stage reads it.
    if noise is None:
        noise = relative_depth_noise(np.asarray(depth)[::NOISE_ROW_STEP])

    def median_uncertainty(square_sum: np.ndarray) -> np.ndarray:
        """Per run, the median's standard error from the summed squares of its samples' noise (in sigmas)."""
        return 1.25 * np.sqrt(square_sum / counts) * noise * median_depth / np.sqrt(counts)

    uncertainty = median_uncertainty(square_width)
    smooth = (counts >= config.fusion_seam_min_pixels) & (np.abs(median_step) <= config.fusion_seam_tolerance)
    if config.fusion_seam_noise > 0:
        smooth &= config.fusion_seam_noise * uncertainty <= config.fusion_seam_tolerance
    # Unsure: a seam that is not smooth, but whose step lies within fusion_seam_unsure standard
    # errors of the tolerance - the small piece a split leaves of a small rock has a seam of
    # a dozen samples, which in clean depth is short of the minimum and under noise cannot
    # tell a cut from a contour.  Such a pair's view says nothing about it (neither one mask
    # nor two), instead of keeping the piece apart from the rest of its rock.
    unsure = np.zeros_like(smooth)
    if config.fusion_seam_unsure > 0:
        unsure = ~smooth & (np.abs(median_step) <= config.fusion_seam_tolerance + config.fusion_seam_unsure * uncertainty)
    apart = np.zeros_like(smooth)
    if config.fusion_seam_apart > 0:
        apart = (counts >= config.fusion_seam_min_pixels) & (
            np.abs(median_step) > config.fusion_seam_tolerance + config.fusion_seam_apart * uncertainty)
    if reads_crease:
        # A crease: the depth's slope falls across the seam (a valley, concave towards the camera)
        # by more than fusion_seam_crease, sure by fusion_seam_noise standard errors.  Two rocks
        # side by side meet in such a valley, at one depth, where the step sees one surface; a
        # cut through one (convex) rock leaves the slope going on, or rising.
        bend_uncertainty = median_uncertainty(square_bend)
        crease = median_bend < -(config.fusion_seam_crease + config.fusion_seam_noise * bend_uncertainty)
        smooth &= ~crease
        unsure &= ~crease
        apart |= crease
    k, u, t = key[starts][smooth], key[starts][unsure], key[starts][apart & ~unsure]
    return Seams(k // span, k % span, counts[smooth].astype(np.int64), median_step[smooth], uncertainty[smooth],
                 u // span, u % span, t // span, t % span, touching.touching_first, touching.touching_second)


def _neighbours(labels: np.ndarray, dy: int, dx: int, gap: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of different segments that follow each other along the rows (``dx`` = 1) or the
    columns (``dy`` = 1) across at most ``gap`` unlabelled pixels: (row, column) of the first
    segment's last pixel, the first and the second segment, and the second's distance ``d``.

    Read from the runs of constant value along each line: the value changes only on border
    pixels, so after one comparison of the image with itself shifted by a pixel everything
    runs on the (few) changes.  A segment's run followed directly by another segment's is a
    pair at ``d`` = 1; one followed by an unlabelled run of ``g`` <= ``gap`` pixels and then
    another segment's run, a pair at ``d`` = ``g + 1``.  The same segment on both sides of a
    gap is a concave border, no pair.
    """
    change = labels[:labels.shape[0] - dy, :labels.shape[1] - dx] != labels[dy:, dx:]
    rows, cols = np.divmod(np.flatnonzero(change), change.shape[1])  # ten times faster than a 2D np.nonzero
    if dy:  # runs along the columns: the changes in column order (row-major order within each)
        order = np.argsort(cols, kind="stable")
        rows, cols = rows[order], cols[order]
    line, position = (rows, cols) if dx else (cols, rows)
    before = labels[rows, cols].astype(np.int64)
    after = labels[rows + dy, cols + dx].astype(np.int64)
    direct = np.flatnonzero((before >= 0) & (after >= 0))
    # An unlabelled run starts after change i and ends at change i + 1 on the same line.
    g = position[1:] - position[:-1]
    across = np.flatnonzero((before[:-1] >= 0) & (after[:-1] < 0) & (line[1:] == line[:-1]) & (g <= gap)
                            & (after[1:] >= 0) & (after[1:] != before[:-1]))
    first = np.concatenate([direct, across])
    return (rows[first], cols[first], before[first], np.concatenate([after[direct], after[across + 1]]),
            np.concatenate([np.ones(direct.size, np.int64), g[across] + 1]))


def _steps(labels: np.ndarray, z: np.ndarray, rows: np.ndarray, cols: np.ndarray, a: np.ndarray, b: np.ndarray,
           d: np.ndarray, dy: np.ndarray, dx: np.ndarray, focal: np.ndarray
           ) -> tuple[np.ndarray, ...]:
    """The relative depth step of each pair of :func:`_neighbours` (``dy``, ``dx``: its direction;
    ``focal``: the focal length in pixels along it) where both sides give a reading: (first
    segment, second segment, step, first side's mean depth, the step's noise in sigmas, the
    bend of the depth gradient across the seam and the bend's noise in sigmas of relative depth)."""
    flat_labels = np.ascontiguousarray(labels).reshape(-1)
    # Each side's depth is read on up to SIDE_PIXELS pixels along the walk, from INSET pixels
    # inside it (a depth sensor mixes the two surfaces on the contour pixel itself), as far as
    # the side's segment and valid depth reach without a break (at least MIN_SIDE_PIXELS), and
    # a line with one slope for both sides is fitted: the step is what that slope does not
    # explain between the sides' centroids (see _step_noise for why a fit, not single pixels).
    # Positions along the walk: this segment's border pixel is 0, the other's first pixel d.
    k = INSET + np.arange(SIDE_PIXELS)
    dy, dx = dy[:, None], dx[:, None]
    side_a = _side_reading(flat_labels, z, a, rows[:, None] - k * dy, cols[:, None] - k * dx)
    side_b = _side_reading(flat_labels, z, b, (rows + d * dy.ravel())[:, None] + k * dy,
                           (cols + d * dx.ravel())[:, None] + k * dx)
    good = np.flatnonzero((side_a[0] >= MIN_SIDE_PIXELS) & (side_b[0] >= MIN_SIDE_PIXELS))
    (n_a, k_a, z_a, kk_a, kz_a), (n_b, k_b, z_b, kk_b, kz_b) = ((x[good] for x in side) for side in (side_a, side_b))
    a, b, d, focal = a[good], b[good], d[good], focal[good]
    # Along the walk this side's positions run -(INSET + k), the other's d + INSET + k: the
    # common slope (per pixel, towards the other side) and the centroids' distance.
    spread = kk_a + kk_b
    slope = (kz_b - kz_a) / spread
    between = d + 2 * INSET + k_a + k_b
    step = (z_b - z_a - slope * between) / z_a
    # Each side's own slope: a crease between two surfaces bends the depth profile at the seam.
    bend = focal * (kz_b / kk_b + kz_a / kk_a) / z_a  # side a is read away from the seam
    bend_noise = focal * np.sqrt(1.0 / kk_a + 1.0 / kk_b)
    return a, b, step, z_a, _step_noise(n_a, n_b, between, spread), bend, bend_noise


def _side_reading(flat_labels: np.ndarray, z: np.ndarray, segment: np.ndarray, rows: np.ndarray, cols: np.ndarray
                  ) -> tuple[np.ndarray, ...]:
    """One side of each seam sample from its (samples, SIDE_PIXELS) pixels, nearest the seam first:
    how many leading pixels lie in the window, on ``segment`` and on valid depth (n), and over
    them the mean position k and depth z and the centred sums of k^2 and k z."""
    h, w = z.shape
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    rows, cols = np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)
    depth = z[rows, cols].astype(np.float64)  # z is a window of the frame's depth: read by (row, column)
    with np.errstate(invalid="ignore"):
        ok = inside & (flat_labels.take(rows * w + cols) == segment[:, None]) & (depth > 0) & np.isfinite(depth)
    n = np.where(ok.all(axis=1), ok.shape[1], np.argmin(ok, axis=1))  # the leading run of usable pixels
    k = np.arange(ok.shape[1], dtype=np.float64)
    used = k[None, :] < n[:, None]
    depth = np.where(used, depth, 0.0)
    count = np.maximum(n, 1).astype(np.float64)
    mean_k, mean_z = (n - 1) / 2.0, depth.sum(axis=1) / count
    kk = n * (n * n - 1.0) / 12.0  # sum over k = 0..n-1 of (k - mean)^2
    kz = depth @ k - count * mean_k * mean_z
    return n, mean_k, mean_z, kk, kz


def _step_noise(n_a: np.ndarray, n_b: np.ndarray, between: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """Standard deviation of one step, in units of the depth noise sigma: the sides' means carry
    ``1 / n`` of variance each, and the common slope (``1 / spread`` of variance, ``spread`` the
    positions' centred sum of squares over both sides) is multiplied by the ``between`` pixels
    from one centroid to the other.

    Across the 6-pixel gap that 3 px of erosion on either side of a cut leaves, two single pixels
    and a slope read over 3 pixels further in carry 4.1 sigma per step; lines fitted to 10 pixels
    a side, 1.5.
    """
    return np.sqrt(1.0 / n_a + 1.0 / n_b + between.astype(np.float64) ** 2 / spread)
