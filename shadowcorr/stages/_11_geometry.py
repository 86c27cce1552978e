"""Stage 11: objects -> each object's fused points, oriented box, volume and seen extent.

Once every segment has its object (stage 10), an object is described in 3D:

* **Fused points** (:func:`fuse_object_points`): the cleaned shell points (stage 04) of all
  its segments, averaged per ``downsample_size`` cell *of the object*, so that a surface
  two views both saw counts once, then statistical outlier removal per object (as stage
  04 does per segment: mixed pixels at depth edges would otherwise stretch the box).
* **Oriented box** (:func:`oriented_boxes`): turned about the world's up axis
  (``ShadowCorrConfig.up_axis``), with its first axis along the principal axis of the
  footprint on the ground plane (the eigenvector of the larger eigenvalue of the
  horizontal 2x2 covariance; the longer side is named first), its second axis horizontal
  and orthogonal to it, its third axis up.  It spans, along each axis, the fused points and
  the centres of the object's voxels that are at least half solid (those reach down where
  the views saw no surface, towards the rock's foot).  A rock rests on the ground, so a
  gravity-aligned box is what a planner grasps or drives around; the footprint's principal
  axes make it tight for elongated rocks.
* **Volume** (:func:`object_volumes`): the solid share (stage 05 occupancy) of the shadow
  voxels the object owns - a voxel belongs to the object of the segment whose shadow gives
  it the most confidence - times the voxel volume.  ``volume_std`` adds, in quadrature,
  half the volume that only one view's background rules out (evidence a missed mask in one
  view would fake), the binomial sampling error of the sub-voxel samples, and
  ``volume_relative_std`` of the volume: the spread of the volume against the true mesh
  volume on synthetic scenes, which the data of one scene cannot show (parts no view saw).
* **Extent**: the axis-aligned bounds of the fused points, i.e. of the surface the views
  saw (the voxel box of stage 10 reaches into the shadows, behind that surface).

Everything is computed for all objects at once with per-object reductions over
object-sorted arrays (``bincount``, ``reduceat``); nothing reads ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..config import ShadowCorrConfig
from ..ops import resolve_threads, segment_max, segment_min, segment_starts
from ..poses import world_up
from ..result import Extent, ObjectSummary, OrientedBox
from ._04_shells import remove_statistical_outliers, voxel_downsample
from ._05_occupancy import ShadowOccupancy


@dataclass
class ObjectPoints:
    """Each object's fused, deduplicated surface points, sorted by object (bundle units).

    ``points[starts[k]:starts[k] + counts[k]]`` are object ``k``'s points.
    """

    points: np.ndarray  # (N, 3) float64, bundle units, world frame
    object: np.ndarray  # (N,) int64 object of each point, ascending
    num_objects: int
    units: str

    @property
    def counts(self) -> np.ndarray:
        return np.bincount(self.object, minlength=self.num_objects)

    @property
    def starts(self) -> np.ndarray:
        return segment_starts(self.object, self.num_objects)

    def of(self, obj: int) -> np.ndarray:
        """The points of object ``obj``."""
        lo, hi = np.searchsorted(self.object, [obj, obj + 1])
        return self.points[lo:hi]


@dataclass
class ObjectGeometry:
    """Per-object geometry, in the bundle's units; rows are objects (NaN where not measurable)."""

    center: np.ndarray  # (K, 3) oriented box centres
    size: np.ndarray  # (K, 3) [long, short, vertical]
    quaternion: np.ndarray  # (K, 4) [x, y, z, w], box frame -> world
    volume: np.ndarray  # (K,) bundle units^3
    volume_std: np.ndarray  # (K,)
    extent_min: np.ndarray  # (K, 3)
    extent_max: np.ndarray  # (K, 3)
    num_points: np.ndarray  # (K,)
    num_views: np.ndarray  # (K,)


