"""Stage 2: scene bundle -> segments (partial 3D surface shells, one per mask blob).

Each view's instance mask is cut into blobs: every instance value is split into its
8-connected components (``split_components``), blobs smaller than ``min_blob_pixels``
are ignored, and the pixels with valid depth are back-projected through the pinhole
model ``((u - cx) d / fx, (v - cy) d / fy, d)`` in the OpenCV optical frame and moved
to the world frame with the view's camera-to-world pose.  Points come out in the
configuration's units.  For method ``fused`` a blob that a depth step parts from side to side
(one mask drawn over a rock and the rock behind it) is first cut into its pieces
(:func:`cut_at_depth_steps`), which stay blobs of their mask value.

Segments are a ragged batch: all points concatenated, with explicit per-segment
``lengths`` (the PyTorch3D convention), so later stages never loop over points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..bundle import SceneBundle, View, unit_scale
from ..config import ShadowCorrConfig
from ..errors import DepthRangeError
from ..ops import NOISE_ROW_STEP, relative_depth_noise, thread_map


@dataclass
class SegmentImage:
    """A view's image of segment indices (-1: no segment), kept as the window of the frame that
    holds every segment pixel: a quarter of the sample scene's frame, and int16 while the
    indices fit (see :attr:`Blobs.labels`), which is what bounds a large field's memory."""

    window: np.ndarray  # (h, w) segment index per pixel of the window
    top: int  # the window's first row and column in the frame
    left: int
    shape: tuple[int, int]  # the whole frame (H, W)
    pixel_scale: int = 1  # pixels of the camera's full image one pixel here spans (a site map's summary: its stride)
    # Pixels here that one pixel of the view's depth (and intrinsics) spans per axis: a site map's
    # stored view keeps its segment image at full resolution and its depth on a coarser grid, the
    # depth's pixel i standing for this image's pixels [i * view_stride, (i + 1) * view_stride).
    view_stride: int = 1

    @classmethod
    def from_blobs(cls, blobs: "Blobs") -> "SegmentImage":
        r0, r1, c0, c1 = blobs.bounds
        return cls(blobs.labels[r0:r1, c0:c1].copy(), r0, c0, blobs.labels.shape)

    def shifted(self, first_index: int) -> "SegmentImage":
        """The image with ``first_index`` added to every segment index (the view's first
        segment in the scene), widened to int32 when the indices outgrow int16."""
        if first_index == 0:
            return self
        window = self.window
        if window.size and int(window.max()) + first_index >= np.iinfo(window.dtype).max:
            window = window.astype(np.int32)
        else:
            window = window.copy()
        window[window >= 0] += first_index
        return SegmentImage(window, self.top, self.left, self.shape, self.pixel_scale, self.view_stride)

    def at(self, row: np.ndarray, col: np.ndarray) -> np.ndarray:
        """Segment index at frame pixels (``row``, ``col``) inside the frame; -1 off the window."""
        r, c = row - self.top, col - self.left
        h, w = self.window.shape
        off = (r < 0) | (r >= h) | (c < 0) | (c >= w)
        if h == 0 or w == 0:
            return np.full(np.shape(row), -1, dtype=np.int64)
        found = self.window.ravel()[np.clip(r, 0, h - 1) * w + np.clip(c, 0, w - 1)].astype(np.int64)
        found[off] = -1
        return found


