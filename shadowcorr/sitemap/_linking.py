"""Which stored views a new scan is linked to, and the poses it is linked with.

**Views that see the same ground.**  Each view's footprint is the bounding box of its segments'
points (widened by ``FOOTPRINT_MARGIN_VOXELS`` voxels), indexed by the map's cells, so finding
the stored views whose footprint meets a new view's costs what the neighbourhood holds, not what
the map holds.  Of those, a stored view is linked when its frustum holds a centroid of a new
segment or a new view's frustum holds one of its segment centroids (in front of the camera,
inside the image, within ``max_depth``).  Where more than ``max_views`` are, they are chosen one by
one for the sides they see the new segments from: each next view is the one that sees most new
segments from a side (one of 26 directions) that neither the new views nor the views already
chosen see them from, ties and the rest by most such centroids.  On a contiguous field (3 x 6
stops of 4 views, ``benchmarks/bench_map.py --part contiguous --stops 3x6``), where the last
scans share rocks with 60 stored views, this brings the map's average purity from 99.87 to 99.98
with 32 views linked (the one-shot run of all 72 views: 100), from 98.67 to 98.81 with 16.

**Poses.**  With ``refine_poses`` the new views are registered together with the linked stored
views by the stage itself (:func:`~shadowcorr.stages.refine_poses`), every view at the pose its
scan declared (the map keeps it beside the registered one), stored views on the stage's own
sampling grid (kept at full precision for this: the very pixels the stage reads of a full
image), and the views listed by name, then scan, not in the order they were added.  Every view
then takes the pose this registration gives it, as one run of all these views would, and
stored views move with their segments (``registered_corrections``).  Registration is path
independent this way: once a neighbourhood's views are all linked, its poses are what
registering them at once gives, whatever the order the scans came in (on the real scene under
the ``field`` errors, after the 4th scan of 2 views, the map's poses equal those of one run of
the 8 views exactly).  Registering from the poses already corrected, or from the coarse summary
depth, moved views by up to 3 degrees from that solution and changed the map's partitions.

**Revisits.**  A new view taken from the place of a stored one (after registration: the camera
within ``REVISIT_VOXELS`` voxels, turned by less than ``REVISIT_DEG``, the same image size and
focal length) repeats it: its segments that cover the same pixels as a stored segment (IoU over
``REVISIT_IOU`` on the summary grid) take that segment's id, and the stored view leaves the run -
the same surface seen twice would count its evidence twice.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..bundle import View
from ..result import ViewPoseCorrection
from ..stages import SegmentImage
from ._summaries import StoredViews, ViewSummary, grid_labels

__all__ = ["FOOTPRINT_MARGIN_VOXELS", "REVISIT_DEG", "REVISIT_IOU", "REVISIT_VOXELS", "corrected_report",
           "footprints", "in_frustum", "rank_views", "registered_corrections", "revisits"]

#: A footprint is widened by this many voxels: the two sides of one rock, seen from opposite
#: views, are two boxes that may only touch.
FOOTPRINT_MARGIN_VOXELS = 4


#: A new view repeats a stored one from within this many voxels and degrees ...
REVISIT_VOXELS = 1.0
REVISIT_DEG = 1.0
#: ... and a new segment repeats a stored segment of it when their pixels' IoU exceeds this
#: (over a half: each is then the other's only match).
REVISIT_IOU = 0.5


def footprints(points: np.ndarray, view: np.ndarray, lengths: np.ndarray, num_views: int
               ) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """Per view the bounding box of its segments' points (None for a view without points)."""
    point_view = np.repeat(view, lengths)
    out: list[tuple[np.ndarray, np.ndarray] | None] = []
    for j in range(num_views):
        pts = points[point_view == j]
        out.append((pts.min(axis=0), pts.max(axis=0)) if pts.size else None)
    return out


def in_frustum(points: np.ndarray, pose: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int,
               height: int, max_depth: float) -> np.ndarray:
    """Which world points (map units) a camera sees: in front, inside the image, within ``max_depth``."""
    cam = (points - pose[:3, 3]) @ pose[:3, :3]
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * cam[:, 0] / z + cx
        v = fy * cam[:, 1] / z + cy
    return (z > 0) & (z <= max_depth) & (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)


def rank_views(new_cams: list[tuple], new_centroids: np.ndarray, stored_cams: dict[int, tuple],
               stored_centroids: dict[int, np.ndarray], max_depth: float, max_views: int) -> list[int]:
    """Stored views (ids) linked to the new views, at most ``max_views`` (see the module docstring).

    ``*_cams``: per view ``(pose, fx, fy, cx, cy, width, height)``; ``new_centroids``: the new
    segments' centroids; ``stored_centroids``: per stored view its segments' centroids.
    """
    shared, seen = {}, {}
    for view, cam in stored_cams.items():
        theirs = stored_centroids.get(view, np.zeros((0, 3)))
        mine = in_frustum(new_centroids, *cam, max_depth) if new_centroids.size else np.zeros(0, dtype=bool)
        count = int(mine.sum())
        for new in new_cams:
            count += int(in_frustum(theirs, *new, max_depth).sum()) if theirs.size else 0
        if count:
            shared[view], seen[view] = count, mine
    order = sorted(shared, key=lambda v: (-shared[v], v))
    if len(order) <= max_views or not new_centroids.size:
        return order[:max_views]
    # Greedy cover of (new centroid, side it is seen from): a view that sees a segment from a side
    # no linked view sees it from brings the evidence a run of all views would have.
    def sides(pose: np.ndarray) -> np.ndarray:
        d = pose[:3, 3] - new_centroids
        return np.argmax(d @ _SIDES.T, axis=1)
    covered = np.zeros((len(new_centroids), len(_SIDES)), dtype=bool)
    rows = np.arange(len(new_centroids))
    for cam in new_cams:
        inside = in_frustum(new_centroids, *cam, max_depth)
        covered[rows[inside], sides(cam[0])[inside]] = True
    side = {v: sides(stored_cams[v][0]) for v in order}
    chosen: list[int] = []
    rest = list(order)
    while rest and len(chosen) < max_views:
        gains = [int((~covered[rows[seen[v]], side[v][seen[v]]]).sum()) for v in rest]
        best = int(np.argmax(gains))  # ties (and no gain left): most shared centroids first
        v = rest.pop(best)
        chosen.append(v)
        covered[rows[seen[v]], side[v][seen[v]]] = True
    return chosen


