"""Perturbations of an in-memory ``SceneBundle``: what a real sensor and segmenter do to a scene.

Each function is pure: it takes a bundle and a ``numpy.random.Generator`` and returns a
new bundle (unchanged arrays are shared, never written to), so a clean scene can be
perturbed many ways with fixed seeds.  They work on depth + mask bundles in any units;
lengths are given in centimetres and converted to the bundle's units.

Ground truth stays exact.  A perturbation that keeps every mask id's meaning (depth
noise, holes, pose errors, erosion/dilation, dropped masks) leaves the ground-truth mode
as it is.  One that creates or fuses ids (splits, merges) converts the
bundle to ``ground_truth = "mapped"``: each view's ``instance_objects`` maps its new ids
to the objects they came from (a merged mask maps to the object owning most of its
pixels).  New ids are fresh per view (above the view's largest id), so an id says
nothing across views: the truth lives only in ``instance_objects``.

Spurious blobs (``spurious_blobs``) are the one perturbation that adds masks with no
rock behind them: a blob on the background is an object of its own, mapped to a fresh
object id (from ``SPURIOUS_OBJECT_BASE`` up), never shared with a rock or another blob;
see that function for why it is not "unknown" (-1).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..bundle import SceneBundle, View, unit_scale
from .noise import morph_mask, noisy_depth, perturbed_pose

__all__ = [
    "DEPTH_NOISE_REFERENCE_CM",
    "SPURIOUS_OBJECT_BASE",
    "depth_holes",
    "depth_noise",
    "drop_masks",
    "mixed_pixels",
    "merge_touching",
    "morph_masks",
    "pose_error",
    "split_masks",
    "spurious_blobs",
]

#: Depth at which ``depth_noise``'s ``fraction`` is the noise sigma relative to depth
#: (the real rig's camera-to-field distance).
DEPTH_NOISE_REFERENCE_CM = 750.0

#: Smallest object id a spurious background blob gets (above every rock id a bundle
#: plausibly has), so such blobs are recognisable in the ground truth.
SPURIOUS_OBJECT_BASE = 1_000_000


# --------------------------------------------------------------------------- helpers
def _image_views(bundle: SceneBundle) -> list[View]:
    if bundle.point_segments is not None or any(v.mask is None or v.depth is None for v in bundle.views):
        raise ValueError("perturbations need depth + mask views (not a point-segment bundle)")
    return bundle.views


def _present_ids(mask: np.ndarray) -> np.ndarray:
    """Sorted non-zero ids in ``mask``."""
    if mask.size == 0:
        return np.zeros(0, dtype=np.int64)
    top = int(mask.max())
    if top < 1 << 20:  # small ids (the usual case): a histogram beats sorting every pixel
        return np.flatnonzero(np.bincount(mask.ravel(), minlength=1)[1:]) + 1
    ids = np.unique(mask)
    return ids[ids != 0].astype(np.int64)


def _truth_table(bundle: SceneBundle, view: View) -> dict[int, int] | None:
    """Ground truth of one view as id -> object, or None when the bundle has none."""
    if bundle.ground_truth == "instance":
        return {int(i): int(i) for i in _present_ids(view.mask)}
    if bundle.ground_truth == "mapped":
        return dict(view.instance_objects or {})
    return None


def _with_masks(bundle: SceneBundle, masks: list[np.ndarray], tables: list[dict[int, int] | None]) -> SceneBundle:
    """A copy of ``bundle`` with new masks and, when it carries truth, ``mapped`` ground truth
    restricted to the ids each new mask still holds."""
    views = []
    for v, mask, table in zip(bundle.views, masks, tables):
        present = set(_present_ids(mask).tolist())
        objects = None if table is None else {i: o for i, o in table.items() if i in present}
        views.append(replace(v, mask=mask, instance_objects=objects))
    truth = "mapped" if bundle.has_ground_truth else "none"
    return replace(bundle, views=views, ground_truth=truth, warnings=list(bundle.warnings))


def _remap(mask: np.ndarray, ids: np.ndarray, new_ids: np.ndarray) -> np.ndarray:
    """``mask`` with every pixel of ``ids[k]`` (sorted) set to ``new_ids[k]``; other pixels kept."""
    flat = mask.ravel()
    pos = np.minimum(np.searchsorted(ids, flat), ids.size - 1)
    hit = ids[pos] == flat
    out = flat.astype(np.int64)
    out[hit] = new_ids[pos[hit]]
    return _mask_dtype(out.reshape(mask.shape), mask.dtype)


def _mask_dtype(mask: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """``mask`` in ``dtype`` when its ids fit, else int64."""
    fits = mask.size == 0 or int(mask.max()) <= np.iinfo(dtype).max
    return mask.astype(dtype if fits else np.int64)


def _choose(rng: np.random.Generator, n: int, share: float) -> np.ndarray:
    """``round(share * n)`` distinct indices of ``range(n)``, as a boolean mask."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"share must lie in [0, 1], got {share}")
    chosen = np.zeros(n, dtype=bool)
    chosen[rng.choice(n, size=int(round(share * n)), replace=False)] = True
    return chosen


