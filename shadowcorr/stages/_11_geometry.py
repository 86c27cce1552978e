"""Stage 11: objects -> each object's fused points, oriented box, volume and seen extent.

Once every segment has its object (stage 10), an object is described in 3D:

* **Fused points** (:func:`fuse_object_points`): the shell points (stage 04) of all its
  segments, averaged per ``downsample_size`` cell *of the object*, so that a surface two
  views both saw counts once.
* **Solid samples**: the sub-cell samples (stage 05 occupancy) that no view rules out, of
  the voxels the object owns - a voxel belongs to the object of the segment whose shadow
  gives it the most confidence - kept only in the object's largest 26-connected set of
  such voxels (by solid volume): stray solid voxels that a mixed depth pixel's shadow or a
  neighbour's leave behind elsewhere would otherwise stretch the box.
* **Oriented box** (:func:`oriented_boxes`): turned about the world's up axis
  (``ShadowCorrConfig.up_axis``), with its first axis along a side of the smallest-area
  rectangle around the footprint on the ground plane (:func:`min_area_angles`: the convex
  hull of the solid samples' columns on their own grid, or of the fused points on that grid
  for an object without any, and the best rectangle along one of its edges; the longer side
  is named first), its second axis horizontal and orthogonal to it, its third axis up.  It
  spans the solid samples (each the centre of a sub-cell, padded by half a sub-cell) and the
  fused points that lie within one sub-cell of one of the object's solid samples.  Points
  farther out are seen by no other view where they are: mixed ("flying") depth pixels at the
  rock's outline, which float between the rock and what lies behind it.  It ends below at the
  lowest of those points, less one sub-cell (``_FLOOR_ALLOWANCE``): the ground under a rock is
  hidden behind the rock in every view, so its samples stay solid.  A rock rests on the
  ground, so a gravity-aligned box is what a planner grasps or drives around; the smallest
  footprint makes it tight for elongated and for blocky rocks alike.  On generated rock
  fields (``benchmarks/bench_geometry.py``, the same construction on the rocks' meshes) it
  took the boxes within 1.5x of the true box from 96.3 to 96.9 % of the objects on exact
  images (95th percentile 1.45 -> 1.34), from 88.5 to 90.1 % with mixed depth pixels at
  every outline, where the footprint's principal axis had turned them.  Boxes still too large
  span space that no view can rule out: behind the rock in the one view that sees that side
  and behind other rocks in every other view.
* **Volume** (:func:`object_volumes`): the solid share of the voxels the object owns,
  plus half the share that only one view's background rules out, times the voxel volume;
  of an object seen by several views, a voxel that the shadows of its segments in only one
  view reach counts half too (:func:`one_view_cells`: behind the rock in that view and
  behind other rocks in the rest, space no view rules out, mostly outside the rock).
  ``volume_std`` adds, in quadrature, those halves (evidence of one view alone, so the
  volume spans both readings within one standard deviation), the
  binomial sampling error of the sub-voxel samples, and
  ``volume_relative_std`` of the volume: the spread of the volume against the true mesh
  volume on synthetic scenes, which the data of one scene cannot show (parts no view saw).
* **Extent**: the axis-aligned bounds of the fused points the box spans, i.e. of the
  surface the views saw (the voxel box of stage 10 reaches into the shadows, behind that
  surface).

Everything is computed for all objects at once with per-object reductions over
object-sorted arrays (``bincount``, ``reduceat``) and sorted integer keys (connected
voxels, the points' neighbouring samples, the footprints' grid columns; the smallest
rectangles are a sorted search over the hulls' edges): n log n in the points; nothing reads
ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from ..config import ShadowCorrConfig
from ..ops import argsort_keys, segment_max, segment_min, segment_starts, sort_keys
from ..poses import world_up
from ..result import Extent, ObjectSummary, OrientedBox
from ._04_shells import voxel_downsample
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
    if not labelled.all():
        points, obj = points[labelled], obj[labelled]
    fused, fused_obj = voxel_downsample(points, obj.astype(np.int64, copy=False), config.downsample_size)
    return ObjectPoints(fused / unit_scale, fused_obj, num_objects, units)


@dataclass
class _UpFrame:
    """Two horizontal axes and the up axis of the world, (h1, h2, up) right-handed."""

    axis: int
    u: np.ndarray
    h1: np.ndarray
    h2: np.ndarray

    @classmethod
    def of(cls, up: tuple[int, float]) -> "_UpFrame":
        axis, sign = up
        u = np.zeros(3)
        u[axis] = sign
        h1 = np.zeros(3)
        h1[(axis + 1) % 3] = 1.0
        return cls(axis, u, h1, np.cross(u, h1))

    def horizontal(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Coordinates along h1 and h2 (each one world axis, up to sign)."""
        i1, i2 = int(np.argmax(np.abs(self.h1))), int(np.argmax(np.abs(self.h2)))
        return points[:, i1] * self.h1[i1], points[:, i2] * self.h2[i2]


