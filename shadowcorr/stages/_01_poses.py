"""Stage 1 (optional): refine the declared camera poses from the scene itself.

Odometry and SLAM poses are off by a fraction of a degree to a few degrees; at 7-10 m
range, 2 degrees moves points by 24-35 cm and whole views stop overlapping in the
shadow grid.  Every view sees the ground and the rocks, and neighbouring views share
much of that surface, so the views can be registered to each other:

1. **Clouds.**  Each view's *full* depth image (terrain included, not only the masked
   pixels) is sampled on a pixel grid, back-projected with the declared pose into the
   world frame (configuration units, centred on the scene) and thinned to one point per
   ``pose_point_spacing`` cell; small_gicp estimates each point's local covariance.
2. **Pairs.**  Pairs whose coarse occupancy overlaps by at least ``pose_min_overlap``
   are registered with GICP (small_gicp), coarse to fine.  A registration is used only
   when it converged, the surfaces overlap enough afterwards, the RMS point-to-plane
   residual is under ``pose_max_residual`` and the surface constrains all six degrees
   of freedom (the normalised GICP Hessian is not degenerate).
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
4. **Bounds and honesty.**  When no view would move by more than ``pose_min_rotation_deg``
   and ``pose_min_translation`` (what registration itself resolves), every pose is kept
   exactly (``unchanged``): clean poses are not perturbed by registration noise.  A view
   whose correction exceeds ``pose_max_rotation_deg`` or ``pose_max_translation`` keeps
   its pose (``correction_too_large``); a view left
   without an accepted pair keeps its pose (``not_registered``); both are removed from
   the graph, which is solved again without them.  Every view gets a report (applied
   correction, residual, overlap) and a warning when it still disagrees with its
   neighbours.

Work is bounded: the clouds have a few thousand points per view, each pair is
registered with at most ``_COARSE_ITERATIONS + _FINE_ITERATIONS`` GICP iterations on one
thread, and the pose graph has six unknowns per view.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import small_gicp
from pykdtree.kdtree import KDTree
from scipy.spatial.transform import Rotation

from ..bundle import SceneBundle, View, unit_scale
from ..config import ShadowCorrConfig
from ..result import ViewPoseCorrection
from ._02_segments import back_project

#: Pixels sampled per view before thinning (a regular grid; about 1 in 100 of a 1080p image).
_SAMPLED_PIXELS = 20_000
#: Neighbours for small_gicp's per-point covariance estimate.
_COVARIANCE_NEIGHBOURS = 10
#: The coarse pass runs on clouds this many times sparser than the fine one.
_COARSE_SPACING = 3.0
_COARSE_ITERATIONS = 20
_FINE_ITERATIONS = 4
#: Fine correspondence distance, in units of ``pose_point_spacing``.
_FINE_MATCH = 1.0
#: Convergence: the coarse pass stops when a step rotates less than this (degrees) and
#: moves less than this share of the spacing; the fine pass at a tenth of both.
_COARSE_STOP_DEG = 0.05
_COARSE_STOP_SPACING = 1.0 / 32.0
#: A pair is degenerate when the weakest direction of its point-to-plane information carries
#: less than this share of the strongest (a flat or a cylindrical surface).
_MIN_CONSTRAINT_RATIO = 1e-3


@dataclass
class _Cloud:
    """One view's surface at two densities (GICP clouds with covariances and k-d trees)."""

    fine: small_gicp.PointCloud
    fine_tree: small_gicp.KdTree
    coarse: small_gicp.PointCloud
    coarse_tree: small_gicp.KdTree
    points: np.ndarray  # (N, 3) the fine cloud, centred world frame, config units
    normals: np.ndarray  # (N, 3)
    nearest: KDTree  # over ``points``, for overlap and residual
    cells: np.ndarray  # sorted unique cell keys at the coarse match distance (overlap pre-check)


@dataclass
class _Pair:
    source: int
    target: int
    transform: np.ndarray  # (4, 4) centred frame: source surface -> target surface
    residual: float  # RMS point-to-plane, config units
    overlap: float  # share of source points with a target point within the fine match distance


