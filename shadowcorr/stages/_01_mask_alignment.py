"""Stage 1 (optional, ``pose_mask_alignment``): turn the views that registration leaves unverified to the other views' masks.

Depth registration (:mod:`._01_poses`) needs surface that two views share.  Cameras low over a
rock field (under a metre high, pitched a few degrees down) share little of it: the ground is
seen at grazing incidence and each camera sees the near side of the rocks, so their pairs overlap
on a few per cent of their samples and most views stay ``not_registered`` with the declared
error.  At 1615 px focal length, 1 degree moves a landing by 28 px, several times what the surface
evidence tolerates, and rocks fall apart into one object per view.

The masks still say where the rocks are.  A rock pixel of view ``i`` (mask set, valid depth),
placed in the world with ``i``'s pose and projected into view ``j``, should land on some mask of
``j``, whichever; under a rotation error it lands beside it.  Each view's correction is a small
rotation about its own camera centre (the rotation dominates: 2.5 cm of position error moves a
landing 5 m away by 8 px, 1 degree by 28 px).  The rotations minimise the sum over all such
landings of the squared pixel distance beyond the masks' outline of the view they land in (a
chamfer distance, from a Euclidean distance transform of every mask at half resolution; a
landing within one sample of the outline counts as on it, :func:`_off_mask`):

* a landing farther than ``_REACH_PX`` from any mask says nothing (a rock that the other view's
  segmenter dropped, or that lies outside its frame), nor does one that lands behind a nearer
  surface there (``_HIDDEN_SHARE``: hidden in that view, it may sit beside the mask of its
  occluder);
* Gauss-Newton on the rotations of the views to move (three unknowns each; the landing moves
  with the projection's Jacobian times ``delta_i x (X - c_i)`` for the view it comes from and
  ``-delta_j x (X - c_j)`` for the view it lands in), with a prior of ``_PRIOR_DEG`` per view;
  the views that registration bore out stay where they are, and when every view moves their
  mean rotation stays zero (a common turn of every camera is invisible in the images);
* at most ``_ITERATIONS`` steps, until no view turns by more than ``_CONVERGED_DEG``.

Measured on the quality benchmark (``benchmarks/bench_quality.py``, 30 scenes per cell): on the
low rig (``syn:4v-low``) the average purity under the ``mild`` errors rises from 98.51 to 98.95,
under ``field`` from 95.74 to 97.43 and under ``harsh`` from 88.39 to 93.57; the clean row goes
from 99.66 to 99.64 (one scene of 30 loses 0.9); the other 106 rows do not move.  Under 1
degree / 2.5 cm of pose error alone, the eight scenes of that rig that lost most rise from 96.79
to 99.58 (99.69 with exact poses), their views' relative rotation error falling from a median 1.5
to about 0.3 degrees.  With exact poses the rig's unregistered views still turn, by a median 0.10
degrees and at most 0.35 (``benchmarks/bench_poses.py``).  Views that registration left
``not_confirmed`` are not moved (``_01_poses``): their poses are often exact and their depth
noisy (under 2 % depth noise the alignment turned such views by about 3 degrees).

Work: the rock pixels on a grid of about ``_SAMPLED_PIXELS`` per view, and per step every ordered
pair of views of which one moves and whose frustum the other's rocks reach (views of separate
places never meet): 0.3-0.5 s of CPU time on a scene of the low rig (four 1080p views, one to
four of them turned), where registration itself takes about 0.12 s.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial.transform import Rotation

from ..bundle import View
from ._01_registration import sampling_stride
from ._03_surface_evidence import _frustum_candidates

#: Rock pixels sampled per view (a regular grid over the image, kept where the mask is set).
_SAMPLED_PIXELS = 60_000
#: The distance transform of each mask is taken at this fraction of the image's resolution.
_FIELD_STRIDE = 2
#: Landings farther than this from every mask of the view (pixels of the full image) say nothing.
_REACH_PX = 10.0
#: A landing whose view sees a surface nearer than this share of its depth is hidden there.
_HIDDEN_SHARE = 0.15
#: Prior on each view's rotation error (degrees): the size of the error the stage corrects.
_PRIOR_DEG = 1.0
_ITERATIONS = 15
_CONVERGED_DEG = 0.005


def _rock_points(view: View, max_depth: float) -> np.ndarray:
    """(N, 3) camera-frame points of the view's masked pixels with valid depth, on a regular grid."""
    height, width = view.depth.shape
    stride = sampling_stride(height, width, _SAMPLED_PIXELS)
    z = np.asarray(view.depth[::stride, ::stride], dtype=np.float64)
    rows, cols = np.mgrid[0:height:stride, 0:width:stride]
    keep = (np.asarray(view.mask[::stride, ::stride]) > 0) & (z > 0) & (z <= max_depth)  # False for NaN
    z, rows, cols = z[keep], rows[keep], cols[keep]
    k = view.intrinsics
    return np.stack([(cols - k.cx) * z / k.fx, (rows - k.cy) * z / k.fy, z], axis=1)