#: Sides a segment is seen from: the 26 directions of a cube's faces, edges and corners.
_SIDES = np.array([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)],
                  dtype=np.float64)
_SIDES /= np.linalg.norm(_SIDES, axis=1, keepdims=True)


def registered_corrections(reports: list[ViewPoseCorrection], current: list[np.ndarray], declared: list[np.ndarray]
                           ) -> list[np.ndarray | None]:
    """Every view's move from its ``current`` pose to the pose a registration of the run at the
    ``declared`` poses gives it (see the module docstring); None where it stays.

    ``reports``: the registration's, one per view.  A corrected view goes to its corrected declared
    pose; a view of a group whose declared poses already agree (``unchanged``) or whose corrections
    the masks do not bear out (``not_confirmed``) goes back to its declared pose, as it would in one
    run of all these views; a view the run could not judge (not registered, correction too large)
    keeps its current pose.
    """
    out: list[np.ndarray | None] = []
    for report, now, before in zip(reports, current, declared):
        if report.status == "corrected":
            target = np.asarray(report.correction, dtype=np.float64) @ before
        elif report.status in ("unchanged", "not_confirmed"):
            target = before
        else:
            target = now
        move = target @ _rigid_inverse(now)
        out.append(None if np.allclose(move, np.eye(4), atol=1e-12) else move)
    return out


def _rigid_inverse(pose: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = pose[:3, :3].T
    out[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return out


def corrected_report(report: ViewPoseCorrection, view: View, correction: np.ndarray | None) -> ViewPoseCorrection:
    """A view's report with its correction relative to its pose in the map (``registered_corrections``)."""
    if correction is None:
        return report
    moved = correction @ view.pose
    return report.model_copy(update={
        "correction": correction.round(9).tolist(),
        "rotation_deg": round(float(np.degrees(Rotation.from_matrix(correction[:3, :3]).magnitude())), 4),
        "translation": round(float(np.linalg.norm(moved[:3, 3] - view.pose[:3, 3])), 4)})


def revisits(summaries: list[ViewSummary], new_view: np.ndarray, stored: StoredViews, voxel_size: float
             ) -> tuple[list[int], list[int], np.ndarray]:
    """The stored views (indices) that new views repeat, the new views (indices) that repeat one, and
    for every new segment the object of the stored segment it repeats (-1: none); see the module
    docstring.  ``new_view``: the view of each new segment."""
    repeats = np.full(len(new_view), -1, dtype=np.int64)
    new_first = np.searchsorted(new_view, np.arange(len(summaries)))
    twins: set[int] = set()
    repeating: set[int] = set()
    for j, summary in enumerate(summaries):
        fx, fy, cx, cy, _, _ = summary.intrinsics
        f = summary.stride
        mine = grid_labels(SegmentImage(summary.labels, summary.labels_top, summary.labels_left,
                                        (summary.intrinsics[5], summary.intrinsics[4]), summary.labels_stride),
                           f, summary.depth.shape, int(new_first[j]))
        for w, view in enumerate(stored.views):
            k = view.intrinsics
            same_camera = view.depth.shape == summary.depth.shape and np.allclose(
                [k.fx, k.fy, k.cx, k.cy], [fx / f, fy / f, (cx - f // 2) / f, (cy - f // 2) / f], rtol=1e-3, atol=1e-3)
            if not same_camera or np.linalg.norm(view.pose[:3, 3] - summary.pose[:3, 3]) > REVISIT_VOXELS * voxel_size:
                continue
            turn = np.clip((np.trace(summary.pose[:3, :3].T @ view.pose[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
            if np.degrees(np.arccos(turn)) > REVISIT_DEG:
                continue
            theirs = grid_labels(stored.segments.pixel_segment[w], f, summary.depth.shape)
            twins.add(w)
            repeating.add(j)
            both = (mine >= 0) & (theirs >= 0)
            if not both.any():
                continue
            span = int(theirs.max()) + 1
            pair, shared = np.unique(mine[both].astype(np.int64) * span + theirs[both], return_counts=True)
            a, b = pair // span, pair % span
            area_a = np.bincount(mine[mine >= 0], minlength=int(a.max()) + 1)
            area_b = np.bincount(theirs[theirs >= 0], minlength=span)
            iou = shared / (area_a[a] + area_b[b] - shared)
            same = iou > REVISIT_IOU
            repeats[a[same]] = stored.segment_objects[b[same]]
    return sorted(twins), sorted(repeating), repeats