@dataclass
class Segments:
    """Ragged batch of segments. Lengths in the configuration's units, world frame."""

    points: np.ndarray  # (P, 3) float64
    lengths: np.ndarray  # (S,) int64, number of points of each segment
    view: np.ndarray  # (S,) int64, index into view_names
    instance: np.ndarray  # (S,) int64, the mask value
    component: np.ndarray  # (S,) int64, blob index within (view, instance), largest first
    num_pixels: np.ndarray  # (S,) int64, blob size in the mask (valid depth or not)
    camera_center: np.ndarray  # (S, 3) float64
    optical_axis: np.ndarray  # (S, 3) float64, unit vector
    view_names: list[str]
    truth: np.ndarray | None = None  # (S,) int64 ground-truth object per segment, metrics only
    # Per view: the segment index on each pixel, for the cross-view surface evidence.  None
    # for views without images (point flavour).
    pixel_segment: list[SegmentImage | None] | None = None
    # (V,) each view's relative depth noise ``a`` (sigma = a z^2; 0 without depth), measured once
    # on its image for the stages that weigh depth against it (seams, occupancy).  None: not measured.
    depth_noise: np.ndarray | None = None
    # (S,) for the pieces of a blob cut at a depth step (stage 2, cut_at_depth_steps), that blob's index
    # in its view before the cut, shared by its pieces; -1 for a segment not cut.  None: nothing was cut.
    cut: np.ndarray | None = None

    @property
    def num_segments(self) -> int:
        return int(self.lengths.shape[0])

    @property
    def segment_index(self) -> np.ndarray:
        """(P,) segment index of every point."""
        return np.repeat(np.arange(self.num_segments), self.lengths)


@dataclass
class Blobs:
    """The blobs of one mask, as an image of blob indices.

    Blobs are ordered by instance value, and the components of one instance by
    decreasing size (ties: scan order), so the numbering does not depend on anything
    but the mask.
    """

    labels: np.ndarray  # (H, W) blob index on each pixel, -1 outside every blob; int16 while
    # every index the mask could produce fits (at most its foreground pixels / min_pixels blobs), else int32
    lengths: np.ndarray  # (B,) pixels per blob
    instance: np.ndarray  # (B,) mask value
    component: np.ndarray  # (B,) index within its instance, largest first
    bounds: tuple[int, int, int, int] = (0, 0, 0, 0)  # row and column ranges [r0, r1) x [c0, c1) holding every blob
    # (B,) for the pieces of a blob cut at a depth step (cut_at_depth_steps), the index that blob had
    # before the cut (one number per cut blob, shared by its pieces); -1 for a blob not cut.  None: no cut read.
    cut: np.ndarray | None = None

    def label_image(self, labels: np.ndarray, fill: int = -1) -> np.ndarray:
        """(H, W) int64 image holding ``labels[b]`` on blob b's pixels and ``fill`` elsewhere."""
        lookup = np.r_[np.asarray(labels, dtype=np.int64), fill]
        return lookup[np.where(self.labels >= 0, self.labels, -1)]