def _all_masks(views: list[View]) -> tuple[np.ndarray, np.ndarray]:
    """Every (view index, id) mask of the bundle, as two parallel arrays."""
    per_view = [_present_ids(v.mask) for v in views]
    view_of = np.repeat(np.arange(len(views)), [ids.size for ids in per_view])
    return view_of, np.concatenate(per_view) if per_view else np.zeros(0, dtype=np.int64)


# --------------------------------------------------------------------------- depth
def depth_noise(bundle: SceneBundle, rng: np.random.Generator, fraction: float, *,
                z_ref_cm: float = DEPTH_NOISE_REFERENCE_CM, correlation_px: float = 0.0) -> SceneBundle:
    """Gaussian depth noise growing with the square of depth, like a stereo or ToF sensor.

    ``sigma(z) = fraction * z^2 / z_ref``: ``fraction`` is the noise relative to depth at
    ``z_ref`` (750 cm, the rig's working distance); e.g. 0.01 gives 7.5 cm at 7.5 m and
    1.9 cm at 3.75 m.  Invalid pixels stay invalid; valid ones stay valid.

    ``correlation_px`` > 0 makes the noise correlated over about that many pixels, as a
    stereo matcher's correlation window makes it: white noise smoothed by a Gaussian of
    that standard deviation and rescaled to unit variance, so each pixel's ``sigma`` is
    unchanged while neighbours err together (which averaging over a surface cannot remove).
    """
    if fraction < 0:
        raise ValueError(f"fraction must be >= 0, got {fraction}")
    if correlation_px < 0:
        raise ValueError(f"correlation_px must be >= 0, got {correlation_px}")
    z_ref = z_ref_cm * unit_scale("cm", bundle.units)
    views = []
    for v in _image_views(bundle):
        z = np.where(v.depth > 0, v.depth, 0.0).astype(np.float64)
        sigma = fraction * z * z / z_ref
        if correlation_px > 0:
            field = ndimage.gaussian_filter(rng.standard_normal(z.shape), correlation_px)
            field /= max(float(field.std()), 1e-12)
            depth = np.where(v.depth > 0, np.maximum(z + sigma * field, 1e-3), 0.0).astype(np.float32)
        else:
            depth = noisy_depth(rng, v.depth, sigma, 0.0)
        views.append(replace(v, depth=depth))
    return replace(bundle, views=views, warnings=list(bundle.warnings))


