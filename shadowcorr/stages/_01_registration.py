"""Stage 1, registration: one view's surface against another's (used by :mod:`._01_poses`).

Each view's *full* depth image is sampled on a regular pixel grid (``_SAMPLED_PIXELS``), each
sample's depth the mean of the ``pose_depth_window`` pixels around it on its surface
(:func:`depth_on_grid`), and back-projected with the declared pose into the centred world frame
(configuration units); the grid keeps the image layout, so normals come from grid neighbours and
any world point is matched with the surface by projecting it into the camera (``_Cloud``).
:func:`_candidate_pairs` picks the view pairs worth registering and :func:`_register` registers
one pair coarse to fine (small_gicp's GICP on thinned clouds, then point-to-plane Gauss-Newton by
projective association) and says whether the result can be trusted (``_Pair``; among others, it
must not fit the surfaces clearly worse than the declared poses).  The pose graph,
the bounds and the masks' confirmation that turn pairs into corrections are in :mod:`._01_poses`,
whose docstring describes the whole algorithm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import small_gicp
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import minimum_spanning_tree

from ..bundle import View
from ..config import ShadowCorrConfig
from ..ops import relative_depth_noise
from ._02_segments import back_project

#: Pixels sampled per view (a regular grid; about 1 in 100 of a 1080p image).
_SAMPLED_PIXELS = 20_000
#: Neighbours for small_gicp's per-point covariance estimate (coarse pass).
_COVARIANCE_NEIGHBOURS = 10
#: The coarse pass (small_gicp GICP) runs on clouds thinned to this many point spacings.
_COARSE_SPACING = 3.0
_COARSE_ITERATIONS = 20
#: Convergence of the coarse pass: a step rotating less than this (degrees) and moving less
#: than this share of the point spacing.
_COARSE_STOP_DEG = 0.05
_COARSE_STOP_SPACING = 1.0 / 32.0
#: Fine pass (point-to-plane, projective association): at most this many iterations per phase, and
#: a phase stops earlier once a step moves the surface by less than this share of the point spacing.
_FINE_ITERATIONS = 6
_FINE_STOP_SPACING = 1.0 / 200.0
#: Fine correspondence distance, in units of ``pose_point_spacing``.
_FINE_MATCH = 1.0
#: A grid neighbour further than this many times the sample spacing at its depth is across a
#: depth edge: no normal there.
_EDGE_RATIO = 4.0
#: Pixels of a depth window differing from the sample's own depth by more than this share of it lie on
#: another surface (across a depth edge) and are not averaged in (``depth_on_grid``).
_WINDOW_EDGE_SHARE = 0.1
#: A pair is degenerate when the weakest direction of its point-to-plane information carries
#: less than this share of the strongest (a flat or a cylindrical surface).
_MIN_CONSTRAINT_RATIO = 1e-3
#: A registration is not used when it fits the surfaces worse than this share of the declared
#: poses' fit (matched share over residual): with exact poses a right registration ties with them
#: within a few per cent, a wrong minimum on grazing ground reaches about half.
_DECLARED_FIT_SHARE = 0.95
#: Each view is registered with at most this many partners (those sharing the most surface),
#: plus whatever keeps the overlap graph connected: registrations grow linearly with the views.
_MAX_PARTNERS = 3
#: The fine pass moves every this many grid points per axis (and matches them against all).
_MOVING_STRIDE = 2
#: The fine pass's first steps move a quarter of those points, until a step moves less than this
#: many times the final stop (moving them all then shifts the result by about a centimetre anyway).
_QUARTER_STOP = 10.0
#: Under measured depth noise sigma (both surfaces together), fine matches reach this many sigma
#: and a registration may fit this many sigma (RMS) before it is refused.
_NOISE_MATCH = 3.0
_NOISE_RESIDUAL = 1.5
#: Normals span enough samples that depth noise tilts them by at most this much (radians),
#: but no more than this many samples either way (a wider reach loses detail and edge points).
_MAX_NORMAL_TILT = 0.1
_MAX_NORMAL_REACH = 6


@dataclass
class _Cloud:
    """One view's surface in the centred world frame (config units), coordinates in rows (3, N).

    ``grid``/``normal_grid`` keep the depth image's pixel-grid layout (flattened), so that a point
    is associated with this view's surface by projecting it into the camera (no search);
    ``points`` is every other grid point (the moving side of the fine pass); ``coarse`` is the
    thinned small_gicp cloud of the coarse pass.
    """

    grid: np.ndarray  # (3, h * w) points of the sampled pixel grid (NaN where the depth is invalid)
    normal_grid: np.ndarray  # (3, h * w) unit normals (NaN where unknown: invalid depth or a depth edge)
    shape: tuple[int, int]  # (h, w) of the grid
    points: np.ndarray  # (3, N) every other grid point (per axis) that has a normal
    normals: np.ndarray  # (3, N) their normals
    quarter: int  # the first this many of them are every other one per axis (a quarter)
    rotation: np.ndarray  # (3, 3) camera to world
    camera: np.ndarray  # (3, 1) camera centre
    projection: np.ndarray  # (fx, fy, cx, cy) onto grid indices: column = fx x / z + cx
    coarse: small_gicp.PointCloud
    coarse_tree: small_gicp.KdTree
    reach: float  # median distance of the surface from the camera: the lever of a rotation error
    cells: np.ndarray  # unique cell keys at the coarse match distance (overlap pre-check)
    depth_grid: np.ndarray  # (h * w,) z-depth of the grid samples in this camera (config units, NaN where invalid)
    noise: float  # the depth noise's standard deviation at the median depth, measured (config units)
    foreground: np.ndarray  # (h * w,) whether the mask has an instance at the grid sample
    interior: np.ndarray  # (h * w,) whether the sample's four grid neighbours are on its side of the mask


@dataclass
class _Pair:
    source: int
    target: int
    transform: np.ndarray  # (4, 4) centred frame: source surface -> target surface
    residual: float  # RMS point-to-plane, config units
    overlap: float  # share of the source's points within the fine match distance of the target's surface
    centre: np.ndarray  # (3,) centroid of the matched surface (centred frame)
    extent: float  # RMS distance of the matched surface from ``centre``: the lever of a rotation
    weight: float  # in the pose graph: overlap / residual, the residual floored at what registration resolves
    incidence: tuple[float, float]  # median degrees between each camera's rays and the matched surface


def sampling_stride(height: int, width: int, samples: int = _SAMPLED_PIXELS) -> int:
    """The stride of a regular pixel grid of about ``samples`` pixels per image (by default the
    registration's ``_SAMPLED_PIXELS``)."""
    return max(1, int(round(np.sqrt(height * width / samples))))


def depth_on_grid(depth: np.ndarray, stride: int, window: int, max_depth: float) -> np.ndarray:
    """(h, w) float64 depth of every ``stride``-th pixel from ``stride // 2`` (NaN where invalid),
    each the mean over the ``window`` x ``window`` pixels around it (at most the stride, odd) whose
    depth lies within ``_WINDOW_EDGE_SHARE`` of the sample's own.

    Registration reads depth at one pixel in ``stride`` x ``stride``; averaging the valid
    neighbours of a sample on the same surface divides independent depth noise by up to the
    window's width (a 5 x 5 window: 5 times) at no cost in resolution, while neighbours across a
    depth edge (another surface) and invalid ones stay out.  An invalid sample stays invalid.
    ``depth`` is read in float32, as a bundle holds it (float32 or float16).
    """
    height, width = depth.shape
    n_rows, n_cols = len(range(stride // 2, height, stride)), len(range(stride // 2, width, stride))
    # Bundle depth is float32 or float16, so every value is exact in float32: the comparisons below run on
    # it at half the memory traffic of float64 and decide as float64 would (see _at_most).
    depth = np.asarray(depth, dtype=np.float32)
    if n_rows * stride > height or n_cols * stride > width:  # a partial last block: NaN beyond the image
        padded = np.full((max(n_rows * stride, height), max(n_cols * stride, width)), np.nan, dtype=np.float32)
        padded[:height, :width] = depth
        depth = padded
    # (sample row, row in its block, sample column, column in its block): a view, no copy; the
    # window around a sample stays within its block (reach <= stride // 2).
    blocks = depth[:n_rows * stride, :n_cols * stride].reshape(n_rows, stride, n_cols, stride)
    half = stride // 2
    centre = blocks[:, half, :, half].astype(np.float64)
    centre[~((centre > 0) & (centre <= max_depth))] = np.nan  # False for NaN and infinities too
    reach = (min(window, stride) - 1) // 2
    if reach == 0:
        return centre
    # Every window pixel of every sample, read once into (row offset, column offset, sample row,
    # sample column) order: the strided reads fetch a window row's pixels together, and each offset's
    # samples are then one contiguous (h, w) plane.
    span = slice(half - reach, half + reach + 1)
    window_depth = np.ascontiguousarray(blocks[:, span, :, span].transpose(1, 3, 0, 2))
    centre32 = centre.astype(np.float32)
    with np.errstate(invalid="ignore"):
        # within a tenth of a valid centre's depth, so positive; False where either is NaN.  Between
        # float32 values within a factor of two of each other the difference is exact (Sterbenz), and
        # one further apart differs by more than a tenth in any rounding: float64 would decide the same.
        same = (np.abs(window_depth - centre32) <= _at_most(_WINDOW_EDGE_SHARE * centre)) \
            & (window_depth <= _at_most(np.float64(max_depth)))
    # The kept values lie within a tenth of the centre's depth (two binades at most): their float64 sum
    # is exact, in any order.
    total = np.zeros_like(centre)
    for dr in range(2 * reach + 1):
        for dc in range(2 * reach + 1):
            np.add(total, window_depth[dr, dc], out=total, where=same[dr, dc])
    count = same.view(np.uint8).sum(axis=(0, 1), dtype=np.uint16)  # bytes summed: several times a bool sum's speed
    return np.where(count > 0, total / np.maximum(count, 1.0), np.nan)


def _at_most(bound: np.ndarray | np.float64) -> np.ndarray:
    """The largest float32 at most ``bound`` (float64): for a float32 x, ``x <= bound`` exactly when
    ``x <= _at_most(bound)`` (NaN stays NaN)."""
    rounded = np.asarray(bound).astype(np.float32)
    return np.where(rounded > bound, np.nextafter(rounded, np.float32(-np.inf)), rounded)


def _view_grid(view: View, max_depth_bundle: float, window: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """A regular pixel grid of the view's depth: world points (bundle units) as (3, h, w) and
    z-depths as (h, w), both NaN where invalid; the grid's pixel rows and columns and its stride."""
    height, width = view.depth.shape
    stride = sampling_stride(height, width)
    rows = np.arange(stride // 2, height, stride)
    cols = np.arange(stride // 2, width, stride)
    depth = depth_on_grid(view.depth, stride, window, max_depth_bundle)
    vv = np.broadcast_to(rows[:, None].astype(np.float64), depth.shape)
    uu = np.broadcast_to(cols[None, :].astype(np.float64), depth.shape)
    grid = back_project(view, vv, uu, depth)  # per-axis arrays stacked on axis 1: (h, 3, w)
    return np.ascontiguousarray(grid.transpose(1, 0, 2)), depth, rows, cols, stride


def _grid_normals(grid: np.ndarray, depth: np.ndarray, camera: np.ndarray, spacing_per_depth: float,
                  reach: int = 1, edge_ratio: float = _EDGE_RATIO) -> np.ndarray:
    """(3, h, w) unit normals (facing the camera) of a (3, h, w) point grid from its central
    differences ``reach`` samples either way; NaN within ``reach`` of the border, next to invalid
    depth and across depth edges (neighbours further apart than ``edge_ratio`` sample spacings,
    ``spacing_per_depth`` x depth, per sample of reach)."""
    k = reach
    inner = (slice(None), slice(k, -k), slice(k, -k))
    along = grid[:, k:-k, 2 * k:] - grid[:, k:-k, :-2 * k]
    down = grid[:, 2 * k:, k:-k] - grid[:, :-2 * k, k:-k]
    limit = (2.0 * k * edge_ratio * spacing_per_depth * depth[k:-k, k:-k]) ** 2
    cross = np.stack([along[1] * down[2] - along[2] * down[1],
                      along[2] * down[0] - along[0] * down[2],
                      along[0] * down[1] - along[1] * down[0]])
    facing = np.einsum("i...,i...->...", camera[:, None, None] - grid[inner], cross)
    length = np.sqrt(np.einsum("i...,i...->...", cross, cross))
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = (np.einsum("i...,i...->...", along, along) < limit) & (np.einsum("i...,i...->...", down, down) < limit) \
            & (length > 0)
        scale = np.where(ok, np.sign(facing) / length, np.nan)
    normals = np.full(grid.shape, np.nan)
    normals[inner] = cross * scale
    return normals


def _normal_reach(median_depth: float, relative_noise: float, spacing_per_depth: float) -> int:
    """How many samples either way a normal is taken over, so that the depth noise tilts it by
    about a tenth of a radian at most (at the median depth): the difference of two samples
    ``2 reach`` apart carries sqrt(2) sigma of noise across ``2 reach`` sample spacings."""
    if not median_depth > 0:
        return 1
    noise_per_spacing = relative_noise * median_depth / spacing_per_depth  # sigma / spacing at that depth
    return int(np.clip(np.ceil(np.sqrt(2.0) * noise_per_spacing / (2.0 * _MAX_NORMAL_TILT)), 1, _MAX_NORMAL_REACH))


def _cell_keys(points: np.ndarray, cell: float) -> np.ndarray:
    idx = np.floor(points / cell).astype(np.int64) + (1 << 20)
    return np.unique((idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2])


def _coarse_match_distance(config: ShadowCorrConfig, reach: float) -> float:
    """How far the largest allowed pose error can move a surface point ``reach`` from its camera."""
    return max(4.0 * config.pose_point_spacing,
               config.pose_max_translation + reach * np.deg2rad(config.pose_max_rotation_deg))


def _mask_interior(foreground: np.ndarray) -> np.ndarray:
    """(h, w) whether a grid sample's four grid neighbours lie on the same side of the mask as it
    (inside a rock or inside the background, not on a mask's outline)."""
    same = np.ones(foreground.shape, dtype=bool)
    vertical, horizontal = foreground[1:, :] == foreground[:-1, :], foreground[:, 1:] == foreground[:, :-1]
    same[1:, :] &= vertical
    same[:-1, :] &= vertical
    same[:, 1:] &= horizontal
    same[:, :-1] &= horizontal
    return same


def _make_cloud(view: View, sampled: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int], centre: np.ndarray,
                scale: float, config: ShadowCorrConfig, edge_ratio: float = _EDGE_RATIO) -> _Cloud | None:
    """The view's cloud from its sampled grid (``_view_grid``), in the centred config-unit frame;
    normals end at neighbours further than ``edge_ratio`` sample spacings (``_grid_normals``)."""
    grid, depth, rows, cols, stride = sampled
    grid = grid * scale - centre[:, None, None]
    camera = view.camera_center * scale - centre
    k = view.intrinsics
    spacing_per_depth = stride / max(k.fx, k.fy)
    # Under depth noise, neighbouring samples' differences are mostly noise: normals span as many
    # samples as the view's measured noise needs (one either way on clean depth).
    relative_noise = relative_depth_noise(depth)
    quarter = depth[::2, ::2]
    median_depth = float(np.nanmedian(quarter)) if np.isfinite(quarter).any() else 0.0
    normals = _grid_normals(grid, depth * scale, camera, spacing_per_depth,
                            _normal_reach(median_depth, relative_noise, spacing_per_depth), edge_ratio)
    # Moving points: every _MOVING_STRIDE-th grid point with a normal, those of twice the stride first.
    step = _MOVING_STRIDE
    index = np.arange(depth.size).reshape(depth.shape)[::step, ::step]
    moving = np.isfinite(normals[0])[::step, ::step]
    rest = moving.copy()
    rest[::2, ::2] = False  # every other moving point per axis comes first
    order = np.r_[index[::2, ::2][moving[::2, ::2]], index[rest]]
    if order.size < 4 * _COVARIANCE_NEIGHBOURS:
        return None
    points, moving_normals = np.take(grid.reshape(3, -1), order, axis=1), np.take(normals.reshape(3, -1), order, axis=1)
    # small_gicp's voxel grid holds 2^20 cells either side of the origin (the scene's centre
    # here) and prints a warning per point beyond; points that far from the scene's centre
    # cannot overlap another view, so they are left out of the coarse cloud.
    coarse_spacing = _COARSE_SPACING * config.pose_point_spacing
    reach_limit = (1 << 19) * coarse_spacing
    kept = points.T if np.abs(points).max() < reach_limit else points.T[np.abs(points).max(axis=0) < reach_limit]
    coarse = small_gicp.voxelgrid_sampling(kept, coarse_spacing, 1)
    if coarse.size() < 4 * _COVARIANCE_NEIGHBOURS:
        return None
    coarse_tree = small_gicp.KdTree(coarse, 1)
    small_gicp.estimate_covariances(coarse, coarse_tree, num_neighbors=_COVARIANCE_NEIGHBOURS, num_threads=1)
    # Grid index of a pixel: (pixel - first) / stride, so fold that into the intrinsics.
    projection = np.array([k.fx / stride, k.fy / stride, (k.cx - cols[0]) / stride, (k.cy - rows[0]) / stride])
    reach = float(np.median(np.sqrt(np.einsum("ij,ij->j", points - camera[:, None], points - camera[:, None]))))
    foreground = (view.mask[rows[0]::stride, cols[0]::stride] > 0 if view.mask is not None
                  else np.zeros(depth.shape, bool))
    return _Cloud(grid.reshape(3, -1), normals.reshape(3, -1), depth.shape, points, moving_normals,
                  order.size - int(rest.sum()), view.pose[:3, :3].copy(), camera[:, None], projection, coarse, coarse_tree,
                  reach, np.zeros(0, dtype=np.int64), (depth * scale).ravel(),
                  relative_noise * median_depth**2 * scale, foreground.ravel(), _mask_interior(foreground).ravel())


def _rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: the 3x3 rotation of a rotation vector (radians)."""
    angle = float(np.linalg.norm(rotvec))
    skew = np.array([[0.0, -rotvec[2], rotvec[1]], [rotvec[2], 0.0, -rotvec[0]], [-rotvec[1], rotvec[0], 0.0]])
    if angle < 1e-12:
        return np.eye(3) + skew
    return np.eye(3) + np.sin(angle) / angle * skew + (1.0 - np.cos(angle)) / angle**2 * (skew @ skew)


def _rotation_angle(rotations: np.ndarray) -> np.ndarray:
    """Angles (radians) of (..., 3, 3) rotations, accurate at small angles too: atan2(2 sin, 2 cos)."""
    axis = np.stack([rotations[..., 2, 1] - rotations[..., 1, 2], rotations[..., 0, 2] - rotations[..., 2, 0],
                     rotations[..., 1, 0] - rotations[..., 0, 1]], axis=-1)
    return np.arctan2(np.linalg.norm(axis, axis=-1), np.trace(rotations, axis1=-2, axis2=-1) - 1.0)


def _constraint_ratio(points: np.ndarray, normals: np.ndarray, centre: np.ndarray, extent: float) -> float:
    """How well matched surface patches pin all six degrees of freedom: weakest / strongest
    eigenvalue of the point-to-plane information matrix (rotations about ``centre`` as
    motions at ``extent``).

    A plane leaves three directions free (ratio near 0), a cylinder one; ground with relief
    and rocks on it pins all of them.
    """
    jac = np.concatenate([np.cross((points - centre) / extent, normals), normals], axis=1)
    eig = np.linalg.eigvalsh(jac.T @ jac)
    return float(eig[0] / eig[-1]) if eig[-1] > 0 else 0.0


def _matches(source: _Cloud, target: _Cloud, transform: np.ndarray, match: float, count: int | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projective association: the source's (first ``count``) moving points, moved by ``transform``,
    are projected into the target camera and matched with the target's grid sample there.

    Kept: matches within ``match`` of each other and facing the same way (normals within 60
    degrees, which keeps points hidden from the target from matching the surface in front of
    them; a sample without a normal matches nothing).  Returns (3, M) moved points, target
    points and target normals.
    """
    rot, shift = transform[:3, :3], transform[:3, 3]
    # Straight into the target camera's frame: R_t^T (T p - c_t).
    to_camera = target.rotation.T @ rot
    local = to_camera @ source.points[:, :count] + (target.rotation.T @ (shift - target.camera[:, 0]))[:, None]
    fx, fy, cx, cy = target.projection
    h, w = target.shape
    with np.errstate(invalid="ignore", divide="ignore"):
        inv_z = 1.0 / local[2]
        col = np.rint(fx * local[0] * inv_z + cx)
        row = np.rint(fy * local[1] * inv_z + cy)
    index = np.flatnonzero((local[2] > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h))
    flat = (row[index] * w + col[index]).astype(np.int64)
    # np.take along an axis gathers several times faster than fancy indexing (this runs in every
    # Gauss-Newton step), with the same values.
    matched, normals = np.take(target.grid, flat, axis=1), np.take(target.normal_grid, flat, axis=1)
    moved = rot @ np.take(source.points, index, axis=1) + shift[:, None]
    gap = moved - matched
    with np.errstate(invalid="ignore"):
        keep = np.flatnonzero((np.einsum("ij,ij->j", gap, gap) <= match * match)
                              & (np.einsum("ij,ij->j", rot @ np.take(source.normals, index, axis=1), normals) > 0.5))
    return np.take(moved, keep, axis=1), np.take(matched, keep, axis=1), np.take(normals, keep, axis=1)


def _fit(source: _Cloud, moved: np.ndarray, matched: np.ndarray, normals: np.ndarray) -> tuple[float, float]:
    """How well matches (``_matches``) fit: the share of the source's moving points matched, and
    their RMS point-to-plane residual (NaN without matches)."""
    offset = np.einsum("ij,ij->j", moved - matched, normals)
    residual = float(np.sqrt(np.mean(offset**2))) if offset.size else float("nan")
    return moved.shape[1] / source.points.shape[1], residual


def _point_to_plane(source: _Cloud, target: _Cloud, transform: np.ndarray, match: float, stop: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Refine ``transform`` (source surface -> target surface) by point-to-plane Gauss-Newton with
    projective association; returns it and its final matches (``_matches``).

    The first iterations move a quarter of the points (every other one per axis) until a step
    moves the surface by less than ``_QUARTER_STOP`` x ``stop``; the rest move them all, until ``stop``.
    """
    for count, until in ((source.quarter, _QUARTER_STOP * stop), (None, stop)):
        transform = _gauss_newton(source, target, transform, match, count, until)
    return (transform, *_matches(source, target, transform, match))


def _gauss_newton(source: _Cloud, target: _Cloud, transform: np.ndarray, match: float, count: int | None,
                  stop: float) -> np.ndarray:
    """At most ``_FINE_ITERATIONS`` point-to-plane Gauss-Newton steps on the first ``count`` moving
    points, until one moves the matched surface by less than ``stop``."""
    for _ in range(_FINE_ITERATIONS):
        moved, matched, normals = _matches(source, target, transform, match, count)
        if moved.shape[1] < 6:
            break
        centre = moved.mean(axis=1, keepdims=True)
        arm = moved - centre
        # Rows of the Jacobian: d(residual)/d(rotation about centre) = arm x normal, d/d(shift) = normal.
        jac = np.concatenate([arm[1:2] * normals[2:3] - arm[2:3] * normals[1:2],
                              arm[2:3] * normals[0:1] - arm[0:1] * normals[2:3],
                              arm[0:1] * normals[1:2] - arm[1:2] * normals[0:1], normals])
        err = np.einsum("ij,ij->j", moved - matched, normals)
        # Regularised by a hair: a degenerate surface is caught afterwards by the constraint ratio.
        hessian = jac @ jac.T
        step = -np.linalg.solve(hessian + 1e-9 * np.trace(hessian) * np.eye(6), jac @ err)
        rot = _rotation_matrix(step[:3])
        update = np.eye(4)
        update[:3, :3] = rot
        update[:3, 3] = centre[:, 0] - rot @ centre[:, 0] + step[3:]
        transform = update @ transform
        extent = np.sqrt(np.mean(np.einsum("ij,ij->j", arm, arm)))
        if np.linalg.norm(step[:3]) * extent + np.linalg.norm(step[3:]) < stop:
            break
    return transform


def _register(source: _Cloud, target: _Cloud, config: ShadowCorrConfig, min_overlap: float | None = None,
              from_declared: bool = False) -> tuple[_Pair | None, str]:
    """Coarse GICP (small_gicp, thinned clouds, wide matching), then point-to-plane on the moving
    grid samples (``_point_to_plane``); None (and why) when the result is not trustworthy (among
    others, when less than ``min_overlap``, by default ``pose_min_overlap``, of the source matches,
    or when it fits the surfaces clearly worse than the declared poses: less than ``_DECLARED_FIT_SHARE``
    of their matched surface per unit of residual).

    With ``from_declared``, point-to-plane also starts from the declared poses, and the motion that
    fits better (matched share over residual) is taken: on a thin overlap of grazing ground, GICP's
    wide matching can carry the surfaces into a wrong minimum that the fine stage cannot leave."""
    min_overlap = config.pose_min_overlap if min_overlap is None else min_overlap
    spacing = config.pose_point_spacing
    coarse = _coarse_match_distance(config, max(source.reach, target.reach))
    result = small_gicp.align(target.coarse, source.coarse, target.coarse_tree, registration_type="GICP",
                              max_correspondence_distance=coarse, num_threads=1, max_iterations=_COARSE_ITERATIONS,
                              rotation_epsilon=np.deg2rad(_COARSE_STOP_DEG),
                              translation_epsilon=_COARSE_STOP_SPACING * spacing)
    # The two surfaces' measured depth noise sets how far apart matched points may lie and how
    # well they can fit: matches cut off inside the noise would bias the fit, and a residual
    # the noise alone explains says nothing against the registration.
    noise = float(np.hypot(source.noise, target.noise))
    fine = max(_FINE_MATCH * spacing, _NOISE_MATCH * noise)
    transform, moved, matched, normals = _point_to_plane(source, target, np.asarray(result.T_target_source),
                                                         fine, _FINE_STOP_SPACING * spacing)
    overlap, residual = _fit(source, moved, matched, normals)
    # Floored: two identical views fit exactly (residual 0), which must not outweigh every other pair.
    floor = _FINE_STOP_SPACING * spacing
    if from_declared:
        other = _point_to_plane(source, target, np.eye(4), fine, _FINE_STOP_SPACING * spacing)
        other_overlap, other_residual = _fit(source, *other[1:])
        if other_overlap / max(other_residual, floor) > overlap / max(residual, floor):
            (transform, moved, matched, normals), overlap, residual = other, other_overlap, other_residual
    if overlap < min_overlap:
        return None, f"overlap {overlap:.2f} < {min_overlap:.3g}"
    max_residual = max(config.pose_max_residual, _NOISE_RESIDUAL * noise)
    if residual > max_residual:
        return None, f"residual {residual:.3g} > {max_residual:.3g} {config.units}"
    matched, normals = matched.T, normals.T
    centre = matched.mean(axis=0)
    extent = max(float(np.sqrt(np.mean(np.sum((matched - centre) ** 2, axis=1)))), spacing)
    ratio = _constraint_ratio(matched, normals, centre, extent)
    if ratio < _MIN_CONSTRAINT_RATIO:
        return None, f"degenerate surface (constraint ratio {ratio:.1e}: the overlap does not pin every direction)"
    weight = overlap / max(residual, floor)
    # The declared poses are the alternative: a motion that fits the surfaces clearly worse than
    # they do (less matched surface per unit of residual, at the same matching distance) is a
    # wrong minimum, not a correction.  Thin overlaps on grazing ground give such minima with
    # exact poses, 0.1-4 degrees off at up to twice the right fit's residual, and the masks
    # confirmed some of them where a segmenter had dropped masks.
    declared = _matches(source, target, np.eye(4), fine)
    if declared[0].shape[1] >= 6:
        declared_overlap, declared_residual = _fit(source, *declared)
        if weight < _DECLARED_FIT_SHARE * declared_overlap / max(declared_residual, floor):
            return None, (f"fits worse than the declared poses (matched {overlap:.3f} at residual {residual:.3g}, "
                          f"declared {declared_overlap:.3f} at {declared_residual:.3g} {config.units})")
    # Each camera's view of the matched surface, the source camera moved with its surface.
    incidence = (_median_incidence(matched, normals, transform[:3, :3] @ source.camera[:, 0] + transform[:3, 3]),
                 _median_incidence(matched, normals, target.camera[:, 0]))
    return _Pair(-1, -1, transform, residual, overlap, centre, extent, weight, incidence), "ok"


def _median_incidence(points: np.ndarray, normals: np.ndarray, camera: np.ndarray) -> float:
    """Median angle (degrees) between the rays of a camera at ``camera`` and a surface, points and
    unit normals as (N, 3) rows: 90 seen head-on, a few degrees at grazing incidence."""
    ray = points - camera
    sine = np.abs(np.einsum("ij,ij->i", ray, normals)) / np.linalg.norm(ray, axis=1)
    return float(np.degrees(np.arcsin(min(float(np.median(sine)), 1.0))))


def _candidate_pairs(clouds: list[_Cloud | None], min_overlap: float) -> list[tuple[int, int]]:
    """View pairs worth registering, (i, j) with i < j.

    Two views are candidates when they share at least ``min_overlap`` of the smaller one's
    coarse cells (counted for all pairs at once by one sparse product, whose cost grows with
    how many views see each cell, not with the square of the views).  Each view keeps its
    ``_MAX_PARTNERS`` candidates sharing the most, and a maximum spanning forest of the
    candidates is added so that pruning never splits a group of overlapping views.
    """
    have = [k for k, c in enumerate(clouds) if c is not None]
    if len(have) < 2:
        return []
    keys = np.concatenate([clouds[k].cells for k in have])
    owner = np.repeat(np.arange(len(have)), [clouds[k].cells.size for k in have])
    _, cell = np.unique(keys, return_inverse=True)
    member = csr_matrix((np.ones(keys.size, dtype=np.int64), (owner, cell.ravel())), shape=(len(have), int(cell.max()) + 1))
    shared = coo_matrix((member @ member.T).tocsr())
    sizes = np.array([clouds[k].cells.size for k in have])
    share = shared.data / np.minimum(sizes[shared.row], sizes[shared.col])
    ok = (shared.row != shared.col) & (share >= min_overlap)
    row, col, share = shared.row[ok], shared.col[ok], share[ok]  # both directions of every candidate
    if row.size == 0:
        return []
    # Rank each view's candidates by share (ties by index) and keep the best few.
    order = np.lexsort((col, -share, row))
    row, col, share = row[order], col[order], share[order]
    first = np.r_[0, np.flatnonzero(np.diff(row)) + 1]
    rank = np.arange(row.size) - np.repeat(first, np.diff(np.r_[first, row.size]))
    best = rank < _MAX_PARTNERS
    # Spanning forest over the candidates, largest shares first (weights must be positive).
    upper = row < col
    forest = minimum_spanning_tree(coo_matrix((2.0 - share[upper], (row[upper], col[upper])), shape=(len(have),) * 2))
    forest = forest.tocoo()
    chosen = {(min(a, b), max(a, b)) for a, b in zip(row[best], col[best])}
    chosen |= {(min(a, b), max(a, b)) for a, b in zip(forest.row, forest.col)}
    return sorted((have[a], have[b]) for a, b in chosen)