def _distance_field(view: View) -> np.ndarray:
    """Each ``_FIELD_STRIDE``-th pixel's distance to the nearest mask pixel, in full-image pixels."""
    outside = np.asarray(view.mask[::_FIELD_STRIDE, ::_FIELD_STRIDE]) == 0
    return distance_transform_edt(outside) * _FIELD_STRIDE


def _off_mask(field: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far landings at pixel coordinates (u, v) lie beyond the masks' outline, and its derivatives by u and v.

    The field is read bilinearly between its samples.  The outline lies half a sample beyond the
    last mask sample, and a landing within another half sample of it counts as on the mask: the
    sampled outline is that uncertain, and with exact poses about one landing in twenty lies
    there, every one on the side of the view it comes from - a pull that turned every view of a
    scene by a third of a degree when they all moved.  A landing on the mask is at distance 0."""
    s = _FIELD_STRIDE
    rows, cols = field.shape
    fr = np.clip(v / s, 0.0, rows - 1.000001)
    fc = np.clip(u / s, 0.0, cols - 1.000001)
    r0 = np.minimum(fr.astype(np.int64), rows - 2) if rows > 1 else np.zeros(fr.shape, np.int64)
    c0 = np.minimum(fc.astype(np.int64), cols - 2) if cols > 1 else np.zeros(fc.shape, np.int64)
    r1, c1 = np.minimum(r0 + 1, rows - 1), np.minimum(c0 + 1, cols - 1)
    ar, ac = fr - r0, fc - c0
    d00, d01, d10, d11 = field[r0, c0], field[r0, c1], field[r1, c0], field[r1, c1]
    distance = (1 - ar) * ((1 - ac) * d00 + ac * d01) + ar * ((1 - ac) * d10 + ac * d11)
    by_u = ((1 - ar) * (d01 - d00) + ar * (d11 - d10)) / s
    by_v = ((1 - ac) * (d10 - d00) + ac * (d11 - d01)) / s
    return distance - s, by_u, by_v


def _cross_matrices(a: np.ndarray) -> np.ndarray:
    """(N, 3, 3) [a]x of each row: [a]x b = a x b."""
    out = np.zeros((a.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -a[:, 2], a[:, 1]
    out[:, 1, 0], out[:, 1, 2] = a[:, 2], -a[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -a[:, 1], a[:, 0]
    return out


def _pair_terms(points: np.ndarray, source_centre: np.ndarray, view: View, pose: np.ndarray, field: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The landings of world ``points`` (of a view centred at ``source_centre``) in ``view``: their
    capped distances to its masks and the distances' derivatives by the source's and the view's
    rotations ((M,), (M, 3), (M, 3)); None with too few landings."""
    k, (height, width) = view.intrinsics, view.depth.shape
    rotation, centre = pose[:3, :3], pose[:3, 3]
    cam = (points - centre) @ rotation
    z = cam[:, 2]
    ahead = z > 1e-9
    safe = np.where(ahead, z, 1.0)
    u, v = k.fx * cam[:, 0] / safe + k.cx, k.fy * cam[:, 1] / safe + k.cy
    # Pixel (r, c) is centred on (v, u) = (r, c): a landing reads the depth of its nearest pixel.
    inside = np.flatnonzero(ahead & (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5))
    if inside.size == 0:
        return None
    row, col = np.rint(v[inside]).astype(np.int64), np.rint(u[inside]).astype(np.int64)
    seen = view.depth[row, col].astype(np.float64)  # the landings' pixels only, not the whole image
    hidden = (seen > 0) & (seen < (1.0 - _HIDDEN_SHARE) * z[inside])
    distance, d_col, d_row = _off_mask(field, u[inside], v[inside])
    use = (distance > 0) & (distance < _REACH_PX) & ~hidden
    if use.sum() < 20:
        return None
    at = inside[use]
    x, y, zz = cam[at, 0], cam[at, 1], cam[at, 2]
    # d(u, v) / d(camera point), then by the world point: (M, 2, 3)
    jac = np.zeros((at.size, 2, 3))
    jac[:, 0, 0], jac[:, 0, 2] = k.fx / zz, -k.fx * x / zz ** 2
    jac[:, 1, 1], jac[:, 1, 2] = k.fy / zz, -k.fy * y / zz ** 2
    jac = jac @ rotation.T
    by_point = np.einsum("mk,mkl->ml", np.stack([d_col[use], d_row[use]], axis=1), jac)
    world = points[at]
    # The source's turn delta moves a point by delta x (X - c_source) = -[X - c_source]x delta; the
    # view's turn moves what it sees as if the world turned by -delta about its centre.
    by_source = np.einsum("ml,mln->mn", by_point, -_cross_matrices(world - source_centre))
    by_view = np.einsum("ml,mln->mn", by_point, _cross_matrices(world - centre))
    return distance[use], by_source, by_view


def _bounding_sphere(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Centre (3,) and radius (1-element array) of a sphere around ``points``; None without any."""
    if points.shape[0] == 0:
        return None
    centre = points.mean(axis=0)
    return centre, np.array([np.sqrt(((points - centre) ** 2).sum(axis=1).max())])


def align_to_masks(views: Sequence[View], free: Sequence[int], max_depth: float) -> list[np.ndarray]:
    """Camera-to-world poses (OpenCV) of ``views`` with the views ``free`` turned about their camera
    centres so that every view's masked pixels land on the masks of the others (see the module
    docstring); the other views keep their poses.  ``max_depth`` in the views' units.  Views
    without depth, mask or intrinsics neither move nor take part."""
    poses = [np.array(v.pose, dtype=np.float64) for v in views]
    usable = [k for k, v in enumerate(views) if v.depth is not None and v.mask is not None and v.intrinsics is not None]
    moving = [k for k in free if k in usable]
    if not moving or len(usable) < 2:
        return poses
    column = {k: 3 * n for n, k in enumerate(moving)}
    unknowns = 3 * len(moving)
    points = {k: _rock_points(views[k], max_depth) for k in usable}
    # The ordered pairs (i, j) of which one moves and whose views can see each other's rocks at all
    # (a bounding sphere against a frustum): views of separate places never meet.
    world = {k: points[k] @ poses[k][:3, :3].T + poses[k][:3, 3] for k in usable}
    spheres = {k: _bounding_sphere(world[k]) for k in usable}
    pairs = [(i, j) for i in usable for j in usable
             if i != j and (i in column or j in column) and spheres[i] is not None
             and _frustum_candidates(spheres[i][0][None], spheres[i][1], poses[j][:3, :3], poses[j][:3, 3],
                                     views[j].intrinsics, views[j].depth.shape[1], views[j].depth.shape[0])[0]]
    fields = {k: _distance_field(views[k]) for k in {j for _, j in pairs}}
    prior = np.eye(unknowns) / np.deg2rad(_PRIOR_DEG) ** 2
    # Every view moving: the common turn is invisible, so the turns' mean is held at zero.
    gauge = np.tile(np.eye(3), len(moving)) if len(moving) == len(usable) else np.zeros((0, unknowns))
    total = np.zeros(unknowns)
    for _ in range(_ITERATIONS):
        hessian, gradient = prior.copy(), prior @ total
        world = {i: points[i] @ poses[i][:3, :3].T + poses[i][:3, 3] for i in {i for i, _ in pairs}}
        for i, j in pairs:
            terms = _pair_terms(world[i], poses[i][:3, 3], views[j], poses[j], fields[j])
            if terms is None:
                continue
            distance, by_source, by_view = terms
            blocks = [(column[i], by_source)] if i in column else []
            blocks += [(column[j], by_view)] if j in column else []
            for a, da in blocks:
                gradient[a:a + 3] += da.T @ distance
                for b, db in blocks:
                    hessian[a:a + 3, b:b + 3] += da.T @ db
        step = -np.linalg.solve(hessian + 1e6 * gauge.T @ gauge, gradient)
        total += step
        for k, c in column.items():
            turn = Rotation.from_rotvec(step[c:c + 3]).as_matrix()
            poses[k][:3, :3] = turn @ poses[k][:3, :3]
        if np.rad2deg(np.abs(step).max()) < _CONVERGED_DEG:
            break
    return poses