def mixed_pixels(bundle: SceneBundle, rng: np.random.Generator, share: float = 1.0, *,
                 jump: float = 0.05) -> SceneBundle:
    """Mixed ("flying") pixels at depth edges, as a ToF sensor or a stereo matcher's window
    makes them where a rock's silhouette meets what lies behind it.

    A valid pixel whose 3 x 3 neighbourhood spans a depth jump of more than ``jump`` times
    its own depth is, with probability ``share``, given a depth drawn uniformly between the
    nearest and the farthest valid depth of that neighbourhood: a point floating between
    the rock and the ground.  Masks are unchanged (the segmenter saw the colour image).
    """
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"share must lie in [0, 1], got {share}")
    views = []
    for v in _image_views(bundle):
        depth = v.depth.astype(np.float64)
        valid = depth > 0
        near = ndimage.minimum_filter(np.where(valid, depth, np.inf), size=3)
        far = ndimage.maximum_filter(np.where(valid, depth, 0.0), size=3)
        edge = valid & (far - near > jump * depth) & (rng.random(depth.shape) < share)
        out = v.depth.copy()
        out[edge] = near[edge] + rng.random(int(edge.sum())) * (far[edge] - near[edge])
        views.append(replace(v, depth=out))
    return replace(bundle, views=views, warnings=list(bundle.warnings))


def depth_holes(bundle: SceneBundle, rng: np.random.Generator, fraction: float, *,
                blob_px: float = 16.0) -> SceneBundle:
    """Invalid-depth holes: ``fraction`` of each view's valid depth pixels become invalid.

    The holes are smooth random blobs about ``blob_px`` pixels across (a coarse random
    field, upsampled; its top ``fraction`` of valid pixels are cut), like the dropouts
    of a depth sensor on dark or glancing surfaces.  Masks are unchanged.
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction must lie in [0, 1], got {fraction}")
    if blob_px <= 0:
        raise ValueError(f"blob_px must be > 0, got {blob_px}")
    views = []
    for v in _image_views(bundle):
        h, w = v.depth.shape
        coarse = rng.standard_normal((int(np.ceil(h / blob_px)) + 1, int(np.ceil(w / blob_px)) + 1))
        field = ndimage.zoom(coarse, (h / coarse.shape[0], w / coarse.shape[1]), order=1, grid_mode=True,
                             mode="grid-constant")[:h, :w]
        field = field + 1e-9 * rng.random(field.shape)  # break ties of the interpolation
        valid = np.flatnonzero(v.depth.ravel() > 0)
        k = int(round(fraction * valid.size))
        depth = v.depth.copy()
        if k:
            cut = valid[np.argpartition(field.ravel()[valid], valid.size - k)[valid.size - k:]]
            depth.ravel()[cut] = 0.0
        views.append(replace(v, depth=depth))
    return replace(bundle, views=views, warnings=list(bundle.warnings))


# --------------------------------------------------------------------------- calibration
def pose_error(bundle: SceneBundle, rng: np.random.Generator, *, rotation_deg: float = 0.0,
               translation_cm: float = 0.0, up_to: bool = False) -> SceneBundle:
    """Miscalibrated extrinsics: each camera's declared pose is off by exactly the given amounts.

    Every camera is rotated about its own centre by ``rotation_deg`` about a random axis
    and moved ``translation_cm`` in a random direction (independently per camera); the
    images stay those of the true pose.  With ``up_to`` each camera's two amounts are
    drawn uniformly between 0 and the given ones instead (a rig whose cameras are
    calibrated unevenly well).
    """
    if rotation_deg < 0 or translation_cm < 0:
        raise ValueError("rotation_deg and translation_cm must be >= 0")
    shift = translation_cm * unit_scale("cm", bundle.units)
    scale = rng.random((len(bundle.views), 2)) if up_to else np.ones((len(bundle.views), 2))
    views = [replace(v, pose=perturbed_pose(rng, v.pose, rotation_deg * a, shift * t))
             for v, (a, t) in zip(bundle.views, scale)]
    return replace(bundle, views=views, warnings=list(bundle.warnings))


# --------------------------------------------------------------------------- masks
def morph_masks(bundle: SceneBundle, rng: np.random.Generator, px: int) -> SceneBundle:
    """Every mask dilated (``px`` > 0, into the background only) or eroded (``px`` < 0) by |px| pixels.

    Ids keep their meaning, so ground truth is unchanged.  (``rng`` is unused: the
    operation is deterministic; it is taken for a uniform signature.)
    """
    del rng
    views = [replace(v, mask=morph_mask(v.mask, int(px))) for v in _image_views(bundle)]
    return replace(bundle, views=views, warnings=list(bundle.warnings))


def drop_masks(bundle: SceneBundle, rng: np.random.Generator, share: float) -> SceneBundle:
    """``round(share * n)`` of the bundle's n masks (view, id) set to background (a missed detection)."""
    views = _image_views(bundle)
    view_of, ids = _all_masks(views)
    chosen = _choose(rng, ids.size, share)
    out = []
    for vi, v in enumerate(views):
        gone = ids[chosen & (view_of == vi)]
        if gone.size == 0:
            out.append(v)
            continue
        mask = np.where(np.isin(v.mask, gone), 0, v.mask).astype(v.mask.dtype)
        gone_ids = set(gone.tolist())
        table = v.instance_objects and {i: o for i, o in v.instance_objects.items() if i not in gone_ids}
        out.append(replace(v, mask=mask, instance_objects=table))
    return replace(bundle, views=out, warnings=list(bundle.warnings))