def find_blobs(mask: np.ndarray, split_components: bool = True, min_pixels: int = 50) -> Blobs:
    """Blobs of an instance mask: each instance value (> 0) cut into 8-connected components.

    With ``split_components`` off, each instance value is one blob.  Blobs with fewer
    than ``min_pixels`` pixels (at least 1) are left out.  The label image numbers the blobs
    from 0 (:meth:`SegmentImage.shifted` moves them to the scene's numbering).

    The mask is read as runs (maximal stretches of one value within a row), so the work
    is one pass over the foreground's bounding box plus a graph of runs, not a labelling
    per instance: two runs of one value in neighbouring rows touch (8-connected) when
    their column ranges, each widened by one, overlap, and the connected components of
    that graph are the blobs.
    """
    # Only the bounding box of the foreground is read (a quarter of the sample scene's frame).
    foreground = mask > 0
    fg_rows, fg_cols = np.flatnonzero(foreground.any(axis=1)), np.flatnonzero(foreground.any(axis=0))
    # int16 indices while every index this mask can produce fits: half the memory of int32.
    most_blobs = int(np.count_nonzero(foreground)) // max(min_pixels, 1)
    image = np.full(mask.shape, -1, dtype=np.int16 if most_blobs < 1 << 15 else np.int32)
    empty = np.zeros(0, dtype=np.int64)
    if fg_rows.size == 0:
        return Blobs(image, empty, empty, empty)
    top, left = int(fg_rows[0]), int(fg_cols[0])
    crop = mask[top : fg_rows[-1] + 1, left : fg_cols[-1] + 1]
    width = crop.shape[1]
    flat = crop.ravel()

    # Runs: a new one starts at every change of value and at every row start.
    change = np.empty(flat.size, dtype=bool)
    change[0] = True
    np.not_equal(flat[1:], flat[:-1], out=change[1:])
    change[::width] = True
    all_start = np.flatnonzero(change)  # raster position of each run's first pixel
    all_length = np.diff(np.r_[all_start, flat.size])
    value = flat[all_start].astype(np.int64)
    on = np.flatnonzero(value > 0)  # foreground runs
    start, run_length, value = all_start[on], all_length[on], value[on]
    row, col = np.divmod(start, width)
    end = col + run_length  # exclusive

    # Instances in ascending value, and each run's instance.
    ids, instance_of_run = np.unique(value, return_inverse=True)
    if split_components:
        # Runs sorted by (instance, row, start column).  Within one row of one instance the
        # runs are disjoint, so their start and end columns are both ascending: the runs
        # one row up that touch run b (start <= end_b and end >= col_b) form one contiguous
        # stretch of that order, found by two searches.  The pairs are therefore at most
        # the runs of both rows (linear in runs), even for a mask that is all tiny runs
        # such as a checkerboard, where "every run of the row above" would be quadratic.
        order = np.lexsort((col, row, instance_of_run))
        line = instance_of_run * (crop.shape[0] + 1) + row  # (instance, row) as one key
        stride = width + 2  # column keys 0..width inclusive stay inside one line
        line_sorted = line[order] * stride
        start_key, end_key = line_sorted + col[order], line_sorted + end[order]
        above = (line - 1) * stride  # same instance, one row up
        lo = np.searchsorted(end_key, above + col, side="left")  # first run up there ending at or after col_b
        hi = np.searchsorted(start_key, above + end, side="right")  # past the last one starting at or before end_b
        count = np.maximum(hi - lo, 0)
        run_b = np.repeat(np.arange(start.size), count)
        run_a = order[np.repeat(lo, count) + (np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count))]
        graph = coo_matrix((np.ones(run_a.size), (run_a, run_b)), shape=(start.size,) * 2)
        _, blob_of_run = connected_components(graph, directed=False)
    else:
        blob_of_run = instance_of_run
    num = int(blob_of_run.max()) + 1
    size = np.bincount(blob_of_run, weights=run_length, minlength=num).astype(np.int64)
    first_pixel = np.full(num, flat.size, dtype=np.int64)
    np.minimum.at(first_pixel, blob_of_run, start)
    instance_of_blob = np.zeros(num, dtype=np.int64)
    instance_of_blob[blob_of_run] = instance_of_run
    # Blob order: instance value, then size (largest first), then scan order of the first pixel.
    kept = np.flatnonzero(size >= max(min_pixels, 1))
    kept = kept[np.lexsort((first_pixel[kept], -size[kept], instance_of_blob[kept]))]
    if kept.size == 0:
        return Blobs(image, empty, empty, empty)
    index = np.full(num, -1, dtype=image.dtype)  # blob -> its index, -1 for a dropped blob
    index[kept] = np.arange(kept.size)
    instance = instance_of_blob[kept]
    first_of_instance = np.flatnonzero(np.r_[True, instance[1:] != instance[:-1]])
    component = np.arange(kept.size) - np.repeat(first_of_instance, np.diff(np.r_[first_of_instance, kept.size]))

    # Paint the crop run by run: every pixel of the box belongs to exactly one run (foreground
    # or not), so one repeat of the per-run labels fills it in raster order.
    all_label = np.full(all_start.size, -1, dtype=image.dtype)
    all_label[on] = index[blob_of_run]
    image[top : fg_rows[-1] + 1, left : fg_cols[-1] + 1] = np.repeat(all_label, all_length).reshape(crop.shape)

    # Bounds: the boxes of every instance with a kept blob (small blobs of theirs included).
    has_kept = np.zeros(ids.size, dtype=bool)
    has_kept[instance] = True
    runs_in = has_kept[instance_of_run]
    bounds = (int(row[runs_in].min()) + top, int(row[runs_in].max()) + 1 + top,
              int(col[runs_in].min()) + left, int(end[runs_in].max()) + left)
    return Blobs(image, size[kept], ids[instance], component.astype(np.int64), bounds)


