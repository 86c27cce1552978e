"""Per-view summaries: what the map keeps of a view instead of its images, and the views they stand in for.

A view's summary is its pose (as registered with the map, and as its scan declared it),
intrinsics and image size; its depth read every ``stride``-th pixel per axis (the pixel at
``stride * i + stride // 2``), so that the long side keeps at most :data:`SUMMARY_SIDE` pixels;
its image of segment indices at full resolution (the window holding every segment pixel); its
depth (float32) and mask on the pixels pose registration samples (stage 01's grid of about
20 000 pixels), so that a stored view is registered from exactly what its full image would give;
and per segment its points averaged on a grid of half the downsampling cell
(``downsample_size / POINT_CELL_DIVISOR``: the run averages them again on the downsampling grid
itself).  Read back, a summary is an ordinary :class:`~shadowcorr.bundle.View` with the coarser
depth's intrinsics, and its segments are ordinary :class:`~shadowcorr.stages.Segments` whose
segment image is finer than the view's depth (:attr:`~shadowcorr.stages.SegmentImage.view_stride`):
the stages that link a new scan to the map read stored views as they read the scan's own (their
depth and masks are coarser, their points fewer).  Maps of format 2 hold segment images on the
depth's grid (``labels_stride`` = ``stride``); those read back as they were written.  Lengths
are in the map's units (the configuration's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..bundle import Intrinsics, SceneBundle, View
from ..stages import SegmentImage, Segments, voxel_downsample
from ..stages._01_registration import depth_on_grid, sampling_stride  # the grid the pose stage samples
from ._store import MapFileError, unpack_array

__all__ = ["LABELS_STRIDE", "SUMMARY_SIDE", "StoredViews", "ViewSummary", "grid_labels", "summarize_views",
           "stored_views"]

#: The long side of a summary's depth, at most (960 for a 1920 x 1080 view: every 2nd pixel).  The
#: new views' landings in a stored view read its depth there, and its depth carves the shadows
#: there.  With segment images on the same grid (format 2), every 4th pixel (480) left the run of
#: all 8 views of the real scene under the ``field`` errors unlike one run of them in 6 of 24 draws
#: and orders (agreement 98.2-99.4), every 2nd in 3 (99.4), for about twice the bytes per view.
SUMMARY_SIDE = 960
#: Segment images are kept at full resolution (every pixel).  Read on the summary grid, the run
#: of all 8 views of the real scene under the ``field`` errors joined two of one run's objects in
#: one of 12 draws and orders (agreement 99.3); at full resolution it gives one run's partition,
#: for about 15 KB more per 1080p view (the labels compress well).
LABELS_STRIDE = 1


@dataclass
class ViewSummary:
    """What the map stores of one view of a new scan."""

    name: str
    pose: np.ndarray  # (4, 4) camera-to-world, map units, as registered with the map
    declared: np.ndarray  # (4, 4) the pose the scan declared (map units)
    intrinsics: tuple[float, float, float, float, int, int]  # fx, fy, cx, cy, width, height of the full image
    stride: int
    depth: np.ndarray  # (h, w) depth on the summary grid, map units, 0 = invalid
    labels: np.ndarray  # window of the segment index (within the view) every labels_stride-th pixel, -1 = none
    labels_top: int  # the window's first row and column, in pixels of the labels' grid
    labels_left: int
    labels_stride: int  # 1: the full image's pixels; == stride: the summary grid (format-2 maps)
    grid_stride: int  # the pose stage's sampling grid: every grid_stride-th pixel from grid_stride // 2
    grid_depth: np.ndarray  # (h, w) float32 depth there, map units, 0 = invalid
    grid_mask: np.ndarray  # (h, w) uint8: 1 where the view's mask has a rock
    lo: np.ndarray | None  # footprint: bounding box of the view's segment points (None: no points)
    hi: np.ndarray | None


def summary_stride(width: int, height: int) -> int:
    return max(1, math.ceil(max(width, height) / SUMMARY_SIDE))


def _on_grid(image: np.ndarray, stride: int) -> np.ndarray:
    return np.asarray(image[stride // 2::stride, stride // 2::stride])


def summarize_views(bundle: SceneBundle, segments: Segments, images: list[SegmentImage | None],
                    max_depth: float, declared: list[np.ndarray], depth_window: int) -> list[ViewSummary]:
    """The summary of every view of ``bundle`` (map units), whose segments are ``segments``
    (``images``: their segment-index images, as cut; ``declared``: the poses the scan declared;
    ``depth_window``: ``pose_depth_window``, so the stored grid is the depth the pose stage read)."""
    out = []
    first = np.searchsorted(segments.view, np.arange(len(bundle.views)))
    for j, view in enumerate(bundle.views):
        k = view.intrinsics
        f = summary_stride(k.width, k.height)
        rows = np.arange(f // 2, k.height, f)
        cols = np.arange(f // 2, k.width, f)
        depth = np.asarray(view.depth[np.ix_(rows, cols)], dtype=np.float32)
        depth = np.where(np.isfinite(depth) & (depth > 0) & (depth <= max_depth), depth, 0.0)
        depth = depth.astype(np.float16) if depth.max(initial=0.0) < 6e4 else depth
        image = images[j]  # a new view's: at full resolution
        if image is not None:
            labels, top, left = np.asarray(image.window), image.top, image.left
        else:
            labels, top, left = np.full((0, 0), -1), 0, 0
        labels = np.where(labels >= 0, labels - first[j], -1)
        on = np.argwhere(labels >= 0)
        if on.size:  # the window of the segment pixels (an image's window may hold none)
            (r0, c0), (r1, c1) = on.min(axis=0), on.max(axis=0) + 1
            window, top, left = labels[r0:r1, c0:c1], top + r0, left + c0
        else:
            window, top, left = labels[:0, :0], 0, 0
        window = window.astype(np.int16 if window.size == 0 or window.max() < np.iinfo(np.int16).max else np.int32)
        g = sampling_stride(k.height, k.width)
        # The depth the pose stage registers this view with (its window averages included): a stored
        # view is registered again at one pixel per sample, so it must hold what this run read.
        grid_depth = depth_on_grid(view.depth, g, depth_window, max_depth).astype(np.float32)
        grid_depth = np.where(np.isfinite(grid_depth) & (grid_depth > 0), grid_depth, np.float32(0.0))
        grid_mask = (_on_grid(view.mask, g) > 0).astype(np.uint8)
        mine = np.repeat(segments.view == j, segments.lengths)
        pts = segments.points[mine]
        lo, hi = (pts.min(axis=0), pts.max(axis=0)) if pts.size else (None, None)
        out.append(ViewSummary(view.name, view.pose.copy(), np.array(declared[j], dtype=np.float64),
                               (k.fx, k.fy, k.cx, k.cy, k.width, k.height), f, depth, window, int(top), int(left),
                               LABELS_STRIDE, g, grid_depth, grid_mask, lo, hi))
    return out


#: Stored points are averaged on a grid this many times finer than ``downsample_size``.  A stored
#: view moves whenever a later registration corrects it, and the shells of a run average its
#: points again on the downsampling grid, whose cells no longer line up with the ones they were
#: averaged in: averages of 2-unit cells, re-averaged after a turn of a degree, gave other shells
#: than the full points and, on the real scene under the ``field`` errors, another partition than
#: one run of all the views (98.9 agreement in two orders of the 3rd draw; 100 with this).
POINT_CELL_DIVISOR = 2


def segment_points(segments: Segments, cell: float) -> list[np.ndarray]:
    """Each segment's points averaged per ``cell / POINT_CELL_DIVISOR`` grid cell, float32 (what the
    map keeps of them; ``cell`` is the downsampling cell, ``downsample_size``)."""
    pts, seg = voxel_downsample(segments.points, segments.segment_index, cell / POINT_CELL_DIVISOR)
    counts = np.bincount(seg, minlength=segments.num_segments)
    return np.split(pts.astype(np.float32), np.cumsum(counts)[:-1])


@dataclass
class StoredViews:
    """Stored views read back: views (coarse images), their segments, and where each came from."""

    views: list[View]  # at their poses as registered with the map
    segments: Segments
    declared: np.ndarray  # (V, 4, 4) the poses their scans declared
    grid_views: list[View]  # the same views on the pose stage's grid, at their declared poses (registration)
    view_ids: np.ndarray  # (V,) map id of each view
    view_scans: np.ndarray  # (V,) the scan that added it
    view_names: list[str]  # as named in their scan
    segment_ids: np.ndarray  # (S,) map id of each segment
    segment_objects: np.ndarray  # (S,) current object of each segment

    def subset(self, keep: list[int]) -> "StoredViews | None":
        """Only the views ``keep`` (indices, ascending) and their segments; None when none is kept."""
        if not keep:
            return None
        seg = self.segments
        mine = np.isin(seg.view, keep)
        renumber = np.full(len(self.views), -1, dtype=np.int64)
        renumber[keep] = np.arange(len(keep))
        view = renumber[seg.view[mine]]
        points = seg.points[np.repeat(mine, seg.lengths)]
        old_first = np.searchsorted(seg.view, np.arange(len(self.views)))
        new_first = np.searchsorted(view, np.arange(len(keep)))
        images = []
        for j, old in enumerate(keep):
            image = seg.pixel_segment[old]
            window = np.where(image.window >= 0, image.window - old_first[old] + new_first[j], -1)
            images.append(SegmentImage(window.astype(image.window.dtype), image.top, image.left, image.shape,
                                       image.pixel_scale, image.view_stride))
        segments = Segments(points=points, lengths=seg.lengths[mine], view=view, instance=seg.instance[mine],
                            component=seg.component[mine], num_pixels=seg.num_pixels[mine],
                            camera_center=seg.camera_center[mine], optical_axis=seg.optical_axis[mine],
                            view_names=[seg.view_names[j] for j in keep], pixel_segment=images,
                            cut=None if seg.cut is None or not (seg.cut[mine] >= 0).any() else seg.cut[mine])
        return StoredViews([self.views[j] for j in keep], segments, self.declared[keep],
                           [self.grid_views[j] for j in keep], self.view_ids[keep],
                           self.view_scans[keep], [self.view_names[j] for j in keep], self.segment_ids[mine],
                           self.segment_objects[mine])


def stored_views(view_rows: list, segment_rows: list) -> StoredViews:
    """Views and segments of the map (rows of ``views`` and ``segments``, both ordered by view)."""
    views, images, declared, grid_views = [], [], [], []
    by_view: dict[int, list] = {}
    for r in segment_rows:
        by_view.setdefault(r["view"], []).append(r)
    points, lengths, view_idx, instance, component, pixels, cuts, centres, axes, seg_ids, objects = (
        [] for _ in range(11))
    for j, r in enumerate(view_rows):
        pose = unpack_array(r["pose"], "float64", "4,4").copy()
        declared.append(unpack_array(r["declared"], "float64", "4,4"))
        g = int(r["grid_stride"])
        grid_depth = unpack_array(r["grid_depth"], r["grid_depth_dtype"], r["grid_depth_shape"], compressed=True)
        grid_mask = unpack_array(r["grid_mask"], r["grid_mask_dtype"], r["grid_mask_shape"], compressed=True)
        grid_views.append(View(name=f"{r['scan']}/{r['name']}", pose=declared[-1], depth=grid_depth, mask=grid_mask,
                               intrinsics=Intrinsics(fx=r["fx"] / g, fy=r["fy"] / g, cx=(r["cx"] - g // 2) / g,
                                                     cy=(r["cy"] - g // 2) / g, width=grid_depth.shape[1],
                                                     height=grid_depth.shape[0])))
        f = int(r["stride"])
        depth = unpack_array(r["depth"], r["depth_dtype"], r["depth_shape"], compressed=True)
        window = unpack_array(r["labels"], r["labels_dtype"], r["labels_shape"], compressed=True)
        h, w = depth.shape
        k = Intrinsics(fx=r["fx"] / f, fy=r["fy"] / f, cx=(r["cx"] - f // 2) / f, cy=(r["cy"] - f // 2) / f,
                       width=w, height=h)
        rows = by_view.get(r["view"], [])
        inst = np.array([s["instance"] for s in rows], dtype=np.int64)
        image = _segment_image(window, int(r["labels_top"]), int(r["labels_left"]), int(r["labels_stride"]), f,
                               (int(r["height"]), int(r["width"])), (h, w))
        # Mask ids on the depth's grid, for pose registration's agreement check.
        on_grid = grid_labels(image, f, (h, w))
        mask = np.where(on_grid >= 0, inst[np.maximum(on_grid, 0)], 0).astype(np.int32) if inst.size else \
            np.zeros((h, w), dtype=np.int32)
        views.append(View(name=f"{r['scan']}/{r['name']}", pose=pose, intrinsics=k, depth=depth, mask=mask))
        images.append(image)
        for s in rows:
            p = unpack_array(s["points"], s["points_dtype"], s["points_shape"])
            points.append(p)
            lengths.append(p.shape[0])
            view_idx.append(j)
            instance.append(s["instance"])
            component.append(s["component"])
            pixels.append(s["num_pixels"])
            cuts.append(s["cut"])
            centres.append(pose[:3, 3])
            axes.append(pose[:3, 2])
            seg_ids.append(s["segment"])
            objects.append(s["object"])
    lengths_a = np.asarray(lengths, dtype=np.int64)
    view_a = np.asarray(view_idx, dtype=np.int64)
    first = np.searchsorted(view_a, np.arange(len(view_rows)))
    segments = Segments(
        points=np.concatenate(points).astype(np.float64) if points else np.zeros((0, 3)),
        lengths=lengths_a,
        view=view_a,
        instance=np.asarray(instance, dtype=np.int64),
        component=np.asarray(component, dtype=np.int64),
        num_pixels=np.asarray(pixels, dtype=np.int64),
        camera_center=np.asarray(centres, dtype=np.float64).reshape(-1, 3),
        optical_axis=np.asarray(axes, dtype=np.float64).reshape(-1, 3),
        view_names=[v.name for v in views],
        pixel_segment=[img.shifted(int(first[j])) for j, img in enumerate(images)],
        cut=np.asarray(cuts, dtype=np.int64) if any(c >= 0 for c in cuts) else None,
    )
    return StoredViews(views, segments, np.array(declared).reshape(-1, 4, 4), grid_views,
                       np.array([r["view"] for r in view_rows], dtype=np.int64),
                       np.array([r["scan"] for r in view_rows], dtype=np.int64), [r["name"] for r in view_rows],
                       np.asarray(seg_ids, dtype=np.int64), np.asarray(objects, dtype=np.int64))


def _segment_image(window: np.ndarray, top: int, left: int, labels_stride: int, stride: int,
                   frame: tuple[int, int], grid: tuple[int, int]) -> SegmentImage:
    """A stored view's segment image: at full resolution (``labels_stride`` 1; the view's depth
    every ``stride``-th pixel) or on the depth's own grid (``labels_stride`` == ``stride``)."""
    window = np.array(window)
    if labels_stride == 1 and stride > 1:
        return SegmentImage(window, top, left, frame, 1, stride)
    if labels_stride == stride:
        return SegmentImage(window, top, left, grid, stride)
    raise MapFileError(f"a view of the map file keeps its segment image every {labels_stride}th pixel and its "
                       f"depth every {stride}th: this version reads the image at every pixel or on the depth's grid")