def _chain(x: np.ndarray, y: np.ndarray, obj: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each object's run of points (``x`` strictly rising or falling within a run) with every inner point
    that makes no strict left turn dropped, pass by pass, until none is left: one side of its convex hull.

    A point on or below the chord of its two neighbours is no hull vertex whatever the neighbours are, so
    a pass drops all such points at once; the chain only rises where a point goes, and it stops as a
    concave chain with every dropped point under it.  Each pass costs the chain's length; a chain loses a
    dent's points from both sides each pass (a few passes on a footprint).
    """
    while x.size > 2:
        inner = np.flatnonzero(np.r_[False, (obj[1:-1] == obj[:-2]) & (obj[1:-1] == obj[2:]), False])
        turn = ((x[inner] - x[inner - 1]) * (y[inner + 1] - y[inner - 1])
                - (y[inner] - y[inner - 1]) * (x[inner + 1] - x[inner - 1]))
        drop = inner[turn <= 0]
        if drop.size == 0:
            break
        keep = np.ones(x.size, dtype=bool)
        keep[drop] = False
        x, y, obj = x[keep], y[keep], obj[keep]
    return x, y, obj


def _sorted_by_column(gx: np.ndarray, gy: np.ndarray, obj: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points ordered by (object, x, y): one sort of packed int64 keys (three times faster than a
    ``lexsort`` of the three columns), or the ``lexsort`` where the keys would not fit."""
    x0, y0 = int(gx.min()), int(gy.min())
    sx, sy = int(gx.max()) - x0 + 1, int(gy.max()) - y0 + 1
    if float(sx) * sy * (float(obj.max()) + 1.0) >= 2.0 ** 62:
        order = np.lexsort((gy, gx, obj))
        return gx[order], gy[order], obj[order]
    key = sort_keys((obj * sx + (gx - x0)) * sy + (gy - y0))
    obj, rest = np.divmod(key, sx * sy)
    x, y = np.divmod(rest, sy)
    return x + x0, y + y0, obj


def convex_hulls(gx: np.ndarray, gy: np.ndarray, obj: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each object's convex hull of integer points (``gx``, ``gy``): its vertices counter-clockwise, sorted by
    object, as (x, y, object).  No vertex repeats; a hull of one point is that point, of collinear points
    their two ends.

    Andrew's monotone chains on each grid column's lowest and highest point (one sort), each chain cut
    down by :func:`_chain` for all objects at once; integer cross products are exact.
    """
    if gx.size == 0:
        return gx, gy, obj
    gx, gy, obj = _sorted_by_column(gx, gy, obj)
    new = np.r_[True, (gx[1:] != gx[:-1]) | (obj[1:] != obj[:-1])]
    first = np.flatnonzero(new)
    last = np.r_[first[1:] - 1, gx.size - 1]
    # lower chain: each column's lowest point, left to right; upper chain: each column's highest, right to left
    lx, ly, lo = _chain(gx[first], gy[first], obj[first])
    ux, uy, uo = _chain(gx[last][::-1], gy[last][::-1], obj[last][::-1])
    x, y, o = np.r_[lx, ux], np.r_[ly, uy], np.r_[lo, uo]
    part = np.r_[np.zeros(lx.size, np.int64), np.ones(ux.size, np.int64)]
    order = np.lexsort((np.r_[lx, -ux], part, o))  # per object: the lower chain, then the upper one
    x, y, o = x[order], y[order], o[order]
    # an end column of a single point ends one chain and starts the other: keep it once
    first_of = np.r_[True, o[1:] != o[:-1]]
    last_of = np.r_[o[1:] != o[:-1], True]
    head = np.flatnonzero(first_of)[np.cumsum(first_of) - 1]  # each vertex's object's first vertex
    same_as_previous = np.r_[False, (x[1:] == x[:-1]) & (y[1:] == y[:-1])] & ~first_of
    same_as_first = last_of & ~first_of & (x == x[head]) & (y == y[head])
    keep = ~same_as_previous & ~same_as_first
    return x[keep], y[keep], o[keep]


def min_area_angles(gx: np.ndarray, gy: np.ndarray, obj: np.ndarray, num_objects: int) -> np.ndarray:
    """Per object: the angle from the x axis of a side of the smallest-area rectangle around its integer
    points (``gx``, ``gy``), in (-pi, pi]; 0 for objects without points or with a single one.

    One side of that rectangle lies along an edge of the convex hull (Freeman and Shapira, 1975), so it
    is the best of the rectangles along the hull's edges: for each edge the hull vertices farthest
    ahead, behind and away from it, found by rotating calipers, here a sorted search of the edges'
    outward normals (each vertex is the farthest in the directions between the normals of its two
    edges).  All objects at once; cost O(h log h) on h hull vertices.
    """
    k = num_objects
    angle = np.zeros(k)
    x, y, o = convex_hulls(gx.astype(np.int64), gy.astype(np.int64), obj.astype(np.int64))
    counts = np.bincount(o, minlength=k)
    start = segment_starts(o, k)
    nxt = np.arange(1, x.size + 1)
    wrap = np.r_[o[1:] != o[:-1], True] if x.size else np.zeros(0, dtype=bool)
    nxt[wrap] = start[o[wrap]]
    edge = np.flatnonzero(counts[o] > 1)  # edge i runs from vertex i to vertex nxt[i]
    if edge.size == 0:
        return angle
    e = o[edge]
    ex, ey = x[nxt[edge]] - x[edge], y[nxt[edge]] - y[edge]
    theta = np.arctan2(ey, ex)
    # the outward normal (theta - pi/2) of each edge, as an angle past its object's first edge's normal:
    # rising along a counter-clockwise hull, within [0, 2 pi)
    base = np.zeros(k)
    base[o[start[counts > 1]]] = theta[np.searchsorted(edge, start[counts > 1])] - np.pi / 2.0
    turn = 2.0 * np.pi
    normal = np.mod(theta - np.pi / 2.0 - base[e], turn)
    normal[np.searchsorted(edge, start[counts > 1])] = 0.0
    key = e * (2.0 * turn) + normal  # sorted: objects ascending, then the normals

    def farthest(direction: np.ndarray) -> np.ndarray:
        """Per edge: the vertex of its object's hull farthest in ``direction`` (angles)."""
        rel = np.mod(direction - base[e], turn)
        j = np.searchsorted(key, e * (2.0 * turn) + rel) - np.searchsorted(e, e)  # edges whose normal comes first
        return start[e] + np.mod(j, counts[e])

    ahead, behind, away = farthest(theta), farthest(theta + np.pi), farthest(theta + np.pi / 2.0)
    length2 = ex.astype(np.float64) ** 2 + ey.astype(np.float64) ** 2
    along = (x[ahead] - x[behind]) * ex + (y[ahead] - y[behind]) * ey  # x |e|
    across = (y[away] - y[edge]) * ex - (x[away] - x[edge]) * ey  # x |e|
    area = along.astype(np.float64) * across / length2
    best = np.lexsort((edge, area, e))
    head = best[np.r_[True, e[best][1:] != e[best][:-1]]]
    angle[e[head]] = theta[head]
    return angle


def _footprint_angle(points: np.ndarray, obj: np.ndarray, k: int, frame: _UpFrame, cell: float) -> np.ndarray:
    """Per object: the angle from h1 of a side of the smallest-area rectangle around its footprint, the
    points' horizontal coordinates on a grid of ``cell`` (:func:`min_area_angles`); 0 for objects without
    points."""
    x, y = frame.horizontal(points)
    return min_area_angles(np.floor(x / cell).astype(np.int64), np.floor(y / cell).astype(np.int64), obj, k)


def _lattice_angle(samples: "SolidSamples", k: int, frame: _UpFrame) -> np.ndarray:
    """:func:`_footprint_angle` of the solid samples on their own grid (their sub-cell indices: exact)."""
    i1, i2 = int(np.argmax(np.abs(frame.h1))), int(np.argmax(np.abs(frame.h2)))
    lattice = samples.lattice
    gx = lattice[:, i1] * int(np.sign(frame.h1[i1]))
    gy = lattice[:, i2] * int(np.sign(frame.h2[i2]))
    return min_area_angles(gx, gy, samples.object, k)


def _local(points: np.ndarray, obj: np.ndarray, cos: np.ndarray, sin: np.ndarray, frame: _UpFrame) -> np.ndarray:
    """Coordinates of each point along its object's box axes (major, minor = up x major, up)."""
    x, y = frame.horizontal(points)
    c, s = cos[obj], sin[obj]
    return np.stack([x * c + y * s, y * c - x * s, points[:, frame.axis] * frame.u[frame.axis]], axis=1)


def _quaternions(angle: np.ndarray, frame: _UpFrame) -> np.ndarray:
    """[x, y, z, w] of the turns by ``angle`` about ``frame``'s up axis from the frame (h1, h2, up): the frame's
    quaternion times the turn's, (v, w) * (0, 0, s, c) = (c v + s (v x e3) + s w e3, c w - s v3)."""
    v = Rotation.from_matrix(np.stack([frame.h1, frame.h2, frame.u], axis=1)).as_quat()
    s, c = np.sin(angle / 2.0), np.cos(angle / 2.0)
    quaternion = np.stack([c * v[0] + s * v[1], c * v[1] - s * v[0], c * v[2] + s * v[3], c * v[3] - s * v[2]], axis=1)
    quaternion[quaternion[:, 3] < 0] *= -1.0  # one of the two: w >= 0
    return quaternion


def _boxes(lo: np.ndarray, hi: np.ndarray, angle: np.ndarray,
           frame: _UpFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres, sizes [long, short, vertical] and rotations (columns: box axes) of boxes spanning
    ``lo``..``hi`` along the axes at ``angle``; the longer footprint side is named first."""
    major = np.cos(angle)[:, None] * frame.h1 + np.sin(angle)[:, None] * frame.h2
    minor = np.cross(frame.u, major)  # major x minor = up: a proper rotation
    rotation = np.stack([major, minor, np.broadcast_to(frame.u, major.shape)], axis=2)
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


def oriented_boxes(points: np.ndarray, obj: np.ndarray, num_objects: int, up: tuple[int, float],
                   cell: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes around each object's points (sorted by object), turned about the world axis ``up`` = (index, sign)
    along a side of the smallest-area rectangle around the points' footprint, taken on a grid of ``cell``
    (default: a 1024th of the points' largest extent).  The boxes span all the points: the grid only
    chooses the turn.

    Returns centres (K, 3), sizes (K, 3) [long, short, vertical] and rotation matrices (K, 3, 3)
    whose columns are the box axes in the world; NaN for objects without points.
    """
    frame = _UpFrame.of(up)
    if cell is None:
        span = float(np.ptp(points, axis=0).max()) if points.shape[0] else 0.0
        cell = span / 1024.0 if span > 0 else 1.0
    angle = _footprint_angle(points, obj, num_objects, frame, cell)
    local = _local(points, obj, np.cos(angle), np.sin(angle), frame)
    lo = segment_min(local, obj, num_objects, empty=np.nan)
    hi = segment_max(local, obj, num_objects, empty=np.nan)
    return _boxes(lo, hi, angle, frame)


@dataclass
class SolidSamples:
    """Each object's solid sub-cell samples in its largest connected set of voxels, sorted by object."""

    points: np.ndarray  # (M, 3) sample centres, bundle units
    object: np.ndarray  # (M,) int64, ascending
    cell: np.ndarray  # (M, 3) int64 voxel of each sample
    sub: np.ndarray  # (M, 3) int64 sub-cell of each sample within its voxel, 0 .. subdivisions - 1
    spacing: float  # sub-cell edge, bundle units
    subdivisions: int

    @property
    def lattice(self) -> np.ndarray:
        """(M, 3) the sub-cell grid index of each sample: floor(position / spacing + subdivisions / 2)."""
        return self.cell * self.subdivisions + self.sub


def solid_samples(occupancy: ShadowOccupancy | None, seg_object: np.ndarray, voxel_size: float,
                  unit_scale: float) -> SolidSamples | None:
    """The solid samples of every object's largest 26-connected set of owned voxels (by solid share).

    None without an occupancy (no shadows or no depth images).
    """
    if occupancy is None or occupancy.cell.shape[0] == 0 or occupancy.solid_samples is None:
        return None
    owner = seg_object[occupancy.segment]
    kept = _largest_components(occupancy.cell, np.where(occupancy.solid > 0, owner, -1), occupancy.solid)
    cells = np.flatnonzero(kept)
    cells = cells[np.argsort(owner[cells], kind="stable")]
    cell_row, sample = np.nonzero(occupancy.solid_samples[cells])
    cell = occupancy.cell[cells][cell_row]
    n = round(occupancy.samples ** (1.0 / 3.0))
    sub = np.rint((occupancy.offsets + 0.5) * n - 0.5).astype(np.int64)  # sub-cell of each sample in its voxel
    points = (cell + occupancy.offsets[sample]) * (voxel_size / unit_scale)
    return SolidSamples(points, owner[cells][cell_row], cell, sub[sample], voxel_size / unit_scale / n, n)


def _largest_components(cell: np.ndarray, owner: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Per cell: whether it lies in its owner's largest (by ``weight``) 26-connected set of cells of that
    owner; False for cells without an owner (< 0)."""
    kept = np.zeros(cell.shape[0], dtype=bool)
    idx = np.flatnonzero(owner >= 0)
    if idx.size == 0:
        return kept
    key, steps = _linear_keys(owner[idx], cell[idx], margin=1)
    # The graph is built on the cells in key order: every shifted copy of the sorted keys is sorted
    # too, and a search for sorted needles walks the keys in order (several times faster than for
    # needles in arbitrary order).
    order = argsort_keys(key)
    idx = idx[order]
    sorted_key = key[order]
    rows, cols = [], []
    for dx, dy, dz in _HALF_NEIGHBOURS:  # each undirected edge once
        target = sorted_key + (dx * steps[0] + dy * steps[1] + dz * steps[2])
        j = np.minimum(np.searchsorted(sorted_key, target), idx.size - 1)
        hit = sorted_key[j] == target
        rows.append(np.flatnonzero(hit))
        cols.append(j[hit])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(r.size, dtype=np.int8), (r, c)), shape=(idx.size, idx.size))
    _, component = connected_components(graph, directed=False)
    mass = np.bincount(component, weights=weight[idx])
    component_owner = np.zeros(mass.size, dtype=np.int64)
    component_owner[component] = owner[idx]
    # per owner the heaviest component; between equal masses the one holding the lowest cell, so the
    # choice depends on neither the order of the graph's nodes nor the sort's stability
    lowest_cell = np.full(mass.size, cell.shape[0], dtype=np.int64)
    np.minimum.at(lowest_cell, component, idx)
    ranked = np.lexsort((lowest_cell, -mass, component_owner))
    first = ranked[np.r_[True, component_owner[ranked][1:] != component_owner[ranked][:-1]]]
    best = np.zeros(mass.size, dtype=bool)
    best[first] = True
    kept[idx] = best[component]
    return kept


#: The 13 neighbour offsets of a 26-neighbourhood that come after (0, 0, 0) in lexicographic order.
_HALF_NEIGHBOURS = [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1) if (dx, dy, dz) > (0, 0, 0)]
_NEIGHBOURS = [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)]


def _linear_keys(group: np.ndarray, cells: np.ndarray, margin: int,
                 low: np.ndarray | None = None, high: np.ndarray | None = None) -> tuple[np.ndarray, tuple[int, int, int]]:
    """int64 keys of (group, cell) in which a step of one cell along an axis adds a fixed amount
    (returned), for cells up to ``margin`` beyond ``low``..``high`` (default: the cells' bounds)."""
    low = cells.min(axis=0) if low is None else low
    high = cells.max(axis=0) if high is None else high
    lo = low - margin
    span = (high + margin) - lo + 1
    if float(span.prod()) * (float(group.max(initial=0)) + 1.0) >= 2.0 ** 62:
        raise ValueError("the objects' voxels span too large a grid for 64-bit keys")
    steps = (int(span[1] * span[2]), int(span[2]), 1)
    q = cells - lo
    return group * int(span.prod()) + q[:, 0] * steps[0] + q[:, 1] * steps[1] + q[:, 2], steps


def _near_samples(points: np.ndarray, obj: np.ndarray, samples: SolidSamples) -> np.ndarray:
    """Per point: whether a solid sample of its object lies in its sub-cell or one of the 26 around it."""
    near = np.zeros(points.shape[0], dtype=bool)
    if points.shape[0] == 0 or samples.points.shape[0] == 0:
        return near
    q = np.floor(points / samples.spacing + samples.subdivisions / 2.0).astype(np.int64)
    n = samples.subdivisions
    low = np.array([samples.cell[:, i].min() for i in range(3)]) * n  # column by column: contiguous reductions
    high = np.array([samples.cell[:, i].max() for i in range(3)]) * n + n - 1
    within = np.flatnonzero(np.all((q >= low - 1) & (q <= high + 1), axis=1))
    if within.size == 0:
        return near
    sample_key, steps = _linear_keys(samples.object, samples.lattice, 2, low, high)
    sample_key = sort_keys(sample_key)
    key, _ = _linear_keys(obj[within], q[within], 2, low, high)  # neighbours stay on the grid
    order = argsort_keys(key)  # sorted needles: each search walks the samples' keys in order
    key = key[order]
    found = np.zeros(within.size, dtype=bool)
    for dx, dy, dz in _NEIGHBOURS:
        target = key + (dx * steps[0] + dy * steps[1] + dz * steps[2])
        j = np.minimum(np.searchsorted(sample_key, target), sample_key.size - 1)
        found |= sample_key[j] == target
    near[within[order]] = found
    return near


def _nan_segment_reduce(ufunc: np.ufunc, values: np.ndarray, segment: np.ndarray, k: int) -> np.ndarray:
    """Per-segment ``np.fmin`` / ``np.fmax`` of rows sorted by segment, skipping NaN; NaN for empty segments."""
    out = np.full((k,) + values.shape[1:], np.nan)
    count = np.bincount(segment, minlength=k)
    nonempty = count > 0
    if values.shape[0]:
        out[nonempty] = ufunc.reduceat(values, segment_starts(segment, k)[nonempty], axis=0)
    return out


def one_view_cells(occupancy: ShadowOccupancy, seg_object: np.ndarray, segment_view: np.ndarray,
                   object_views: np.ndarray) -> np.ndarray:
    """Per occupancy cell: whether only one view's segments of the cell's object cast a shadow over it,
    while the object has segments in more than one view.

    A rock's inside lies behind its surface in every view that sees it, so the shadows of its
    segments in several views reach it.  A cell only one view's shadow of the object reaches lies
    behind the rock in that view alone; if every other view's line of sight to it is blocked by
    other rocks, no view rules it out, yet on generated rock fields most such space lies outside
    the rock (the rock's far side, hidden from every view).
    """
    owner = seg_object[occupancy.segment]
    if occupancy.member_cell is None or owner.size == 0:
        return np.zeros(owner.size, dtype=bool)
    cell, seg = occupancy.member_cell, occupancy.member_segment
    own = (seg_object[seg] == owner[cell]) & (owner[cell] >= 0)
    # One view at most: the lowest and the highest view of the cell's own shadows are the same (an
    # unsorted scatter, linear in the members; a sort of the (cell, view) pairs took several times longer).
    cell, view = cell[own], segment_view[seg[own]]
    lowest = np.full(owner.size, np.iinfo(np.int64).max)
    highest = np.full(owner.size, -1, dtype=np.int64)
    np.minimum.at(lowest, cell, view)
    np.maximum.at(highest, cell, view)
    return (owner >= 0) & (highest <= lowest) & (object_views[np.maximum(owner, 0)] > 1)


def object_volumes(occupancy: ShadowOccupancy | None, seg_object: np.ndarray, num_objects: int, voxel_size: float,
                   unit_scale: float, relative_std: float = 0.0, one_view: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Volume and its standard deviation per object (bundle units^3); NaN where none was measured.

    ``one_view`` (per occupancy cell, :func:`one_view_cells`): cells that one view's evidence
    alone leaves solid count half, with the other half as uncertainty - as the share that one
    view's background alone rules out.
    """
    k = num_objects
    if occupancy is None or occupancy.cell.shape[0] == 0:
        return np.full(k, np.nan), np.full(k, np.nan)
    obj = seg_object[occupancy.segment]
    owned = obj >= 0
    weak = np.zeros(obj.size, dtype=bool) if one_view is None else one_view
    obj, single, weak = obj[owned], occupancy.single_view[owned], weak[owned]
    # One view's evidence alone - its background in front of a sample, or its shadow alone over a
    # cell - counts half solid, and the other half goes into the uncertainty.
    full = np.where(weak, 0.0, occupancy.solid[owned])
    half = single + np.where(weak, occupancy.solid[owned], 0.0)
    solid = full + half / 2.0
    cell_volume = (voxel_size / unit_scale) ** 3
    volume = np.bincount(obj, weights=solid, minlength=k) * cell_volume
    uncertain = np.bincount(obj, weights=half, minlength=k) * cell_volume
    sampling_var = np.bincount(obj, weights=solid * (1.0 - solid) / occupancy.samples, minlength=k) * cell_volume ** 2
    std = np.sqrt((uncertain / 2.0) ** 2 + sampling_var + (relative_std * volume) ** 2)
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
            if np.isfinite(geometry.extent_min[i]).all() else None,
            "num_views": int(geometry.num_views[i]),
            "num_points": int(geometry.num_points[i]),
        }))
    return out


#: How far (sub-cells) an object's box reaches below the lowest surface point it spans: the part of a
#: rock set into the ground.  On generated rock fields (rocks sunk 5 cm, sub-cells of 4 cm, exact images,
#: ``benchmarks/bench_geometry.py``) 1 took the boxes within 1.5x of the true box from 97.7 to 98.1 % of
#: the objects of 30 scenes (95th percentile 1.36 -> 1.29); on 10 scenes the boxes' height went from 1.16
#: to 1.10 of the true one at the 95th percentile, with the median at 1.00 -> 0.99, where 0 cut it to 0.94.
_FLOOR_ALLOWANCE = 1.0


def object_geometry(cloud: ObjectPoints, occupancy: ShadowOccupancy | None, seg_object: np.ndarray,
                    segment_view: np.ndarray, segment_points: np.ndarray, poses: np.ndarray, unit_scale: float,
                    config: ShadowCorrConfig) -> ObjectGeometry:
    """Oriented box, volume, seen extent and counts of every object of ``cloud``.

    ``segment_points`` counts each segment's cleaned points (a view without any adds no view);
    ``poses`` (V, 4, 4) are the views' camera-to-world poses, for ``up_axis`` ``auto``.
    """
    k = cloud.num_objects
    frame = _UpFrame.of(world_up(poses, config.up_axis))
    seen = (seg_object >= 0) & (segment_points > 0)
    pairs = np.unique(seg_object[seen] * (int(segment_view.max(initial=0)) + 1) + segment_view[seen])
    num_views = np.bincount(pairs // (int(segment_view.max(initial=0)) + 1), minlength=k)
    one_view = None if occupancy is None else one_view_cells(occupancy, seg_object, segment_view, num_views)
    samples = solid_samples(occupancy, seg_object, config.voxel_size, unit_scale)
    points, obj = cloud.points, cloud.object
    rejected = np.zeros(0, dtype=np.int64)
    # the footprint's grid: the solid samples' (fused points are snapped to it too)
    cell = config.voxel_size / unit_scale / config.volume_subdivisions
    if samples is None or samples.points.shape[0] == 0:
        angle = _footprint_angle(points, obj, k, frame, cell)
        local = _local(points, obj, np.cos(angle), np.sin(angle), frame)
        lo = segment_min(local, obj, k, empty=np.nan)
        hi = segment_max(local, obj, k, empty=np.nan)
    else:
        has_samples = np.bincount(samples.object, minlength=k) > 0
        angle = _lattice_angle(samples, k, frame)
        if not has_samples.all():
            angle = np.where(has_samples, angle, _footprint_angle(points, obj, k, frame, cell))
        cos, sin = np.cos(angle), np.sin(angle)
        pad = samples.spacing / 2.0
        local_samples = _local(samples.points, samples.object, cos, sin, frame)
        lo = segment_min(local_samples, samples.object, k, empty=np.nan) - pad
        hi = segment_max(local_samples, samples.object, k, empty=np.nan) + pad
        # A point inside its object's box of solid samples cannot widen it; one outside must lie within a
        # sub-cell of a solid sample of its object (objects without solid samples keep all their points).
        local = _local(points, obj, cos, sin, frame)
        counts = np.bincount(obj, minlength=k)
        low = np.where(has_samples[:, None], lo, np.inf)
        high = np.where(has_samples[:, None], hi, -np.inf)
        outside = np.zeros(points.shape[0], dtype=bool)
        for axis in range(3):  # per axis on contiguous columns; the bounds repeated along the sorted points
            column = local[:, axis]
            outside |= (column < np.repeat(low[:, axis], counts)) | (column > np.repeat(high[:, axis], counts))
        candidates = np.flatnonzero(outside)
        near = _near_samples(points[candidates], obj[candidates], samples)
        accepted, rejected = candidates[near], candidates[~near]
        lo = np.fmin(lo, segment_min(local[accepted], obj[accepted], k, empty=np.nan))
        hi = np.fmax(hi, segment_max(local[accepted], obj[accepted], k, empty=np.nan))
        # The box's floor: beneath a rock, below where it meets the visible ground, lies ground that every
        # view's line of sight passes through the rock to reach, so no view rules it out; the box ends at
        # the lowest surface point it spans, less _FLOOR_ALLOWANCE sub-cells for a rock set into the ground.
        spanned = np.ones(points.shape[0], dtype=bool)
        spanned[rejected] = False
        lowest_seen = segment_min(local[spanned, 2:], obj[spanned], k, empty=np.nan)[:, 0]
        lo[:, 2] = np.fmax(lo[:, 2], lowest_seen - _FLOOR_ALLOWANCE * samples.spacing)
        # objects without solid samples: their points alone
        lo = np.where(has_samples[:, None], lo, segment_min(local, obj, k, empty=np.nan)) if not has_samples.all() else lo
        hi = np.where(has_samples[:, None], hi, segment_max(local, obj, k, empty=np.nan)) if not has_samples.all() else hi
    center, size, rotation = _boxes(lo, hi, angle, frame)
    quaternion = _quaternions(np.arctan2(rotation[:, :, 0] @ frame.h2, rotation[:, :, 0] @ frame.h1), frame)
    quaternion[~np.isfinite(size).all(axis=1)] = np.nan
    volume, volume_std = object_volumes(occupancy, seg_object, k, config.voxel_size, unit_scale,
                                        config.volume_relative_std, one_view)
    seen = points
    if rejected.size:  # the extent spans the points the box spans: rejected rows drop out of the reductions
        seen = points.copy()
        seen[rejected] = np.nan
    return ObjectGeometry(
        center=center, size=size, quaternion=quaternion, volume=volume, volume_std=volume_std,
        extent_min=_nan_segment_reduce(np.fmin, seen, obj, k),
        extent_max=_nan_segment_reduce(np.fmax, seen, obj, k),
        num_points=cloud.counts, num_views=num_views,
    )
