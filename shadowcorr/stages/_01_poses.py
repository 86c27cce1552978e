"""Stage 1 (optional): refine the declared camera poses from the scene itself.

(Over 500 lines for now: one algorithm - clouds, pairwise registration, pose graph, bounds - whose
steps share private types; splitting registration from the pose graph is the next step.)

Odometry and SLAM poses are off by a fraction of a degree to a few degrees; at 7-10 m
range, 2 degrees moves points by 24-35 cm and whole views stop overlapping in the
shadow grid.  Every view sees the ground and the rocks, and neighbouring views share
much of that surface, so the views can be registered to each other:

1. **Surfaces.**  Each view's *full* depth image (terrain included, not only the masked
   pixels) is sampled on a regular pixel grid (about 20 000 samples), each sample's depth
   the mean over a ``pose_depth_window`` square of the pixels around it on the same
   surface (depth noise shrinks by up to the window's width: registrations under 1-2 %
   depth noise land 3-10 times closer), and back-projected
   with the declared pose into the world frame (configuration units, centred on the
   scene).  The grid keeps the image layout, so each sample's normal comes from its grid
   neighbours (none across a depth edge), and any world point can be matched with the
   view's surface by projecting it into the camera: no search structure is needed.
   Each view's depth noise is measured on that grid (``sigma(z) = a z^2``, from the second
   differences along its rows) and sets the scale of everything noise touches below: the
   normals span as many samples as the noise needs, and matching and fit bounds grow with it.
2. **Pairs.**  Views sharing at least ``pose_min_overlap`` of their coarse cells are
   candidates (counted for all pairs at once by one sparse product); each view keeps its
   ``_MAX_PARTNERS`` best candidates plus a maximum spanning forest, so registrations grow
   linearly with the views.  Each pair is registered coarse to fine: GICP (small_gicp) on
   clouds thinned to ``3 x pose_point_spacing`` with a wide matching distance (as far as
   the largest allowed pose error moves a point) brings the surfaces within a few
   centimetres; point-to-plane Gauss-Newton on every other grid sample, matched by
   projection into the other view (normals within 60 degrees, within
   ``pose_point_spacing`` or three noise sigmas), finishes.  A registration is used only
   when the surfaces overlap enough afterwards, the RMS point-to-plane residual is under
   ``pose_max_residual`` (or 1.5 noise sigmas) and the surface constrains all six degrees of freedom (the
   point-to-plane information matrix is not degenerate).  The views' clouds are made
   ``num_threads`` at a time; registration keeps one thread (small_gicp's multi-threaded
   sums would make the result depend on the thread count).
   Views left without any usable pair are registered once more on their *grazing* surfaces
   (``_grazing_pairs``): cameras under a metre high see the ground they share with other views
   at 5-15 degrees of incidence, where neighbouring samples lie further apart than a normal
   allows; with normals up to ``_GRAZING_EDGE_RATIO`` spacings, pairs need only match a
   quarter of ``pose_min_overlap``, and the masks (step 5) turn down the wrong registrations
   such thin overlaps also give.  Views that register are left as they were.
3. **Pose graph.**  Each accepted pair (i, j) measures ``T_ij``, the world-frame motion
   that brings view i's surface onto view j's, which ties the corrections:
   ``C_i = C_j T_ij``.  Rotations are averaged in the Lie algebra (iterated linear least
   squares on rotation vectors), then translations follow by linear least squares.  The
   system only fixes *relative* corrections; of all exact solutions, least squares'
   minimum-norm one is taken, i.e. **the average correction of each connected group of
   views is zero**.  This keeps the scene where the declared poses put it (the best
   estimate when every pose is equally uncertain, and no view's error becomes everyone's
   as it would with one view held fixed); the common motion of all cameras is invisible
   in the images and so is never "corrected".  Edges that disagree with the solution are
   dropped one at a time (worst first) and the graph solved again.
4. **Bounds and honesty.**  When no view of a connected group would move by more than
   ``pose_min_rotation_deg`` and ``pose_min_translation`` (what registration itself
   resolves), the group's poses are kept exactly (``unchanged``): clean poses are not
   perturbed by registration noise, and separate places are judged apart.  A view
   whose correction exceeds ``pose_max_rotation_deg`` or ``pose_max_translation`` keeps
   its pose (``correction_too_large``); a view left
   without an accepted pair keeps its pose (``not_registered``); both are removed from
   the graph, which is solved again without them.
5. **Confirmed by the scene.**  Registration reads only depth, and depth noise can lead it
   to a wrong motion that it then calls consistent.  The masks are independent evidence:
   where two views see the same surface, they should agree on what is rock.  A group's
   corrections are applied only when, moved by them, the views' masks agree better than
   with the declared poses; otherwise every declared pose of the group stays
   (``not_confirmed``).  Only samples away from a mask's outline take part: a segmenter
   that erodes its masks makes the outlines disagree exactly where the right poses let
   the views see them, so outline samples spoke against good corrections.  The masks judge
   only where they agree with the declared poses on at least ``_JUDGING_AGREEMENT`` (90 %)
   of the shared surface: then the declared poses already explain them, and a correction
   that does not improve them was read from depth noise (with exact poses and 1 % depth
   noise correlated over 4 px, the views' masks agree on 95-99 %).  Where they disagree more,
   the poses are off or the masks are wrong (a segmenter's drops, splits, merges and erosion
   at once: 60-90 % with the right poses), and the masks cannot tell a good correction from
   a bad one - on synthetic 4-camera rock fields under the ``field`` errors, the right
   corrections (1-1.6 degrees between views brought to 0.1) made the masks agree less in 4
   scenes of 10, so with the masks as judge those scenes kept their declared poses.  Every view gets a
   report (applied correction, residual, overlap) and a warning when it still disagrees with
   its neighbours or was not refined.

Work is bounded and vectorised: about 20 000 samples per view, at most
``_COARSE_ITERATIONS`` GICP iterations (one thread) and ``2 x _FINE_ITERATIONS``
point-to-plane steps per pair, at most a few pairs per view, and a sparse pose graph with
six unknowns per view.  ``benchmarks/bench_poses.py`` measures time and accuracy.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import small_gicp
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation

from ..bundle import SceneBundle, View, unit_scale
from ..config import ShadowCorrConfig
from ..ops import relative_depth_noise, thread_map
from ..result import ViewPoseCorrection
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
#: Views left without any usable pair are tried again with normals up to this many spacings (ground
#: seen at grazing incidence down to about 5 degrees, whose row neighbours lie 1 / sin(incidence)
#: spacings apart) and a pair need only match ``_GRAZING_OVERLAP_SHARE`` of ``pose_min_overlap``.
_GRAZING_EDGE_RATIO = 12.0
_GRAZING_OVERLAP_SHARE = 0.25
#: Pixels of a depth window differing from the sample's own depth by more than this share of it lie on
#: another surface (across a depth edge) and are not averaged in (``depth_on_grid``).
_WINDOW_EDGE_SHARE = 0.1
#: A pair is degenerate when the weakest direction of its point-to-plane information carries
#: less than this share of the strongest (a flat or a cylindrical surface).
_MIN_CONSTRAINT_RATIO = 1e-3
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
#: A point projected into another view is seen there when that view's depth at the pixel is
#: within this share of the point's own depth (not hidden behind something, not in front).
_VISIBLE_DEPTH_SHARE = 0.03
#: The masks judge a group's corrections only where, with the declared poses, they agree on at
#: least this share of the surface the views share (see step 5 of the module docstring).
_JUDGING_AGREEMENT = 0.9


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


def sampling_stride(height: int, width: int) -> int:
    """The stride of the pose stage's pixel grid: about ``_SAMPLED_PIXELS`` samples per image."""
    return max(1, int(round(np.sqrt(height * width / _SAMPLED_PIXELS))))