def fuse_object_points(points: np.ndarray, point_segment: np.ndarray, seg_object: np.ndarray, num_objects: int,
                       unit_scale: float, units: str, config: ShadowCorrConfig) -> ObjectPoints:
    """The objects' fused points from the segments' cleaned points (``config`` units, sorted by segment).

    Segments labelled -1 contribute nothing.  Returns bundle units (``unit_scale``: bundle -> config units).
    """
    obj = seg_object[point_segment] if point_segment.size else np.zeros(0, np.int64)
    labelled = obj >= 0
    fused, fused_obj = voxel_downsample(points[labelled], obj[labelled].astype(np.int64), config.downsample_size)
    keep = remove_statistical_outliers(fused, fused_obj, num_objects, config, resolve_threads(config.num_threads))
    return ObjectPoints(fused[keep] / unit_scale, fused_obj[keep], num_objects, units)


def oriented_boxes(points: np.ndarray, obj: np.ndarray, num_objects: int,
                   up: tuple[int, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes around each object's points (sorted by object), turned about the world axis ``up`` = (index, sign).

    Returns centres (K, 3), sizes (K, 3) [long, short, vertical] and rotation matrices (K, 3, 3)
    whose columns are the box axes in the world; NaN for objects without points.
    """
    k = num_objects
    axis, sign = up
    u = np.zeros(3)
    u[axis] = sign
    h1 = np.zeros(3)
    h1[(axis + 1) % 3] = 1.0
    h2 = np.cross(u, h1)  # (h1, h2, u) is right-handed
    count = np.bincount(obj, minlength=k).astype(np.float64)
    safe = np.maximum(count, 1.0)
    x, y = points @ h1, points @ h2
    mx, my = np.bincount(obj, weights=x, minlength=k) / safe, np.bincount(obj, weights=y, minlength=k) / safe
    dx, dy = x - mx[obj], y - my[obj]
    cxx = np.bincount(obj, weights=dx * dx, minlength=k)
    cxy = np.bincount(obj, weights=dx * dy, minlength=k)
    cyy = np.bincount(obj, weights=dy * dy, minlength=k)
    angle = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)  # direction of the larger eigenvalue's eigenvector
    major = np.cos(angle)[:, None] * h1 + np.sin(angle)[:, None] * h2
    minor = np.cross(u, major)  # major x minor = up: a proper rotation
    rotation = np.stack([major, minor, np.broadcast_to(u, major.shape)], axis=2)  # columns: box axes
    local = np.einsum("nij,ni->nj", rotation[obj], points)  # coordinates along the object's box axes
    lo = segment_min(local, obj, k, empty=np.nan)
    hi = segment_max(local, obj, k, empty=np.nan)
    size = hi - lo
    # Name the longer footprint axis first where the covariance's order disagrees with the extents:
    # a quarter turn about up, (x, y) -> (y, -x).
    swap = size[:, 1] > size[:, 0]
    if swap.any():
        r, low, high = rotation[swap], lo[swap], hi[swap]
        rotation[swap] = np.stack([r[:, :, 1], -r[:, :, 0], r[:, :, 2]], axis=2)
        lo[swap] = np.stack([low[:, 1], -high[:, 0], low[:, 2]], axis=1)
        hi[swap] = np.stack([high[:, 1], -low[:, 0], high[:, 2]], axis=1)
        size = hi - lo
    center = np.einsum("nij,nj->ni", rotation, (lo + hi) / 2.0)
    return center, size, rotation


def object_volumes(occupancy: ShadowOccupancy | None, seg_object: np.ndarray, num_objects: int, voxel_size: float,
                   unit_scale: float, relative_std: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Volume and its standard deviation per object (bundle units^3); NaN where none was measured."""
    k = num_objects
    if occupancy is None or occupancy.cell.shape[0] == 0:
        return np.full(k, np.nan), np.full(k, np.nan)
    obj = seg_object[occupancy.segment]
    owned = obj >= 0
    obj, solid, single = obj[owned], occupancy.solid[owned], occupancy.single_view[owned]
    cell_volume = (voxel_size / unit_scale) ** 3
    volume = np.bincount(obj, weights=solid, minlength=k) * cell_volume
    one_view = np.bincount(obj, weights=single, minlength=k) * cell_volume
    sampling_var = np.bincount(obj, weights=solid * (1.0 - solid) / occupancy.samples, minlength=k) * cell_volume ** 2
    std = np.sqrt((one_view / 2.0) ** 2 + sampling_var + (relative_std * volume) ** 2)
    none = np.bincount(obj, minlength=k) == 0
    volume[none] = np.nan
    std[none] = np.nan
    return volume, std


def with_geometry(objects: list[ObjectSummary], geometry: ObjectGeometry, support: np.ndarray,
                  seg_object: np.ndarray) -> list[ObjectSummary]:
    """The object summaries of stage 10 with their geometry and confidence (the mean support of their segments)."""
    k = len(objects)
    labelled = seg_object >= 0
    confidence = (np.bincount(seg_object[labelled], weights=support[labelled], minlength=k)
                  / np.maximum(np.bincount(seg_object[labelled], minlength=k), 1))

    def rounded(a: np.ndarray) -> list[float]:
        return [round(float(x), 4) + 0.0 for x in a]  # + 0.0: no -0.0 in the JSON

    out = []
    for i, summary in enumerate(objects):  # one row per object: the arrays above hold the work
        box = None
        if np.isfinite(geometry.size[i]).all():
            box = OrientedBox(center=rounded(geometry.center[i]), size=rounded(geometry.size[i]),
                              quaternion=[round(float(q), 8) + 0.0 for q in geometry.quaternion[i]])
        volume = geometry.volume[i]
        out.append(summary.model_copy(update={
            "confidence": round(float(confidence[i]), 4),
            "oriented_box": box,
            "volume": round(float(volume), 4) if np.isfinite(volume) else None,
            "volume_std": round(float(geometry.volume_std[i]), 4) if np.isfinite(volume) else None,
            "extent": Extent(min=rounded(geometry.extent_min[i]), max=rounded(geometry.extent_max[i]))
            if box is not None else None,
            "num_views": int(geometry.num_views[i]),
            "num_points": int(geometry.num_points[i]),
        }))
    return out


def object_geometry(cloud: ObjectPoints, occupancy: ShadowOccupancy | None, seg_object: np.ndarray,
                    segment_view: np.ndarray, segment_points: np.ndarray, poses: np.ndarray, unit_scale: float,
                    config: ShadowCorrConfig) -> ObjectGeometry:
    """Oriented box, volume, seen extent and counts of every object of ``cloud``.

    ``segment_points`` counts each segment's cleaned points (a view without any adds no view);
    ``poses`` (V, 4, 4) are the views' camera-to-world poses, for ``up_axis`` ``auto``.
    """
    k = cloud.num_objects
    box_points, box_object = cloud.points, cloud.object
    if occupancy is not None and occupancy.cell.size:  # the solid voxels reach below what the views saw
        owner = seg_object[occupancy.segment]
        solid = (owner >= 0) & (occupancy.solid >= 0.5)
        box_points = np.concatenate([box_points, occupancy.cell[solid] * (config.voxel_size / unit_scale)])
        box_object = np.concatenate([box_object, owner[solid]])
        order = np.argsort(box_object, kind="stable")
        box_points, box_object = box_points[order], box_object[order]
    center, size, rotation = oriented_boxes(box_points, box_object, k, world_up(poses, config.up_axis))
    quaternion = np.full((k, 4), np.nan)
    measured = np.isfinite(size).all(axis=1)
    if measured.any():
        quaternion[measured] = Rotation.from_matrix(rotation[measured]).as_quat()  # [x, y, z, w]
    volume, volume_std = object_volumes(occupancy, seg_object, k, config.voxel_size, unit_scale,
                                        config.volume_relative_std)
    seen = (seg_object >= 0) & (segment_points > 0)
    pairs = np.unique(seg_object[seen] * (int(segment_view.max(initial=0)) + 1) + segment_view[seen])
    num_views = np.bincount(pairs // (int(segment_view.max(initial=0)) + 1), minlength=k)
    return ObjectGeometry(
        center=center, size=size, quaternion=quaternion, volume=volume, volume_std=volume_std,
        extent_min=segment_min(cloud.points, cloud.object, k, empty=np.nan),
        extent_max=segment_max(cloud.points, cloud.object, k, empty=np.nan),
        num_points=cloud.counts, num_views=num_views,
    )