def grid_labels(image: SegmentImage, stride: int, shape: tuple[int, int], first: int = 0) -> np.ndarray:
    """A view's segment indices (``first`` + index; -1: none) on its summary's grid of ``shape``
    (every ``stride``-th pixel from ``stride // 2``), from a stored or new view's segment image."""
    if image.pixel_scale == 1 and stride > 1:  # a full-resolution image
        rows = np.arange(shape[0]) * stride + stride // 2
        cols = np.arange(shape[1]) * stride + stride // 2
        found = image.at(rows[:, None], cols[None, :])
    else:  # already on the grid
        found = np.full(shape, -1, dtype=np.int64)
        h, w = image.window.shape
        found[image.top:image.top + h, image.left:image.left + w] = image.window
    return np.where(found >= 0, found + first, -1)


def join_segments(first: Segments, second: Segments) -> Segments:
    """The segments of two sets of views as one batch: ``second``'s views follow ``first``'s."""
    offset_views, offset_segments = len(first.view_names), first.num_segments
    images = [*(first.pixel_segment or [None] * offset_views),
              *[None if img is None else img.shifted(offset_segments) for img in
                (second.pixel_segment or [None] * len(second.view_names))]]
    return Segments(
        points=np.concatenate([first.points, second.points]),
        lengths=np.concatenate([first.lengths, second.lengths]),
        view=np.concatenate([first.view, second.view + offset_views]),
        instance=np.concatenate([first.instance, second.instance]),
        component=np.concatenate([first.component, second.component]),
        num_pixels=np.concatenate([first.num_pixels, second.num_pixels]),
        camera_center=np.concatenate([first.camera_center, second.camera_center]),
        optical_axis=np.concatenate([first.optical_axis, second.optical_axis]),
        view_names=[*first.view_names, *second.view_names],
        pixel_segment=images,
        cut=None if first.cut is None and second.cut is None else np.concatenate(
            [np.full(s.num_segments, -1, np.int64) if s.cut is None else s.cut for s in (first, second)]),
    )