#: Standard deviations of the depth noise of a difference of two pixels beyond which a jump is a step
#: (:func:`cut_at_depth_steps`): about one pair in 16 000 of a smooth surface passes by chance, too few
#: to part anything.
CUT_NOISE = 4.0
#: Smallest share of a blob's pixels that each piece of a cut keeps: a rock's own overhangs and
#: the far rim of a slanted surface step inside one rock as well, over a sliver.
CUT_MIN_SHARE = 0.1
#: The steps are looked for on every CUT_GRID-th row and column first; a blob with one is read again
#: at full resolution.
CUT_GRID = 2


def cut_at_depth_steps(blobs: Blobs, depth: np.ndarray, noise: float, step: float) -> Blobs:
    """The blobs with each blob that a depth step parts cut into its pieces (method ``fused``).

    A segmenter that draws one mask over two touching rocks, one in front of the other, leaves
    an occlusion contour inside the mask: across it the depth jumps from the nearer rock to the
    farther.  Such a mask is one segment to every later stage, which then has to give both rocks
    one label.  Here two neighbouring pixels of one blob, one or two pixels apart along a row or
    a column, are *stepped* when their depths differ by more than ``step`` of the nearer depth,
    and by more than :data:`CUT_NOISE` standard deviations of such a difference under the view's
    depth noise (``noise`` is ``a`` in ``sigma = a z^2``, :func:`shadowcorr.ops.relative_depth_noise`;
    two pixels apart, a step that a sensor spreads over a mixed pixel still counts).  The pixels of
    stepped pairs are taken out and the rest of the blob falls into 8-connected parts; where at least
    two of them keep :data:`CUT_MIN_SHARE` of the blob's pixels each, the blob is cut: every pixel of
    it (stepped, without depth, or of a smaller part) goes to the nearest of those parts.  Two rocks
    that touch where the mask joins them at one depth (both resting on the ground side by side) are
    not parted: the step must run across the whole blob.

    Pieces keep the blob's mask value, are numbered as components of it (largest first) and
    carry the blob's former index in :attr:`Blobs.cut`.  Costs one pass over the blobs on a
    ``CUT_GRID`` grid, and a full-resolution read of the window of the blobs with a step.
    """
    if step <= 0 or blobs.lengths.size == 0:
        return blobs
    num = blobs.lengths.size
    r0, r1, c0, c1 = blobs.bounds
    # On the grid first (one pixel apart there is two of the frame's): only the blobs it finds in
    # pieces are read again at full resolution.
    grid, grid_depth, _, _ = _frame_grid(blobs, depth, CUT_GRID)
    found = _parts(grid.astype(np.int64), grid_depth, noise, step, (1,), num)
    if found is None:
        return blobs
    # The frame's window of those blobs, read at full resolution.
    is_candidate = np.zeros(num + 1, dtype=bool)
    is_candidate[found[3] + 1] = True
    on = is_candidate[blobs.labels[r0:r1, c0:c1].astype(np.int64) + 1]
    rows, cols = np.flatnonzero(on.any(axis=1)), np.flatnonzero(on.any(axis=0))
    top, left = r0 + int(rows[0]), c0 + int(cols[0])
    bottom, right = r0 + int(rows[-1]) + 1, c0 + int(cols[-1]) + 1
    on = on[top - r0:bottom - r0, left - c0:right - c0]
    labels = np.where(on, blobs.labels[top:bottom, left:right], -1).astype(np.int64)
    found = _parts(labels, depth[top:bottom, left:right], noise, step, (1, 2), num)
    if found is None:
        return blobs
    parts, blob_of_part, big, cut_blobs = found

    # Every pixel of a cut blob goes to its nearest big part (one distance transform per cut blob, in its box;
    # the boxes of every blob found in one pass over the window).
    from scipy.ndimage import distance_transform_edt, find_objects

    keeps = big & np.isin(blob_of_part, cut_blobs)
    piece_of_part = np.full(parts.lengths.size, -1, dtype=np.int64)
    piece_of_part[keeps] = np.arange(int(keeps.sum()))
    part_image = np.where(parts.labels >= 0, piece_of_part[np.maximum(parts.labels, 0)], -1)
    piece_blob = blob_of_part[keeps]
    piece_image = np.full(labels.shape, -1, dtype=np.int64)
    boxes = find_objects(labels + 1)  # boxes[b]: blob b's rows and columns in the window
    for b in cut_blobs.tolist():
        box = boxes[b]
        inside = labels[box] == b
        own = np.where(inside, part_image[box], -1)  # b's big parts
        _, (ri, ci) = distance_transform_edt(own < 0, return_indices=True)
        piece_image[box][inside] = own[ri, ci][inside]

    # Renumber: the blobs not cut and the pieces, by mask value, then size (largest first), then the
    # former blob and piece order.  A piece is numbered num + its index until then.
    piece_size = np.bincount(piece_image[piece_image >= 0], minlength=piece_blob.size)
    is_cut = np.zeros(num, dtype=bool)
    is_cut[cut_blobs] = True
    whole = np.flatnonzero(~is_cut)
    old_id = np.r_[whole, num + np.arange(piece_blob.size)]
    origin = np.r_[whole, piece_blob]
    size = np.r_[blobs.lengths[whole], piece_size]
    instance = blobs.instance[origin]
    order = np.lexsort((old_id, -size, instance))
    count = order.size
    new_index = np.empty(count, dtype=np.int64)
    new_index[order] = np.arange(count)
    lookup = np.full(num + piece_blob.size + 1, -1, dtype=np.int64)  # former id + 1 -> new index
    lookup[old_id + 1] = new_index
    dtype = blobs.labels.dtype if count < np.iinfo(blobs.labels.dtype).max else np.int32
    renumbered = lookup[blobs.labels[r0:r1, c0:c1].astype(np.int64) + 1]  # a cut blob's pixels: -1 here
    in_piece = piece_image >= 0  # every pixel of a cut blob, all inside the candidates' window
    renumbered[top - r0:bottom - r0, left - c0:right - c0][in_piece] = new_index[whole.size + piece_image[in_piece]]
    image = np.full(blobs.labels.shape, -1, dtype=dtype)
    image[r0:r1, c0:c1] = renumbered
    instance = instance[order]
    first_of_instance = np.flatnonzero(np.r_[True, instance[1:] != instance[:-1]])
    component = np.arange(count) - np.repeat(first_of_instance, np.diff(np.r_[first_of_instance, count]))
    cut = np.where(old_id[order] >= num, origin[order], -1)
    return Blobs(image, size[order], instance, component.astype(np.int64), blobs.bounds, cut)