def split_masks(bundle: SceneBundle, rng: np.random.Generator, share: float) -> SceneBundle:
    """``round(share * n)`` of the n masks (view, id) cut in two by a straight line.

    The line passes through the mask's pixel centroid at a random angle; the pixels on
    its positive side get a fresh id of that view, mapped to the same object.
    """
    views = _image_views(bundle)
    view_of, ids = _all_masks(views)
    chosen = _choose(rng, ids.size, share)
    angles = rng.uniform(0.0, np.pi, size=ids.size)
    masks, tables = [], []
    for vi, v in enumerate(views):
        table = _truth_table(bundle, v)
        cut = np.flatnonzero(chosen & (view_of == vi))
        if cut.size == 0:
            masks.append(v.mask)
            tables.append(table)
            continue
        mask = v.mask.astype(np.int64)
        rows, cols = np.nonzero(np.isin(mask, ids[cut]))
        slot = np.searchsorted(ids[cut], mask[rows, cols])  # which chosen mask each pixel is in (ids are sorted)
        count = np.bincount(slot, minlength=cut.size)
        cy = np.bincount(slot, rows, minlength=cut.size) / count
        cx = np.bincount(slot, cols, minlength=cut.size) / count
        theta = angles[cut][slot]
        side = (cols - cx[slot]) * np.cos(theta) + (rows - cy[slot]) * np.sin(theta) > 0
        new_ids = int(mask.max()) + 1 + np.arange(cut.size)
        mask[rows[side], cols[side]] = new_ids[slot[side]]
        if table is not None:
            for s, j in enumerate(cut):
                if int(ids[j]) in table:
                    table[int(new_ids[s])] = table[int(ids[j])]
        masks.append(_mask_dtype(mask, v.mask.dtype))
        tables.append(table)
    return _with_masks(bundle, masks, tables)


def _touching_pairs(mask: np.ndarray, connectivity: int) -> np.ndarray:
    """Distinct (a, b), a < b, of different non-zero ids that touch (4- or 8-adjacent pixels)."""
    shifts = [(0, 1), (1, 0)] + ([(1, 1), (1, -1)] if connectivity == 8 else [])
    h, w = mask.shape
    pairs = []
    for dy, dx in shifts:  # pixel (y, x) against (y + dy, x + dx)
        a = mask[: h - dy, max(0, -dx): w - max(0, dx)]
        b = mask[dy:, max(0, dx): w - max(0, -dx)]
        touch = (a != b) & (a > 0) & (b > 0)
        pairs.append(np.stack([np.minimum(a[touch], b[touch]), np.maximum(a[touch], b[touch])], axis=1))
    both = np.concatenate(pairs).astype(np.int64)
    return np.unique(both, axis=0) if both.size else np.zeros((0, 2), dtype=np.int64)