def _view_points(view: View, max_depth_bundle: float) -> np.ndarray:
    """World points (bundle units) of a regular pixel grid of the view's valid depth."""
    height, width = view.depth.shape
    stride = max(1, int(round(np.sqrt(height * width / _SAMPLED_PIXELS))))
    rows = np.arange(stride // 2, height, stride)
    cols = np.arange(stride // 2, width, stride)
    depth = view.depth[np.ix_(rows, cols)].astype(np.float64)
    valid = np.isfinite(depth) & (depth > 0) & (depth <= max_depth_bundle)
    vv, uu = np.nonzero(valid)
    return back_project(view, rows[vv].astype(np.float64), cols[uu].astype(np.float64), depth[vv, uu])


def _cell_keys(points: np.ndarray, cell: float) -> np.ndarray:
    idx = np.floor(points / cell).astype(np.int64) + (1 << 20)
    return np.unique((idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2])


def _coarse_match_distance(config: ShadowCorrConfig, radius: float) -> float:
    """How far the largest allowed pose error can move a surface point ``radius`` from the scene centre."""
    return max(4.0 * config.pose_point_spacing,
               config.pose_max_translation + radius * np.deg2rad(config.pose_max_rotation_deg))


def _gicp_cloud(points: np.ndarray, spacing: float) -> tuple[small_gicp.PointCloud, small_gicp.KdTree]:
    cloud = small_gicp.voxelgrid_sampling(points, spacing, 1)
    tree = small_gicp.KdTree(cloud, 1)
    if cloud.size() > _COVARIANCE_NEIGHBOURS:
        small_gicp.estimate_normals_covariances(cloud, tree, num_neighbors=_COVARIANCE_NEIGHBOURS, num_threads=1)
    return cloud, tree


def _make_cloud(points: np.ndarray, config: ShadowCorrConfig, coarse: float) -> _Cloud | None:
    fine, fine_tree = _gicp_cloud(points, config.pose_point_spacing)
    sparse, sparse_tree = _gicp_cloud(points, _COARSE_SPACING * config.pose_point_spacing)
    if sparse.size() < 4 * _COVARIANCE_NEIGHBOURS:
        return None
    pts = np.asarray(fine.points())[:, :3]
    return _Cloud(fine, fine_tree, sparse, sparse_tree, pts, np.asarray(fine.normals())[:, :3], KDTree(pts),
                  _cell_keys(pts, coarse))


def _constraint_ratio(points: np.ndarray, normals: np.ndarray, radius: float) -> float:
    """How well matched surface patches pin all six degrees of freedom: weakest / strongest
    eigenvalue of the point-to-plane information matrix (rotations as motions at ``radius``).

    A plane leaves three directions free (ratio near 0), a cylinder one; ground with relief
    and rocks on it pins all of them.
    """
    jac = np.concatenate([np.cross(points / radius, normals), normals], axis=1)
    eig = np.linalg.eigvalsh(jac.T @ jac)
    return float(eig[0] / eig[-1]) if eig[-1] > 0 else 0.0


def _register(source: _Cloud, target: _Cloud, config: ShadowCorrConfig, radius: float) -> tuple[_Pair | None, str]:
    """GICP source -> target, coarse to fine; None (and why) when the result is not trustworthy."""
    spacing = config.pose_point_spacing
    stop_rad, stop_len = np.deg2rad(_COARSE_STOP_DEG), _COARSE_STOP_SPACING * spacing
    result = small_gicp.align(target.coarse, source.coarse, target.coarse_tree, registration_type="GICP",
                              max_correspondence_distance=_coarse_match_distance(config, radius), num_threads=1,
                              max_iterations=_COARSE_ITERATIONS, rotation_epsilon=stop_rad, translation_epsilon=stop_len)
    fine = _FINE_MATCH * spacing
    result = small_gicp.align(target.fine, source.fine, target.fine_tree, init_T_target_source=result.T_target_source,
                              registration_type="GICP", max_correspondence_distance=fine, num_threads=1,
                              max_iterations=_FINE_ITERATIONS, rotation_epsilon=stop_rad / 10,
                              translation_epsilon=stop_len / 10)
    transform = np.asarray(result.T_target_source)
    moved = source.points @ transform[:3, :3].T + transform[:3, 3]
    dist, nearest = target.nearest.query(moved, k=1)
    inlier = dist <= fine
    overlap = float(inlier.mean())
    if overlap < config.pose_min_overlap:
        return None, f"overlap {overlap:.2f} < {config.pose_min_overlap}"
    offset = np.einsum("ij,ij->i", moved[inlier] - target.points[nearest[inlier]], target.normals[nearest[inlier]])
    residual = float(np.sqrt(np.mean(offset**2)))
    if residual > config.pose_max_residual:
        return None, f"residual {residual:.3g} > {config.pose_max_residual} {config.units}"
    ratio = _constraint_ratio(target.points[nearest[inlier]], target.normals[nearest[inlier]], radius)
    if ratio < _MIN_CONSTRAINT_RATIO:
        return None, f"degenerate surface (constraint ratio {ratio:.1e}: the overlap does not pin every direction)"
    return _Pair(-1, -1, transform, residual, overlap), "ok"


def _weighted_incidence(n: int, edges: list[_Pair]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Source and target index, and the (E, n) incidence matrix (+w at source, -w at target) and
    weights w of the edges: a pair counts more the more surface it shares and the better it fits."""
    src = np.array([e.source for e in edges])
    tgt = np.array([e.target for e in edges])
    weight = np.array([e.overlap / e.residual for e in edges])
    weight = weight / weight.max()
    incidence = np.zeros((len(edges), n))
    incidence[np.arange(len(edges)), src] = weight
    incidence[np.arange(len(edges)), tgt] = -weight
    return src, tgt, incidence, weight


def _average_rotations(n: int, edges: list[_Pair], iterations: int = 8) -> np.ndarray:
    """(n, 3, 3) rotations R with R_i ~ R_j R_ij for every edge, minimum-norm (Lie-algebraic averaging)."""
    rotations = np.repeat(np.eye(3)[None], n, axis=0)
    if not edges:
        return rotations
    src, tgt, incidence, weight = _weighted_incidence(n, edges)
    measured = np.stack([e.transform[:3, :3] for e in edges])
    for _ in range(iterations):
        # residual e_ij = log(R_j R_ij R_i^T); left updates with d_i - d_j = e_ij cancel it to first order.
        err = Rotation.from_matrix(rotations[tgt] @ measured @ rotations[src].transpose(0, 2, 1)).as_rotvec()
        step = np.linalg.lstsq(incidence, err * weight[:, None], rcond=None)[0]  # min-norm: zero mean per group
        rotations = Rotation.from_rotvec(step).as_matrix() @ rotations
        if np.abs(step).max() < 1e-10:
            break
    return rotations


def _solve_graph(n: int, edges: list[_Pair]) -> tuple[np.ndarray, np.ndarray]:
    """Corrections (R_i, t_i) in the centred frame with C_i = C_j T_ij in least squares, zero mean per group."""
    rotations = _average_rotations(n, edges)
    translations = np.zeros((n, 3))
    if edges:
        src, tgt, incidence, weight = _weighted_incidence(n, edges)
        # t_i - t_j = R_j t_ij, exactly linear once the rotations are known.
        rhs = np.einsum("eij,ej->ei", rotations[tgt], np.stack([e.transform[:3, 3] for e in edges]))
        translations = np.linalg.lstsq(incidence, rhs * weight[:, None], rcond=None)[0]
    return rotations, translations


def _edge_disagreement(edge: _Pair, rotations: np.ndarray, translations: np.ndarray, radius: float) -> float:
    """How far (config units, at ``radius`` from the centre) the solved corrections miss the edge's measurement."""
    i, j = edge.source, edge.target
    rot = Rotation.from_matrix(rotations[j] @ edge.transform[:3, :3] @ rotations[i].T).magnitude()
    shift = np.linalg.norm(rotations[j] @ edge.transform[:3, 3] + translations[j] - translations[i])
    return float(rot * radius + shift)


def _correction_size(rotation: np.ndarray, translation: np.ndarray, centre_offset: np.ndarray) -> tuple[float, float]:
    """(degrees, how far a camera at ``centre_offset`` from the scene centre moves) of one correction."""
    angle = float(np.rad2deg(Rotation.from_matrix(rotation).magnitude()))
    moved = rotation @ centre_offset + translation - centre_offset
    return angle, float(np.linalg.norm(moved))


def refine_poses(
    bundle: SceneBundle, config: ShadowCorrConfig | None = None
) -> tuple[SceneBundle, list[ViewPoseCorrection]]:
    """Register the views to each other and correct their poses (see the module docstring).

    Returns a copy of the bundle with refined poses (views that could not be refined
    keep theirs) and one report per view, in view order.  The input is not modified.
    """
    config = config or ShadowCorrConfig()
    scale = unit_scale(bundle.units, config.units)
    n = len(bundle.views)
    identity = np.eye(4).tolist()
    if bundle.point_segments is not None or any(v.depth is None for v in bundle.views):
        return bundle, [ViewPoseCorrection(view=v.name, status="not_registered", rotation_deg=0.0, translation=0.0,
                                           correction=identity, message="the bundle has no depth images to register")
                        for v in bundle.views]

    raw = [_view_points(v, config.max_depth / scale) * scale for v in bundle.views]
    # Median centre and distance: a view declared far away (another place) must not move them.
    all_points = np.concatenate([p for p in raw if p.size] or [np.zeros((1, 3))])
    centre = np.median(all_points, axis=0)
    radius = max(float(np.median(np.linalg.norm(all_points - centre, axis=1))), config.pose_point_spacing)
    coarse = _coarse_match_distance(config, radius)
    clouds = [_make_cloud(p - centre, config, coarse) if p.shape[0] else None for p in raw]

    why: dict[int, str] = {}
    edges: list[_Pair] = []
    for i in range(n):
        for j in range(i + 1, n):
            a, b = clouds[i], clouds[j]
            if a is None or b is None:
                continue
            shared = np.intersect1d(a.cells, b.cells, assume_unique=True).size
            if shared < config.pose_min_overlap * min(a.cells.size, b.cells.size):
                continue
            pair, reason = _register(a, b, config, radius)
            if pair is None:
                why.setdefault(i, f"registration with {bundle.views[j].name}: {reason}")
                why.setdefault(j, f"registration with {bundle.views[i].name}: {reason}")
                continue
            edges.append(dataclasses.replace(pair, source=i, target=j))

    # Solve; drop disagreeing edges and out-of-bound views until everything left is consistent.
    status = ["corrected"] * n
    camera_offset = np.stack([v.camera_center * scale for v in bundle.views]) - centre
    agree = max(config.pose_max_residual, config.pose_point_spacing / 2.0)
    while True:
        rotations, translations = _solve_graph(n, edges)
        if edges:
            miss = np.array([_edge_disagreement(e, rotations, translations, radius) for e in edges])
            worst = int(np.argmax(miss))
            if miss[worst] > agree and len(edges) > 1:
                e = edges.pop(worst)
                for k in (e.source, e.target):
                    why.setdefault(k, f"its registration with {bundle.views[e.target + e.source - k].name} "
                                      f"disagrees with the others by {miss[worst] / scale:.3g} {bundle.units}")
                continue
        sizes = [_correction_size(rotations[k], translations[k], camera_offset[k]) for k in range(n)]
        over = [k for k in range(n) if status[k] == "corrected"
                and (sizes[k][0] > config.pose_max_rotation_deg or sizes[k][1] > config.pose_max_translation)]
        if not over:
            break
        worst = max(over, key=lambda k: sizes[k][0] / config.pose_max_rotation_deg + sizes[k][1] / config.pose_max_translation)
        status[worst] = "correction_too_large"
        why[worst] = (f"the correction ({sizes[worst][0]:.2f} deg, {sizes[worst][1] / scale:.3g} {bundle.units}) "
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
    # view would move by more, the declared poses already agree and are left exactly as they are.
    refined = [k for k in range(n) if status[k] == "corrected"]
    if refined and all(sizes[k][0] < config.pose_min_rotation_deg
                       and sizes[k][1] < config.pose_min_translation for k in refined):
        for k in refined:
            status[k] = "unchanged"
            why[k] = (f"the declared pose agrees with its neighbours to within {sizes[k][0]:.3f} deg and "
                      f"{sizes[k][1] / scale:.3g} {bundle.units} (under pose_min_rotation_deg / pose_min_translation); kept")
    reports, views = [], []
    for k, view in enumerate(bundle.views):
        mine = [e for e in edges if k in (e.source, e.target)]
        correction = np.eye(4)
        if status[k] == "corrected":
            r, t = rotations[k], translations[k]
            correction[:3, :3] = r
            correction[:3, 3] = (t + centre - r @ centre) / scale  # centred config frame -> bundle world frame
        angle, shift = sizes[k] if status[k] == "corrected" else (0.0, 0.0)
        miss = max((_edge_disagreement(e, rotations, translations, radius) for e in mine), default=0.0)
        consistent = miss <= agree / 2.0 if status[k] in ("corrected", "unchanged") else None
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