def depth_on_grid(depth: np.ndarray, stride: int, window: int, max_depth: float) -> np.ndarray:
    """(h, w) float64 depth of every ``stride``-th pixel from ``stride // 2`` (NaN where invalid),
    each the mean over the ``window`` x ``window`` pixels around it (at most the stride, odd) whose
    depth lies within ``_WINDOW_EDGE_SHARE`` of the sample's own.

    Registration reads depth at one pixel in ``stride`` x ``stride``; averaging the valid
    neighbours of a sample on the same surface divides independent depth noise by up to the
    window's width (a 5 x 5 window: 5 times) at no cost in resolution, while neighbours across a
    depth edge (another surface) and invalid ones stay out.  An invalid sample stays invalid.
    """
    height, width = depth.shape
    n_rows, n_cols = len(range(stride // 2, height, stride)), len(range(stride // 2, width, stride))
    if n_rows * stride > height or n_cols * stride > width:  # a partial last block: NaN beyond the image
        padded = np.full((max(n_rows * stride, height), max(n_cols * stride, width)), np.nan)
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
    tolerance = _WINDOW_EDGE_SHARE * centre
    total, count = np.zeros_like(centre), np.zeros_like(centre)
    with np.errstate(invalid="ignore"):
        for dr in range(-reach, reach + 1):
            for dc in range(-reach, reach + 1):
                neighbour = blocks[:, half + dr, :, half + dc].astype(np.float64)
                # within a tenth of a valid centre's depth, so positive; False where either is NaN
                same = (np.abs(neighbour - centre) <= tolerance) & (neighbour <= max_depth)
                np.add(total, neighbour, out=total, where=same)
                count += same
    return np.where(count > 0, total / np.maximum(count, 1.0), np.nan)


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


def _register(source: _Cloud, target: _Cloud, config: ShadowCorrConfig, min_overlap: float | None = None
              ) -> tuple[_Pair | None, str]:
    """Coarse GICP (small_gicp, thinned clouds, wide matching), then point-to-plane on the moving
    grid samples (``_point_to_plane``); None (and why) when the result is not trustworthy (among
    others, when less than ``min_overlap``, by default ``pose_min_overlap``, of the source matches)."""
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
    overlap = moved.shape[1] / source.points.shape[1]
    if overlap < min_overlap:
        return None, f"overlap {overlap:.2f} < {min_overlap:.3g}"
    offset = np.einsum("ij,ij->j", moved - matched, normals)
    residual = float(np.sqrt(np.mean(offset**2)))
    max_residual = max(config.pose_max_residual, _NOISE_RESIDUAL * noise)
    if residual > max_residual:
        return None, f"residual {residual:.3g} > {max_residual:.3g} {config.units}"
    matched, normals = matched.T, normals.T
    centre = matched.mean(axis=0)
    extent = max(float(np.sqrt(np.mean(np.sum((matched - centre) ** 2, axis=1)))), spacing)
    ratio = _constraint_ratio(matched, normals, centre, extent)
    if ratio < _MIN_CONSTRAINT_RATIO:
        return None, f"degenerate surface (constraint ratio {ratio:.1e}: the overlap does not pin every direction)"
    # Floored: two identical views fit exactly (residual 0), which must not outweigh every other pair.
    weight = overlap / max(residual, _FINE_STOP_SPACING * spacing)
    return _Pair(-1, -1, transform, residual, overlap, centre, extent, weight), "ok"


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


class _EdgeSystem:
    """Least squares over the views of a graph of pairwise differences: x_i - x_j = b_ij per edge.

    A pair counts more (weight w) the more surface it shares and the better it fits.  Such a
    system fixes x only up to one constant per connected group of views; of all least-squares
    solutions ``solve`` returns the minimum-norm one (zero mean over each group; zero for a view
    without edges).  The normal equations are a sparse graph Laplacian, factorised once with one
    view per group pinned at zero; each group's mean is removed afterwards.
    """

    def __init__(self, n: int, edges: list[_Pair]) -> None:
        self.source = np.array([e.source for e in edges], dtype=np.int64)
        self.target = np.array([e.target for e in edges], dtype=np.int64)
        weight = np.array([e.weight for e in edges])
        self.weight = weight / weight.max()
        rows = np.r_[np.arange(len(edges)), np.arange(len(edges))]
        self.incidence = csr_matrix((np.r_[self.weight, -self.weight], (rows, np.r_[self.source, self.target])),
                                    shape=(len(edges), n))
        laplacian = (self.incidence.T @ self.incidence).tocsc()
        self.groups, self.label = connected_components(laplacian, directed=False)
        pinned = np.zeros(n, dtype=bool)
        pinned[np.unique(self.label, return_index=True)[1]] = True
        self.free = np.flatnonzero(~pinned)
        self.factor = splu(laplacian[self.free][:, self.free].tocsc()) if self.free.size else None
        self.size = np.bincount(self.label, minlength=self.groups)[:, None]

    def solve(self, differences: np.ndarray) -> np.ndarray:
        """(n, k) minimum-norm least-squares x for per-edge (E, k) differences b."""
        x = np.zeros((self.label.size, differences.shape[1]))
        if self.factor is not None:
            x[self.free] = self.factor.solve((self.incidence.T @ (differences * self.weight[:, None]))[self.free])
        mean = np.zeros((self.groups, differences.shape[1]))
        np.add.at(mean, self.label, x)
        return x - (mean / self.size)[self.label]


def _solve_graph(n: int, edges: list[_Pair], iterations: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Corrections (R_i, t_i) in the centred frame with C_i = C_j T_ij in least squares, zero mean per group.

    Rotations first, averaged in the Lie algebra (iterated, minimum-norm); then translations,
    exactly linear once the rotations are known: t_i - t_j = R_j t_ij.
    """
    rotations = np.repeat(np.eye(3)[None], n, axis=0)
    translations = np.zeros((n, 3))
    if not edges:
        return rotations, translations
    system = _EdgeSystem(n, edges)
    src, tgt = system.source, system.target
    measured = np.stack([e.transform[:3, :3] for e in edges])
    for _ in range(iterations):
        # residual e_ij = log(R_j R_ij R_i^T); left updates with d_i - d_j = e_ij cancel it to first order.
        err = Rotation.from_matrix(rotations[tgt] @ measured @ rotations[src].transpose(0, 2, 1)).as_rotvec()
        step = system.solve(err)
        rotations = Rotation.from_rotvec(step).as_matrix() @ rotations
        if np.abs(step).max() < 1e-10:
            break
    translations = system.solve(np.einsum("eij,ej->ei", rotations[tgt], np.stack([e.transform[:3, 3] for e in edges])))
    return rotations, translations


def _disagreements(edges: list[_Pair], rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """How far (config units) the solved corrections miss each edge's measurement on its matched surface.

    The miss D = C_j T_ij C_i^-1 (identity when they agree) moves the surface's centroid c by
    |D c - c| and turns it by angle(D), which moves points ``extent`` away by about angle x extent.
    """
    if not edges:
        return np.zeros(0)
    src = np.array([e.source for e in edges])
    tgt = np.array([e.target for e in edges])
    measured = np.stack([e.transform for e in edges])
    centre = np.stack([e.centre for e in edges])
    rot_i_inv, rot_j = rotations[src].transpose(0, 2, 1), rotations[tgt]
    miss = rot_j @ measured[:, :3, :3] @ rot_i_inv
    # D c = R_j (R_ij (R_i^T (c - t_i)) + t_ij) + t_j
    back = np.einsum("eij,ej->ei", rot_i_inv, centre - translations[src])
    moved = np.einsum("eij,ej->ei", rot_j, np.einsum("eij,ej->ei", measured[:, :3, :3], back) + measured[:, :3, 3])
    moved += translations[tgt]
    return _rotation_angle(miss) * np.array([e.extent for e in edges]) + np.linalg.norm(moved - centre, axis=1)


def _correction_sizes(rotations: np.ndarray, translations: np.ndarray, offsets: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Per view: degrees of its correction, and how far the correction moves a point of the view
    at ``offsets`` from the scene centre (its camera, or its surface)."""
    moved = np.einsum("kij,kj->ki", rotations, offsets) + translations - offsets
    return np.rad2deg(_rotation_angle(rotations)), np.linalg.norm(moved, axis=1)


def _mask_agreement(clouds: list[_Cloud | None], pairs: list[tuple[int, int]], rotations: np.ndarray,
                    translations: np.ndarray) -> tuple[int, int]:
    """How well the views' masks agree where the views see the same surface, with each view
    moved by its correction (``rotations``/``translations``, centred frame).

    Every other grid sample (per axis) of one view of a pair is projected into the other
    camera; where that camera sees it (its depth there within ``_VISIBLE_DEPTH_SHARE``), the
    two masks should both say "rock" or both "not rock".  Returns (samples where both say
    rock, samples where exactly one does), both directions of every pair added up.  The
    masks are the one input the registration does not use, so they can confirm it.

    Only samples whose grid neighbours lie on their side of the mask count, in both views:
    under eroded masks (3 px) the outlines disagree wherever the views see them, which the
    right poses do more often than wrong ones (on synthetic rock fields under the ``field``
    errors, outline samples made 2 of 6 good corrections look worse than the declared poses).
    """
    both = one = 0
    for a, b in pairs:
        for source, target, s, t in ((clouds[a], clouds[b], a, b), (clouds[b], clouds[a], b, a)):
            h, w = source.shape
            take = (np.arange(h)[:, None] % 2 == 0) & (np.arange(w)[None, :] % 2 == 0)
            take = np.flatnonzero(take.ravel() & np.isfinite(source.grid[0]) & source.interior)
            points = rotations[s] @ np.take(source.grid, take, axis=1) + translations[s][:, None]
            # Into the corrected target camera: (R_t rot)^T (p - (R_t c + t_t)).
            to_camera = (rotations[t] @ target.rotation).T
            local = to_camera @ (points - (rotations[t] @ target.camera + translations[t][:, None]))
            fx, fy, cx, cy = target.projection
            with np.errstate(invalid="ignore", divide="ignore"):
                col = np.rint(fx * local[0] / local[2] + cx)
                row = np.rint(fy * local[1] / local[2] + cy)
            inside = np.flatnonzero((local[2] > 0) & (col >= 0) & (col < target.shape[1]) & (row >= 0)
                                    & (row < target.shape[0]))
            flat = (row[inside] * target.shape[1] + col[inside]).astype(np.int64)
            with np.errstate(invalid="ignore"):
                seen = np.abs(target.depth_grid[flat] - local[2, inside]) < _VISIBLE_DEPTH_SHARE * local[2, inside]
            seen &= target.interior[flat]
            mine, theirs = source.foreground[take[inside]][seen], target.foreground[flat][seen]
            both += int(np.count_nonzero(mine & theirs))
            one += int(np.count_nonzero(mine != theirs))
    return both, one


def _masks_refuse(share_before: float, share_after: float) -> bool:
    """Whether the masks turn a group's corrections down: they agree on ``share_before`` of the
    surface the views share with the declared poses and on ``share_after`` with the corrected ones.
    Only masks that agree with the declared poses on at least ``_JUDGING_AGREEMENT`` judge (step 5
    of the module docstring); those refuse a correction that does not make them agree better."""
    return share_before >= _JUDGING_AGREEMENT and share_after <= share_before


def _grazing_pairs(bundle: SceneBundle, sampled: list, clouds: list[_Cloud | None], edges: list[_Pair],
                   why: dict[int, str], centre: np.ndarray, scale: float, cell: float, config: ShadowCorrConfig
                   ) -> list[tuple[int, int]]:
    """Register the views left without any usable pair again, on their grazing surfaces.

    Cameras low over the ground (under a metre, pitched a few degrees down) see the ground
    they share with other views at 5-15 degrees of incidence, where neighbouring grid samples
    lie up to 12 spacings apart: ``_EDGE_RATIO`` takes that for a depth edge, so the shared
    ground has no normals and two such views 90 degrees apart match 0-4 % of their samples (the
    near ground, most of each view, is seen by no other).  Such views are registered once more
    with normals up to ``_GRAZING_EDGE_RATIO`` spacings and a quarter of ``pose_min_overlap``
    (``_GRAZING_OVERLAP_SHARE``); the pairs found are used like the others (pose graph, then the
    masks' confirmation, which turns down the wrong registrations such thin overlaps also give).
    Views that already register are left exactly as they were: on rigs whose views share their
    surface head-on, the grazing normals would change their registrations without improving them.
    Accepted pairs join ``edges`` (and ``clouds`` takes the grazing cloud of a view that had none);
    returns the pairs tried.
    """
    paired = np.zeros(len(clouds), dtype=bool)
    for e in edges:
        paired[[e.source, e.target]] = True
    if paired.all() or len(clouds) < 2:
        return []
    grazing = thread_map(lambda vs: _make_cloud(*vs, centre, scale, config, _GRAZING_EDGE_RATIO),
                         zip(bundle.views, sampled), config.num_threads)
    for k, c in enumerate(grazing):
        if c is not None:
            c.cells = _cell_keys(c.points.T, cell)
            if clouds[k] is None:
                clouds[k] = c
    min_overlap = _GRAZING_OVERLAP_SHARE * config.pose_min_overlap
    tried = [(i, j) for i, j in _candidate_pairs(grazing, min_overlap) if not (paired[i] and paired[j])]
    for i, j in tried:
        pair, reason = _register(grazing[i], grazing[j], config, min_overlap)
        if pair is None:
            for k, other in ((i, j), (j, i)):
                if not paired[k]:
                    why[k] = f"registration with {bundle.views[other].name}: {reason}"
            continue
        edges.append(dataclasses.replace(pair, source=i, target=j))
    return tried


def _groups(n: int, edges: list[_Pair]) -> np.ndarray:
    """Connected group label of every view in the graph of ``edges`` (a view without edges is its own group)."""
    src = [e.source for e in edges]
    tgt = [e.target for e in edges]
    return connected_components(coo_matrix((np.ones(len(edges)), (src, tgt)), shape=(n, n)), directed=False)[1]


def refine_poses(
    bundle: SceneBundle, config: ShadowCorrConfig | None = None, *, view_order: str = "name"
) -> tuple[SceneBundle, list[ViewPoseCorrection]]:
    """Register the views to each other and correct their poses (see the module docstring).

    Returns a copy of the bundle with refined poses (views that could not be refined
    keep theirs) and one report per view, in view order.  The input is not modified.
    With ``view_order="name"`` the views are registered in one canonical order, sorted by
    name, so the same views listed in another order get the same corrections;
    ``"listed"`` registers them as listed (for a caller that orders them canonically itself,
    such as a site map, whose views' names repeat across scans).
    """
    config = config or ShadowCorrConfig()
    if view_order not in ("name", "listed"):
        raise ValueError(f"view_order must be 'name' or 'listed', not {view_order!r}")
    # Under depth noise, registering a pair one way and the other converges to slightly different
    # motions, and pairs are chosen and dropped in view order; in the listing order, the same views
    # listed differently could be corrected differently (and labelled differently downstream).
    order = list(range(len(bundle.views)))
    if view_order == "name":
        order.sort(key=lambda k: bundle.views[k].name)
    if bundle.point_segments is not None or order == list(range(len(bundle.views))):
        return _refine_in_order(bundle, config)
    refined, reports = _refine_in_order(dataclasses.replace(bundle, views=[bundle.views[k] for k in order]), config)
    listed = np.argsort(order)
    return (dataclasses.replace(refined, views=[refined.views[i] for i in listed]),
            [reports[i] for i in listed])


def _refine_in_order(bundle: SceneBundle, config: ShadowCorrConfig
                     ) -> tuple[SceneBundle, list[ViewPoseCorrection]]:
    """:func:`refine_poses` with the views in the bundle's order."""
    scale = unit_scale(bundle.units, config.units)
    n = len(bundle.views)
    identity = np.eye(4).tolist()
    if bundle.point_segments is not None or any(v.depth is None for v in bundle.views):
        return bundle, [ViewPoseCorrection(view=v.name, status="not_registered", rotation_deg=0.0, translation=0.0,
                                           correction=identity, message="the bundle has no depth images to register")
                        for v in bundle.views]

    sampled = thread_map(lambda v: _view_grid(v, config.max_depth / scale, config.pose_depth_window), bundle.views,
                         config.num_threads)
    # Median centre (of every other sample): a view declared far away (another place) must not move it.
    valid = [g[:, ::2, ::2].reshape(3, -1) for g, *_ in sampled]
    valid = [p[:, np.isfinite(p[0])] * scale for p in valid]
    centre = np.median(np.concatenate([p for p in valid if p.size] or [np.zeros((3, 1))], axis=1), axis=1)
    clouds = thread_map(lambda vs: _make_cloud(*vs, centre, scale, config), zip(bundle.views, sampled),
                        config.num_threads)
    camera_offset = np.stack([v.camera_center * scale for v in bundle.views]) - centre
    reaches = [c.reach for c in clouds if c is not None]
    cell = _coarse_match_distance(config, float(np.median(reaches)) if reaches else 0.0)
    for c in clouds:
        if c is not None:
            c.cells = _cell_keys(c.points.T, cell)

    why: dict[int, str] = {}
    edges: list[_Pair] = []
    candidates = _candidate_pairs(clouds, config.pose_min_overlap)
    for i, j in candidates:
        pair, reason = _register(clouds[i], clouds[j], config)
        if pair is None:
            why.setdefault(i, f"registration with {bundle.views[j].name}: {reason}")
            why.setdefault(j, f"registration with {bundle.views[i].name}: {reason}")
            continue
        edges.append(dataclasses.replace(pair, source=i, target=j))
    candidates = sorted(set(candidates) | set(_grazing_pairs(bundle, sampled, clouds, edges, why, centre, scale, cell,
                                                             config)))

    # Solve; drop disagreeing edges and out-of-bound views until everything left is consistent.
    status = ["corrected"] * n
    agree = max(config.pose_max_residual, config.pose_point_spacing / 2.0)
    while True:
        rotations, translations = _solve_graph(n, edges)
        if edges:
            miss = _disagreements(edges, rotations, translations)
            worst = int(np.argmax(miss))
            if miss[worst] > agree and len(edges) > 1:
                e = edges.pop(worst)
                for k in (e.source, e.target):
                    why.setdefault(k, f"its registration with {bundle.views[e.target + e.source - k].name} "
                                      f"disagrees with the others by {miss[worst] / scale:.3g} {bundle.units}")
                continue
        degrees, shifts = _correction_sizes(rotations, translations, camera_offset)
        over = [k for k in range(n) if status[k] == "corrected"
                and (degrees[k] > config.pose_max_rotation_deg or shifts[k] > config.pose_max_translation)]
        if not over:
            break
        worst = max(over, key=lambda k: degrees[k] / config.pose_max_rotation_deg + shifts[k] / config.pose_max_translation)
        status[worst] = "correction_too_large"
        why[worst] = (f"the correction ({degrees[worst]:.2f} deg, {shifts[worst] / scale:.3g} {bundle.units}) "
                      f"exceeds the bound ({config.pose_max_rotation_deg} deg, "
                      f"{config.pose_max_translation / scale:.3g} {bundle.units}); pose kept")
        edges = [e for e in edges if worst not in (e.source, e.target)]

    in_graph = np.zeros(n, dtype=bool)
    for e in edges:
        in_graph[[e.source, e.target]] = True
    for k in np.flatnonzero(~in_graph):
        if status[k] == "corrected":
            status[k] = "not_registered"
            why.setdefault(k, "no other view overlaps it enough")
    # Corrections within the registration's own accuracy are noise, not information: when no
    # view of a connected group would move by more, the group's declared poses already agree
    # and are left exactly as they are (groups are separate places and are judged apart).
    # Moves are judged where registration measures them, on the view's surface: at the camera,
    # metres from the scene centre, the lever arm turns 0.04 deg of noise into a centimetre.
    surface = np.stack([c.points.mean(axis=1) if c is not None else camera_offset[k] for k, c in enumerate(clouds)])
    surface_shifts = _correction_sizes(rotations, translations, surface)[1]
    group = _groups(n, edges)
    for g in np.unique(group[in_graph]):
        members = [k for k in np.flatnonzero(group == g) if status[k] == "corrected"]
        if members and all(degrees[k] < config.pose_min_rotation_deg
                           and surface_shifts[k] < config.pose_min_translation for k in members):
            for k in members:
                status[k] = "unchanged"
                why[k] = (f"the declared pose agrees with its neighbours to within {degrees[k]:.3f} deg and "
                          f"{surface_shifts[k] / scale:.3g} {bundle.units} on its surface (under "
                          "pose_min_rotation_deg / pose_min_translation); kept")
    # A correction must be confirmed by what registration did not use: the masks.  Under depth
    # noise (or a surface that fits two ways) registration converges to a wrong motion and calls
    # it consistent; moved by such a correction, the views' masks agree less where they see the
    # same surface, not more.  A group whose corrections do not make its views' masks agree
    # better keeps every declared pose - where the masks agree with the declared poses well
    # enough to judge (_JUDGING_AGREEMENT); below that, segmenter errors dominate what they say.
    declared_r, declared_t = np.broadcast_to(np.eye(3), (n, 3, 3)), np.zeros((n, 3))
    for g in np.unique(group[in_graph]):
        members = [k for k in np.flatnonzero(group == g) if status[k] == "corrected"]
        moving = set(members)
        pairs = [(i, j) for i, j in candidates if i in moving or j in moving]
        if not members or not pairs:
            continue
        moved_r, moved_t = declared_r.copy(), declared_t.copy()
        moved_r[members], moved_t[members] = rotations[members], translations[members]
        before = _mask_agreement(clouds, pairs, declared_r, declared_t)
        after = _mask_agreement(clouds, pairs, moved_r, moved_t)
        share_before, share_after = (b / max(b + o, 1) for b, o in (before, after))
        if _masks_refuse(share_before, share_after):
            for k in members:
                status[k] = "not_confirmed"
                why[k] = (f"corrected, the views' masks would not agree better where they see the same surface "
                          f"({share_after:.3f} against {share_before:.3f} with the declared poses): the "
                          "registration is not borne out by the scene; pose kept")
    incident: list[list[_Pair]] = [[] for _ in range(n)]
    worst_miss = np.zeros(n)
    for e, m in zip(edges, _disagreements(edges, rotations, translations)):
        for k in (e.source, e.target):
            incident[k].append(e)
            worst_miss[k] = max(worst_miss[k], m)
    reports, views = [], []
    for k, view in enumerate(bundle.views):
        mine, miss = incident[k], worst_miss[k]
        correction = np.eye(4)
        if status[k] == "corrected":
            r, t = rotations[k], translations[k]
            correction[:3, :3] = r
            correction[:3, 3] = (t + centre - r @ centre) / scale  # centred config frame -> bundle world frame
        angle, shift = (float(degrees[k]), float(shifts[k])) if status[k] == "corrected" else (0.0, 0.0)
        consistent = bool(miss <= agree / 2.0) if status[k] in ("corrected", "unchanged") else None
        message = why.get(k) if status[k] != "corrected" else None
        if consistent is False:
            message = f"refined pose still disagrees with its neighbours by {miss / scale:.3g} {bundle.units}"
        reports.append(ViewPoseCorrection(
            view=view.name, status=status[k], rotation_deg=round(angle, 4), translation=round(shift / scale, 4),
            correction=correction.round(9).tolist(),
            residual=round(float(np.mean([e.residual for e in mine])) / scale, 4) if mine else None,
            overlap=round(max(e.overlap for e in mine), 4) if mine else None,
            neighbours=[bundle.views[e.target + e.source - k].name for e in mine],
            consistent=consistent, message=message,
        ))
        views.append(dataclasses.replace(view, pose=correction @ view.pose) if status[k] == "corrected" else view)
    return dataclasses.replace(bundle, views=views, warnings=list(bundle.warnings)), reports


def pose_warnings(reports: list[ViewPoseCorrection]) -> list[str]:
    """One warning per view whose pose could not be refined or still looks inconsistent."""
    out = []
    for r in reports:
        if r.status not in ("corrected", "unchanged"):
            out.append(f"pose of view {r.view} not refined ({r.status.replace('_', ' ')}): {r.message}")
        elif r.consistent is False:
            out.append(f"pose of view {r.view}: {r.message}")
    return out


def pose_errors(estimated: np.ndarray, truth: np.ndarray, *, common_motion: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Per-view rotation error (degrees) and camera-centre error (pose units) of (V, 4, 4) camera-to-world poses.

    With ``common_motion`` the one rigid motion that best brings all estimated cameras
    onto the true ones is taken out first: the images cannot reveal a motion shared by
    every camera, so that is the error refinement can be asked to remove.
    """
    rot_e, rot_t = estimated[:, :3, :3], truth[:, :3, :3]
    centre_e, centre_t = estimated[:, :3, 3], truth[:, :3, 3]
    if common_motion:
        common = Rotation.from_matrix(rot_t @ rot_e.transpose(0, 2, 1)).mean().as_matrix()
        rot_e = common @ rot_e
        centre_e = centre_e @ common.T
        centre_e = centre_e + (centre_t - centre_e).mean(axis=0)
    angles = np.rad2deg(Rotation.from_matrix(rot_e @ rot_t.transpose(0, 2, 1)).magnitude())
    return angles, np.linalg.norm(centre_e - centre_t, axis=1)