def merge_touching(bundle: SceneBundle, rng: np.random.Generator, share: float, *,
                   connectivity: int = 8) -> SceneBundle:
    """``round(share * n)`` of the n touching pairs of masks (per view) fused into one mask.

    A pair is two different ids of one view with ``connectivity``-adjacent pixels.
    Chosen pairs that share an id fuse transitively.  Each fused mask gets a fresh id,
    mapped to the object owning most of its pixels.  Only the connected regions where the
    masks touch are fused, as a segmenter that cannot see a boundary would fuse them: a
    piece of a mask that touches none of the others (a blob of its own, elsewhere in the
    image) keeps its id and its object, instead of carrying the majority's object.
    """
    if connectivity not in (4, 8):
        raise ValueError(f"connectivity must be 4 or 8, got {connectivity}")
    views = _image_views(bundle)
    per_view = [_touching_pairs(v.mask, connectivity) for v in views]
    chosen = _choose(rng, sum(p.shape[0] for p in per_view), share)
    offsets = np.cumsum([0] + [p.shape[0] for p in per_view])
    masks, tables = [], []
    for vi, v in enumerate(views):
        table = _truth_table(bundle, v)
        pairs = per_view[vi][chosen[offsets[vi]: offsets[vi + 1]]]
        if pairs.shape[0] == 0:
            masks.append(v.mask)
            tables.append(table)
            continue
        nodes, inverse = np.unique(pairs, return_inverse=True)
        inverse = inverse.reshape(pairs.shape)
        graph = coo_matrix((np.ones(len(pairs)), (inverse[:, 0], inverse[:, 1])), shape=(nodes.size,) * 2)
        n_groups, group = connected_components(graph, directed=False)
        new_ids = int(v.mask.max()) + 1 + np.arange(n_groups)
        mask = _remap(v.mask, nodes, new_ids[group])
        mask = _unfuse_lone_pieces(mask, v.mask, new_ids, connectivity)
        masks.append(mask)
        if table is not None:
            fused = mask > int(v.mask.max())
            pairs, pixels = np.unique(np.stack([mask[fused], v.mask[fused]]).astype(np.int64), axis=1,
                                      return_counts=True)
            votes: dict[int, dict[int, int]] = {}  # fused id -> object -> pixels of it the object owns
            for new, old, n in zip(*pairs.tolist(), pixels.tolist()):
                if old in table:
                    per_object = votes.setdefault(new, {})
                    per_object[table[old]] = per_object.get(table[old], 0) + n
            for new, per_object in votes.items():
                table[new] = min(per_object, key=lambda o: (-per_object[o], o))
        tables.append(table)
    return _with_masks(bundle, masks, tables)


def _unfuse_lone_pieces(mask: np.ndarray, original: np.ndarray, fused_ids: np.ndarray, connectivity: int
                        ) -> np.ndarray:
    """``mask`` with every connected piece of a fused id that covers one original id only given
    that id back (a blob of one mask that touches none of the others it was fused with)."""
    structure = np.ones((3, 3), bool) if connectivity == 8 else None
    out = mask.copy()
    for new in fused_ids.tolist():
        pieces, n = ndimage.label(mask == new, structure=structure)
        if n < 2:
            continue
        inside = pieces > 0
        ids = np.unique(np.stack([pieces[inside], original[inside]]).astype(np.int64), axis=1)
        kinds = np.bincount(ids[0], minlength=n + 1)  # distinct original ids per piece
        lone = np.flatnonzero(kinds == 1)
        restore = np.isin(pieces, lone)
        out[restore] = original[restore]
    return out


def _largest_object(bundle: SceneBundle, views: list[View]) -> int:
    """The largest ground-truth object id of the bundle (0 when it has none)."""
    tables = [_truth_table(bundle, v) or {} for v in views]
    return max((max(t.values()) for t in tables if t), default=0)