def _parts(labels: np.ndarray, depth: np.ndarray, noise: float, step: float, offsets: tuple[int, ...], num: int
           ) -> tuple[Blobs, np.ndarray, np.ndarray, np.ndarray] | None:
    """The parts that the stepped pixels leave of the blobs of ``labels`` (blob indices, -1: none; ``num`` blobs),
    each part's blob, whether it keeps CUT_MIN_SHARE of its blob's pixels here, and the blobs with two such
    parts; None when no blob has."""
    stepped = _stepped_pixels(labels, depth, noise, step, offsets)
    if not stepped.any():
        return None
    parts = find_blobs(np.where(stepped, 0, labels + 1), True, 1)  # mask value: blob + 1, largest part first
    blob_of_part = parts.instance - 1
    pixels = np.bincount(labels[labels >= 0], minlength=num)
    big = parts.lengths >= CUT_MIN_SHARE * pixels[blob_of_part]
    cut_blobs = np.flatnonzero(np.bincount(blob_of_part[big], minlength=num) >= 2)
    return (parts, blob_of_part, big, cut_blobs) if cut_blobs.size else None


def _stepped_pixels(labels: np.ndarray, depth: np.ndarray, noise: float, step: float, offsets: tuple[int, ...]
                    ) -> np.ndarray:
    """(h, w) bool: the pixels of pairs of one blob, ``offsets`` pixels apart along a row or a column, whose
    depths jump (see :func:`cut_at_depth_steps`), and the pixels between them."""
    z = np.asarray(depth, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        valid = (labels >= 0) & (z > 0) & np.isfinite(z)
    out = np.zeros(labels.shape, dtype=bool)
    spread = np.float32(CUT_NOISE * np.sqrt(2.0) * noise)
    for axis in (0, 1):
        n = labels.shape[axis]
        for o in offsets:
            if n <= o:
                continue
            first = (slice(0, n - o), slice(None)) if axis == 0 else (slice(None), slice(0, n - o))
            second = (slice(o, n), slice(None)) if axis == 0 else (slice(None), slice(o, n))
            za, zb = z[first], z[second]
            near = np.minimum(za, zb)
            jump = (valid[first] & valid[second] & (labels[first] == labels[second])
                    & (np.abs(za - zb) > near * np.maximum(np.float32(step), spread * near)))
            for k in range(o + 1):  # both ends and every pixel between
                part = (slice(k, n - o + k), slice(None)) if axis == 0 else (slice(None), slice(k, n - o + k))
                out[part] |= jump
    return out


def view_blobs(view: View, config: ShadowCorrConfig, noise: float | None = None) -> Blobs:
    """The blobs of a view's mask as the segments are cut from them: :func:`find_blobs`, then, where
    ``config.cut_step`` is on and the view has depth, :func:`cut_at_depth_steps` (``noise``: the view's
    relative depth noise, measured here when None)."""
    blobs = find_blobs(view.mask, config.split_components, config.min_blob_pixels)
    if config.cut_step <= 0 or view.depth is None:
        return blobs
    if noise is None:
        noise = relative_depth_noise(view.depth[::NOISE_ROW_STEP])
    return cut_at_depth_steps(blobs, view.depth, noise, config.cut_step)


def back_project(view: View, pixels_v: np.ndarray, pixels_u: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(N, 3) world points (bundle units) of pixels (row v, column u) with z-depth ``depth``, through the view's pose."""
    k = view.intrinsics
    x = (pixels_u - k.cx) * depth / k.fx
    y = (pixels_v - k.cy) * depth / k.fy
    r, t = view.pose[:3, :3], view.pose[:3, 3]
    # Written out per axis: numpy's (N, 3) @ (3, 3) takes a slow non-BLAS path.
    return np.stack([r[i, 0] * x + r[i, 1] * y + r[i, 2] * depth + t[i] for i in range(3)], axis=1)


def _frame_grid(blobs: Blobs, depth: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Blob indices and float32 depth on the frame's grid of every ``step``-th row and column, read
    inside the blobs' bounds only (the same blob pixels as on the whole frame), and the frame row
    and column of the grid's first pixel.  Float16 depth is widened here, on the grid's pixels only."""
    r0, r1, c0, c1 = blobs.bounds
    r0, c0 = -(-r0 // step) * step, -(-c0 // step) * step  # the first grid row and column inside the bounds
    window = np.asarray(depth[r0:r1:step, c0:c1:step], dtype=np.float32)
    return blobs.labels[r0:r1:step, c0:c1:step], window, r0, c0


def _pixel_stride(view: View, blobs: Blobs, max_depth: float, scale: float, config: ShadowCorrConfig) -> int:
    """Every how many pixels (per axis) a point is back-projected: as many as fit, at the median
    depth of the view's segments (read on every 4th pixel per axis), into ``pixel_spacing``
    of a ``downsample_size`` cell.  Facing the camera, every cell that step 1 averages over
    keeps a point; cells the surface crosses at a slant or only grazes may lose theirs.  Half a
    cell (stride 2 on the sample scene) gave the partitions of every pixel on 16 real and
    synthetic scenes at two thirds of the CPU time; 0.7 (stride 3 there) measured as good again on
    the quality benchmark (average purity within a standard error in every row, voxel ARI higher
    in nearly all) at 15-35 % less time per scene, most of it under depth noise, whose scattered
    points fill many cells."""
    if not config.subsample_pixels:
        return 1
    labels, depth, _, _ = _frame_grid(blobs, view.depth, 4)
    d = depth[labels >= 0]
    d = d[np.isfinite(d) & (d > 0) & (d <= max_depth)]
    if d.size == 0:
        return 1
    footprint = float(np.median(d)) * scale / max(view.intrinsics.fx, view.intrinsics.fy)
    # A stride beyond the frame samples one pixel all the same; capping it keeps the pixel
    # arithmetic in range however small a footprint the depth and intrinsics declare.
    return max(1, int(min(config.pixel_spacing * config.downsample_size / footprint, max(view.depth.shape))))


def extract_segments(bundle: SceneBundle, config: ShadowCorrConfig | None = None) -> Segments:
    """Cut every view into segments and back-project them (see the module docstring).

    Views are independent: ``config.num_threads`` of them are cut at once.
    """
    config = config or ShadowCorrConfig()
    scale = unit_scale(bundle.units, config.units)
    if bundle.point_segments is not None:
        return _from_point_segments(bundle, scale)

    noise = [relative_depth_noise(v.depth[::NOISE_ROW_STEP]) if v.depth is not None else 0.0 for v in bundle.views]
    found = thread_map(lambda view_noise: _view_segments(*view_noise, scale, config), list(zip(bundle.views, noise)),
                       config.num_threads)
    points, lengths, view_idx, instances, components, pixels, centers, axes, truth, cuts = ([] for _ in range(10))
    pixel_segment: list[SegmentImage | None] = []
    first_segment = 0
    for vi, (view, part) in enumerate(zip(bundle.views, found)):
        pixel_segment.append(part.image.shifted(first_segment))
        inst, comp, sizes = part.instance, part.component, part.num_pixels
        first_segment += inst.size
        if inst.size == 0:
            continue
        points.append(part.points)
        lengths.append(part.lengths)
        view_idx.append(np.full(inst.size, vi))
        instances.append(inst)
        components.append(comp)
        pixels.append(sizes)
        cuts.append(part.cut)
        centers.append(np.repeat(view.camera_center[None] * scale, inst.size, axis=0))
        axes.append(np.repeat(view.optical_axis[None], inst.size, axis=0))
        if bundle.ground_truth == "instance":
            truth.append(inst.copy())
        elif bundle.ground_truth == "mapped":
            table = view.instance_objects or {}
            truth.append(np.array([table.get(int(i), -1) for i in inst], dtype=np.int64))

    if not lengths:
        empty3 = np.zeros((0, 3))
        return Segments(empty3, *(np.zeros(0, dtype=np.int64) for _ in range(5)), empty3, empty3,
                        [v.name for v in bundle.views], None)
    cut = np.concatenate(cuts)
    return Segments(
        points=np.concatenate(points),
        lengths=np.concatenate(lengths).astype(np.int64),
        view=np.concatenate(view_idx).astype(np.int64),
        instance=np.concatenate(instances),
        component=np.concatenate(components),
        num_pixels=np.concatenate(pixels),
        camera_center=np.concatenate(centers),
        optical_axis=np.concatenate(axes),
        view_names=[v.name for v in bundle.views],
        truth=np.concatenate(truth) if truth else None,
        pixel_segment=pixel_segment,
        depth_noise=np.array(noise),
        cut=cut if (cut >= 0).any() else None,
    )


class _ViewSegments(NamedTuple):
    """One view's segments; the frame-sized blob image is not kept (only its window), so a
    field's views cut side by side do not hold a frame each."""

    image: SegmentImage  # blob indices from 0
    points: np.ndarray  # (P, 3) configuration units, grouped by blob
    lengths: np.ndarray  # (B,) points per blob
    instance: np.ndarray  # (B,)
    component: np.ndarray  # (B,)
    num_pixels: np.ndarray  # (B,)
    cut: np.ndarray  # (B,) see Segments.cut


def _view_segments(view: View, noise: float, scale: float, config: ShadowCorrConfig) -> _ViewSegments:
    """One view's blobs (``noise``: its relative depth noise), cut and back-projected."""
    blobs = view_blobs(view, config, noise)
    image = SegmentImage.from_blobs(blobs)
    if blobs.lengths.size == 0:
        return _ViewSegments(image, np.zeros((0, 3)), *(np.zeros(0, dtype=np.int64) for _ in range(5)))
    # Back-project the pixels of a stride x stride grid, blob after blob, in raster order.
    max_depth_bundle = config.max_depth / scale
    stride = _pixel_stride(view, blobs, max_depth_bundle, scale, config)
    on_grid, depth, r0, c0 = _frame_grid(blobs, view.depth, stride)
    chosen = (on_grid >= 0) & np.isfinite(depth) & (depth > 0) & (depth <= max_depth_bundle)
    on_grid_pixel = np.flatnonzero(chosen)
    # Grouped by blob, raster order within a blob: a stable sort, radix on int16 indices.
    blob_of_pixel = on_grid.ravel()[on_grid_pixel]
    by_blob = np.argsort(blob_of_pixel, kind="stable")
    blob_of_pixel = blob_of_pixel[by_blob]
    on_grid_pixel = on_grid_pixel[by_blob]
    rows, cols = np.divmod(on_grid_pixel, chosen.shape[1])
    rows, cols = rows * stride + r0, cols * stride + c0
    d = depth.ravel()[on_grid_pixel]  # the grid's depth (widened exactly from float16), not a second frame read
    pts = back_project(view, rows.astype(np.float64), cols.astype(np.float64), d.astype(np.float64))
    return _ViewSegments(image, pts * scale if scale != 1.0 else pts,
                         np.bincount(blob_of_pixel, minlength=blobs.lengths.size), blobs.instance, blobs.component,
                         blobs.lengths, np.full(blobs.lengths.size, -1, np.int64) if blobs.cut is None else blobs.cut)


def _from_point_segments(bundle: SceneBundle, scale: float) -> Segments:
    ps = bundle.point_segments
    view = np.asarray(ps.view, dtype=np.int64)
    poses = np.stack([v.pose for v in bundle.views])
    num = np.asarray(ps.lengths, dtype=np.int64)
    # Components: numbered in listing order within (view, instance).
    key = view * (int(np.max(ps.instance, initial=0)) + 1) + np.asarray(ps.instance, dtype=np.int64)
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    first = np.searchsorted(sorted_key, sorted_key, side="left")
    component = np.empty_like(key)
    component[order] = np.arange(key.size) - first
    return Segments(
        points=np.asarray(ps.points, dtype=np.float64) * scale,
        lengths=num,
        view=view,
        instance=np.asarray(ps.instance, dtype=np.int64),
        component=component,
        num_pixels=num.copy(),
        camera_center=poses[view, :3, 3] * scale,
        optical_axis=poses[view, :3, 2],
        view_names=[v.name for v in bundle.views],
        truth=None if ps.object is None else np.asarray(ps.object, dtype=np.int64),
    )


#: Share of segments without a valid point at which a scene is refused rather than labelled.
MAX_EMPTY_SEGMENT_SHARE = 0.9


def check_valid_depth(segments: Segments, bundle_units: str, config: ShadowCorrConfig) -> list[str]:
    """Refuse a scene whose segments nearly all lack valid depth; warn about any that do.

    Raises :class:`DepthRangeError` when at least ``MAX_EMPTY_SEGMENT_SHARE`` of the
    segments have no back-projected point (depth <= 0, non-finite, or beyond
    ``max_depth``).  Otherwise returns one summary warning when some segments are
    empty (the per-segment details come later, from the assignment), or nothing.
    """
    empty = int(np.count_nonzero(segments.lengths == 0))
    total = segments.num_segments
    if empty == 0 or total == 0:
        return []
    limit = config.max_depth / unit_scale(bundle_units, config.units)
    what = (f"{empty} of {total} segments have no valid depth point (every depth is <= 0, not finite, or beyond "
            f"max_depth = {config.max_depth:g} {config.units} = {limit:g} {bundle_units} in the bundle's units)")
    if empty >= MAX_EMPTY_SEGMENT_SHARE * total:
        raise DepthRangeError(f"{what}: check the manifest's units (\"{bundle_units}\") and max_depth")
    return [f"{what}; they are labelled without 3D evidence"]
