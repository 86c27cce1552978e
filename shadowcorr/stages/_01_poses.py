"""Stage 1 (optional): refine the declared camera poses from the scene itself.

Pairwise registration (steps 1 and 2: the views' surfaces, pairs registered one by one) is in
:mod:`._01_registration`; the pose graph, the bounds and the masks' confirmation are here.

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
   ``pose_max_residual`` (or 1.5 noise sigmas), the surface constrains all six degrees of freedom (the
   point-to-plane information matrix is not degenerate) and it does not fit the surfaces clearly
   worse than the declared poses (``_DECLARED_FIT_SHARE`` of their matched share over residual, at
   the same matching distance): a registration that converged to a wrong minimum fits worse than
   where it started.  The views' clouds are made
   ``num_threads`` at a time; registration keeps one thread (small_gicp's multi-threaded
   sums would make the result depend on the thread count).
   Views left without any usable pair are registered once more on their *grazing* surfaces
   (``_grazing_pairs``): cameras under a metre high see the ground they share with other views
   at 5-15 degrees of incidence, where neighbouring samples lie further apart than a normal
   allows; with normals up to ``_GRAZING_EDGE_RATIO`` spacings, pairs need only match a
   quarter of ``pose_min_overlap``, and the masks (step 5) turn down the wrong registrations
   such thin overlaps also give.  On such overlaps GICP's wide matching can carry the surfaces
   into a wrong minimum that point-to-plane cannot leave, so point-to-plane also starts from the
   declared poses and the better fit of the two is taken (on the low rig of the quality benchmark
   with the ``mild`` errors, 30 scenes, the pairs' median relative rotation error went from 0.55
   to 0.25 degrees).  Views that register are left as they were.  Ground shared at grazing
   incidence pins a view's tilt and height but hardly where it stands along it, so a view
   registered only on surfaces seen at under ``_GRAZING_INCIDENCE_DEG`` takes its correction's
   rotation (about its own camera) and vertical shift, and keeps its declared horizontal position
   (``_keep_grazing_positions``).
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
   with the declared poses, by more than a tie (``_CONFIRM_STANDARD_ERRORS``); otherwise
   every declared pose of the group stays (``not_confirmed``).  Only samples away from a
   mask's outline take part: a segmenter that erodes its masks makes the outlines disagree
   exactly where the right poses let the views see them, so outline samples spoke against
   good corrections.  The masks judge
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
6. **Turned to the masks** (``pose_mask_alignment``, :mod:`._01_mask_alignment`).  Views left
   ``not_registered`` or ``correction_too_large`` (cameras too low to share surface) turn about
   their camera centres until the other views' masked pixels land on their masks; the views
   registration bore out are held.  They keep their status, and their reports give the turn.

Work is bounded and vectorised: about 20 000 samples per view, at most
``_COARSE_ITERATIONS`` GICP iterations (one thread) and ``2 x _FINE_ITERATIONS``
point-to-plane steps per pair, at most a few pairs per view, and a sparse pose graph with
six unknowns per view.  ``benchmarks/bench_poses.py`` measures time and accuracy.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation

from ..bundle import SceneBundle, View, unit_scale
from ..config import ShadowCorrConfig
from ..ops import thread_map
from ..poses import world_up
from ..result import ViewPoseCorrection
from ._01_mask_alignment import align_to_masks
from ._01_registration import (
    _Cloud,
    _Pair,
    _candidate_pairs,
    _cell_keys,
    _coarse_match_distance,
    _make_cloud,
    _register,
    _rotation_angle,
    _view_grid,
)

#: Views left without any usable pair are tried again with normals up to this many spacings (ground
#: seen at grazing incidence down to about 5 degrees, whose row neighbours lie 1 / sin(incidence)
#: spacings apart) and a pair need only match ``_GRAZING_OVERLAP_SHARE`` of ``pose_min_overlap``.
_GRAZING_EDGE_RATIO = 12.0
_GRAZING_OVERLAP_SHARE = 0.25
#: A view registered only on grazing surfaces, each seen by the pair's two cameras at under this
#: incidence on average (degrees, medians over the matched surface), keeps its declared horizontal
#: position (``_keep_grazing_positions``).
_GRAZING_INCIDENCE_DEG = 20.0
#: A point projected into another view is seen there when that view's depth at the pixel is
#: within this share of the point's own depth (not hidden behind something, not in front).
_VISIBLE_DEPTH_SHARE = 0.03
#: The masks judge a group's corrections only where, with the declared poses, they agree on at
#: least this share of the surface the views share (see step 5 of the module docstring).
_JUDGING_AGREEMENT = 0.9
#: Judging masks confirm a correction only when it makes them agree better by more than this many
#: standard errors of the difference (binomial, over the samples compared): with exact poses under
#: 2 % depth noise, corrections of 0.03-0.28 degrees gained 0.05 of one (16 disagreeing samples of
#: 1816 before, 15 of 1734 after) and the labels lost 1.9 points; right corrections of half a degree
#: gained 0.75-0.8 of one.
_CONFIRM_STANDARD_ERRORS = 0.3


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


def _masks_refuse(before: tuple[int, int], after: tuple[int, int]) -> bool:
    """Whether the masks turn a group's corrections down, from :func:`_mask_agreement`'s counts
    with the declared poses (``before``) and with the corrected ones (``after``).  Only masks that
    agree with the declared poses on at least ``_JUDGING_AGREEMENT`` judge (step 5 of the module
    docstring); those refuse a correction that does not make them agree better by more than
    ``_CONFIRM_STANDARD_ERRORS`` standard errors of the difference: a smaller gain is a tie."""
    n_before, n_after = (max(agree + disagree, 1) for agree, disagree in (before, after))
    share_before, share_after = before[0] / n_before, after[0] / n_after
    if share_before < _JUDGING_AGREEMENT:
        return False
    spread = np.sqrt(share_before * (1.0 - share_before) / n_before + share_after * (1.0 - share_after) / n_after)
    return share_after - share_before <= _CONFIRM_STANDARD_ERRORS * spread


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
    paired = _paired(len(clouds), edges)
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
        pair, reason = _register(grazing[i], grazing[j], config, min_overlap, from_declared=True)
        if pair is None:
            for k, other in ((i, j), (j, i)):
                if not paired[k]:
                    why[k] = f"registration with {bundle.views[other].name}: {reason}"
            continue
        edges.append(dataclasses.replace(pair, source=i, target=j))
    return tried


def _keep_grazing_positions(rotations: np.ndarray, translations: np.ndarray, camera_offset: np.ndarray,
                            grazing: np.ndarray, group: np.ndarray, up: tuple[int, float]
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Corrections (centred frame) in which every ``grazing`` view's camera keeps its declared
    horizontal position: it turns about its own centre and moves only up or down (``up``: the
    world's up axis, ``poses.world_up``).

    A view registered only on its grazing surfaces (``_grazing_pairs``), every one of them seen by
    both cameras at a median incidence under ``_GRAZING_INCIDENCE_DEG`` on average, shares mostly
    ground with the other views: the overlap pins its tilt and its height above that ground, but
    hardly where it stands along it, and there registration slides (on the low rig of the quality
    benchmark under the ``mild`` errors, the whole corrections left such views' points 7-10 cm
    from where they belong in the scenes that lost most, against 3-4 cm with the declared poses).

    The graph's corrections have zero mean per group, so each view's rotation also carries the
    group's invisible common rotation; turned about each camera's own centre instead of the
    scene's, that common part would no longer cancel, and the views would disagree by about its
    angle times their distance.  So each group with two or more grazing views is first moved as a
    whole (a turn about the up axis and a horizontal shift, which no image can see) so that their
    corrected camera centres lie as near their declared ones as least squares can bring them.

    On ``syn:4v-low`` (30 scenes): ``mild`` 97.98 against 97.48 with the whole corrections and
    97.74 without refinement; ``field`` 95.49 against 95.54; ``harsh`` 87.00 against 87.04; pose
    errors alone (1 / 2 degrees, 2.5 / 5 cm, rotations or shifts alone) within 0.06 of the whole
    corrections or better (2 degrees: 91.90 against 91.36).  Without the common turn, the rows of
    pose errors alone lost up to 1.2 points.  The opposite cameras of ``syn:2v-opposite``, 3.3 m
    high, also register only on the grazing pass, but see the surface they share at 21-24 degrees
    (the low rig's pairs: under 20 in 92 of 99), rocks' sides that pin them every way; kept in
    place too, they lost 0.5 and 0.9 points under ``field`` and ``harsh``.
    """
    rotations, translations = rotations.copy(), translations.copy()
    axis = up[0]
    vertical = np.eye(3)[axis]
    flat = np.ones(3, dtype=bool)
    flat[axis] = False
    for g in np.unique(group[grazing]).tolist():
        members = np.flatnonzero(group == g)
        held = members[grazing[members]]
        if held.size < 2:
            continue
        moved = np.einsum("kij,kj->ki", rotations[held], camera_offset[held]) + translations[held]
        # Horizontal Procrustes: the turn about the up axis taking the corrected centres onto the declared.
        a = (moved - moved.mean(axis=0)) * flat
        b = (camera_offset[held] - camera_offset[held].mean(axis=0)) * flat
        turn = Rotation.from_rotvec(vertical * np.arctan2(np.cross(a, b).sum(axis=0) @ vertical,
                                                           np.einsum("ij,ij->", a, b))).as_matrix()
        shift = (camera_offset[held].mean(axis=0) - turn @ moved.mean(axis=0)) * flat
        rotations[members] = turn @ rotations[members]
        translations[members] = translations[members] @ turn.T + shift
    # A correction moves camera centre o to R o + t; turned about the camera itself, t = o - R o.
    turned = np.einsum("kij,kj->ki", rotations[grazing], camera_offset[grazing])
    rise = (turned + translations[grazing] - camera_offset[grazing])[:, axis]
    translations[grazing] = camera_offset[grazing] - turned
    translations[grazing, axis] += rise
    return rotations, translations