def spurious_blobs(bundle: SceneBundle, rng: np.random.Generator, count: int, *,
                   radius_px: tuple[float, float] = (2.0, 6.0), on_rocks: float = 0.5) -> SceneBundle:
    """``count`` small false detections per view: elliptic blobs of fresh mask ids.

    Each blob is an ellipse with semi-axes drawn in ``radius_px`` at a random angle,
    centred on a random pixel: with probability ``on_rocks`` a pixel of a mask (a
    segmenter cutting a fragment off a rock), otherwise a background pixel with valid
    depth (a shadow or pebble taken for a rock; any background pixel when none has
    depth).  A blob takes only the pixels of the ellipse that carried the centre's label
    in the input and that no earlier blob took, so blobs never overlap and never cross
    a mask boundary.  A blob that would take no pixel is left out.

    Ground truth (when the bundle has some; the bundle becomes ``mapped``): a blob on a
    mask maps to that mask's object (every pixel of it belongs to that rock).  A blob on
    the background maps to a fresh object id of its own, from ``SPURIOUS_OBJECT_BASE``
    (or above the bundle's largest object id) up, unique in the bundle.  It is not
    marked unknown (-1) on purpose: the metrics leave unknown segments out, so merging a
    false detection into a rock would cost nothing, and training treats all unknown
    voxels of a scene as one object, which would pull unrelated blobs together.  As an
    object of its own, the blob must stay alone to score well.
    """
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    lo, hi = radius_px
    if not 0.0 < lo <= hi:
        raise ValueError(f"radius_px must be (lo, hi) with 0 < lo <= hi, got {radius_px}")
    if not 0.0 <= on_rocks <= 1.0:
        raise ValueError(f"on_rocks must lie in [0, 1], got {on_rocks}")
    views = _image_views(bundle)
    next_object = max(SPURIOUS_OBJECT_BASE, _largest_object(bundle, views) + 1)
    masks, tables = [], []
    for v in views:
        table = _truth_table(bundle, v)
        clean = v.mask
        h, w = clean.shape
        on_rock = rng.random(count) < on_rocks
        axes = rng.uniform(lo, hi, size=(count, 2))
        angles = rng.uniform(0.0, np.pi, size=count)
        picks = rng.random(count)  # where among the candidate pixels each centre falls
        rock_px = np.flatnonzero(clean.ravel() > 0)
        ground_px = np.flatnonzero((clean.ravel() == 0) & (v.depth.ravel() > 0))
        if ground_px.size == 0:
            ground_px = np.flatnonzero(clean.ravel() == 0)
        mask = clean.astype(np.int64)
        next_id = int(clean.max(initial=0)) + 1
        for k in range(count):  # a few blobs per view, each vectorised over its window
            candidates = rock_px if on_rock[k] and rock_px.size else ground_px
            if candidates.size == 0:
                continue
            cy, cx = divmod(int(candidates[int(picks[k] * candidates.size)]), w)
            label = int(clean[cy, cx])
            reach = int(np.ceil(axes[k].max()))
            y0, y1, x0, x1 = max(0, cy - reach), min(h, cy + reach + 1), max(0, cx - reach), min(w, cx + reach + 1)
            yy, xx = np.mgrid[y0:y1, x0:x1]
            c, s = np.cos(angles[k]), np.sin(angles[k])
            along, across = (xx - cx) * c + (yy - cy) * s, -(xx - cx) * s + (yy - cy) * c
            inside = (along / axes[k, 0]) ** 2 + (across / axes[k, 1]) ** 2 <= 1.0
            window = mask[y0:y1, x0:x1]
            take = inside & (clean[y0:y1, x0:x1] == label) & (window == label)
            if not take.any():
                continue
            window[take] = next_id
            if table is not None:
                if label == 0:
                    table[next_id] = next_object
                    next_object += 1
                elif label in table:
                    table[next_id] = table[label]
            next_id += 1
        masks.append(_mask_dtype(mask, clean.dtype))
        tables.append(table)
    return _with_masks(bundle, masks, tables)