def _paired(n: int, edges: list[_Pair]) -> np.ndarray:
    """(n,) whether each view has at least one of ``edges``."""
    paired = np.zeros(n, dtype=bool)
    for e in edges:
        paired[[e.source, e.target]] = True
    return paired


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
    first_pass = _paired(n, edges)
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

    # How consistent the registrations are is judged on the graph's own solution, before views
    # registered only on grazing surfaces keep their horizontal positions.
    graph_misses = _disagreements(edges, rotations, translations)
    # A view's registrations pin its horizontal position unless every one of them is on surface
    # both cameras see at grazing incidence (their mean, the pair's median).
    incidence = np.zeros(n)
    for e in edges:
        incidence[[e.source, e.target]] = np.maximum(incidence[[e.source, e.target]], np.mean(e.incidence))
    grazing = ~first_pass & (incidence < _GRAZING_INCIDENCE_DEG)
    group = _groups(n, edges)
    rotations, translations = _keep_grazing_positions(
        rotations, translations, camera_offset, grazing, group,
        world_up(np.stack([v.pose for v in bundle.views]), config.up_axis))
    degrees, shifts = _correction_sizes(rotations, translations, camera_offset)
    in_graph = _paired(n, edges)
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
        if _masks_refuse(before, after):
            for k in members:
                status[k] = "not_confirmed"
                why[k] = (f"corrected, the views' masks would not agree better where they see the same surface "
                          f"({share_after:.3f} against {share_before:.3f} with the declared poses): the "
                          "registration is not borne out by the scene; pose kept")
    incident: list[list[_Pair]] = [[] for _ in range(n)]
    worst_miss = np.zeros(n)
    for e, m in zip(edges, graph_misses):
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
    if config.pose_mask_alignment:
        _align_unregistered(views, reports, config.max_depth / scale, config.pose_max_rotation_deg)
    return dataclasses.replace(bundle, views=views, warnings=list(bundle.warnings)), reports


#: Statuses of the views that ``pose_mask_alignment`` turns to the other views' masks: those whose
#: declared pose registration could not check.  ``not_confirmed`` views stay: registration saw them,
#: and under depth noise their declared poses are often exact while the alignment drifts.
_MASK_ALIGNED = ("not_registered", "correction_too_large")


def _align_unregistered(views: list[View], reports: list[ViewPoseCorrection], max_depth: float,
                        max_rotation_deg: float) -> None:
    """Turn the views left ``_MASK_ALIGNED`` to the other views' masks (:func:`align_to_masks`), in place:
    their poses, and their reports' correction, rotation and message (the status stays).  A turn
    beyond ``max_rotation_deg`` is refused, as a registration's correction would be."""
    free = [k for k, r in enumerate(reports) if r.status in _MASK_ALIGNED]
    if not free:
        return
    poses = align_to_masks(views, free, max_depth)
    for k in free:
        correction = poses[k] @ np.linalg.inv(views[k].pose)
        degrees = float(np.rad2deg(_rotation_angle(correction[:3, :3])))
        said = reports[k].message
        if degrees > max_rotation_deg:
            note = (f"the other views' masks would turn it {degrees:.2f} deg, beyond the bound "
                    f"({max_rotation_deg} deg); pose kept")
            reports[k] = reports[k].model_copy(update={"message": f"{said}; {note}" if said else note})
            continue
        note = f"turned {degrees:.3f} deg about its camera centre to the other views' masks (pose_mask_alignment)"
        reports[k] = reports[k].model_copy(update={
            "rotation_deg": round(degrees, 4), "correction": correction.round(9).tolist(),
            "message": f"{said}; {note}" if said else note})
        views[k] = dataclasses.replace(views[k], pose=poses[k])


#: Statuses of a view whose pose the registration bore out: moved by a confirmed correction, or kept
#: because every view registered and none needed a correction.
_VERIFIED = ("corrected", "unchanged")


def unverified_poses(reports: list[ViewPoseCorrection]) -> np.ndarray:
    """(V,) bool: whether each view's declared pose stands without the registration bearing it out
    (``not_registered``, ``correction_too_large``, ``not_confirmed``).  Such a pose keeps whatever
    error it was declared with; the surface evidence allows for it
    (``projection_depth_tolerance_unverified_rel``)."""
    return np.array([r.status not in _VERIFIED for r in reports], dtype=bool)


def pose_warnings(reports: list[ViewPoseCorrection]) -> list[str]:
    """One warning per view whose pose could not be refined or still looks inconsistent."""
    out = []
    for r in reports:
        if r.status not in _VERIFIED:
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
