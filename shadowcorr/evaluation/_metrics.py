"""Evaluation metrics (SPEC §5): segment-level purities, voxel ARI, multi-scene summary.

These functions read ground truth and exist only to *score* a prediction.  They
must never feed features, filtering or clustering: nothing in the pipeline that
produces a prediction may import them.

Conventions
-----------
* Segment metrics are unweighted: every segment counts once, whatever its size.
* A predicted label < 0 means "unlabelled".  For the purities each unlabelled
  segment counts as its own singleton predicted object (it is neither merged with
  the other unlabelled segments nor dropped).  A singleton is trivially pure, so it
  does not lower cluster purity, but it lowers rock purity whenever its rock has
  other segments; ``coverage`` reports how many segments were labelled at all.
* A true label < 0 means "no ground truth" for that segment (or voxel): it is left
  out of every metric except ``coverage`` and ``num_segments``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numpy as np
from sklearn.metrics import adjusted_rand_score

__all__ = ["segment_metrics", "voxel_ari", "summarize"]


def _int_labels(a: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(a)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name} must hold integers")
    return arr.astype(np.int64)


def _singletons_for_unlabelled(pred: np.ndarray) -> np.ndarray:
    """Give each negative prediction a fresh label of its own (above all real ones)."""
    out = pred.copy()
    neg = np.flatnonzero(out < 0)
    base = int(out.max()) + 1 if out.size and out.max() >= 0 else 0
    out[neg] = base + np.arange(neg.size)
    return out


def segment_metrics(true_object: np.ndarray, pred_object: np.ndarray) -> dict[str, float | int]:
    """Segment-level correspondence metrics of SPEC §5.

    Algorithm
    ---------
    The contingency table ``n[r, o]`` (segments of true rock ``r`` in predicted
    object ``o``) is built sparsely from the unique (rock, object) pairs.  Then

    * rock purity    = mean over rocks   of ``max_o n[r, o] / n[r, :]``;
    * cluster purity = mean over objects of ``max_r n[r, o] / n[:, o]``;
    * average purity = (rock purity + cluster purity) / 2;
    * a rock is *perfect one-to-one* when all its segments are labelled, lie in a
      single object, and that object holds no segment of another rock
      (``n[r, o] == n[r, :] == n[:, o]``).  An unlabelled segment never makes its
      rock perfect, even though its singleton object would be pure;
    * coverage = segments with a label >= 0 / all segments.

    Unlabelled segments (pred < 0) are singleton objects for the purities;
    segments without ground truth (true < 0) are ignored except in ``coverage``
    and ``num_segments``.

    Parameters
    ----------
    true_object : ndarray of shape (S,)
        Ground-truth rock id per segment.
    pred_object : ndarray of shape (S,)
        Predicted object id per segment, -1 (any negative) for unlabelled.

    Returns
    -------
    dict
        ``rock_purity``, ``cluster_purity``, ``average_purity``, ``coverage``,
        ``perfect_one_to_one_share`` (percent, 0-100; NaN when undefined) and
        ``perfect_one_to_one``, ``num_rocks``, ``num_objects`` (distinct labelled
        objects among scored segments), ``num_segments`` (all input segments),
        ``num_unlabelled`` (scored segments with pred < 0) as ints.
    """
    true = _int_labels(true_object, "true_object")
    pred = _int_labels(pred_object, "pred_object")
    if true.shape != pred.shape:
        raise ValueError(f"true_object and pred_object differ in length: {true.size} vs {pred.size}")

    num_segments = int(true.size)
    coverage = 100.0 * float(np.count_nonzero(pred >= 0)) / num_segments if num_segments else math.nan

    scored = true >= 0
    true, pred = true[scored], pred[scored]
    labelled = pred >= 0
    num_objects = int(np.unique(pred[labelled]).size)
    num_unlabelled = int(np.count_nonzero(~labelled))
    if true.size == 0:
        nan = math.nan
        return {
            "rock_purity": nan, "cluster_purity": nan, "average_purity": nan, "coverage": coverage,
            "perfect_one_to_one": 0, "perfect_one_to_one_share": nan, "num_rocks": 0,
            "num_objects": num_objects, "num_segments": num_segments, "num_unlabelled": num_unlabelled,
        }  # fmt: skip

    pred_s = _singletons_for_unlabelled(pred)
    rocks, r_idx = np.unique(true, return_inverse=True)
    objs, o_idx = np.unique(pred_s, return_inverse=True)
    r_idx, o_idx = r_idx.reshape(-1), o_idx.reshape(-1)
    n_r, n_o = rocks.size, objs.size

    # sparse contingency table: one entry per occurring (rock, object) pair
    pair_keys, pair_count = np.unique(r_idx * n_o + o_idx, return_counts=True)
    pair_r, pair_o = pair_keys // n_o, pair_keys % n_o
    rock_size = np.bincount(r_idx, minlength=n_r)
    obj_size = np.bincount(o_idx, minlength=n_o)

    best_in_rock = np.zeros(n_r, dtype=np.int64)
    np.maximum.at(best_in_rock, pair_r, pair_count)
    best_in_obj = np.zeros(n_o, dtype=np.int64)
    np.maximum.at(best_in_obj, pair_o, pair_count)
    rock_purity = 100.0 * float(np.mean(best_in_rock / rock_size))
    cluster_purity = 100.0 * float(np.mean(best_in_obj / obj_size))

    # perfect: the pair covers the whole rock and the whole object, and the object
    # is a real (labelled) one - not the singleton of an unlabelled segment.
    real_obj = np.isin(objs, pred[labelled])
    perfect_pair = (pair_count == rock_size[pair_r]) & (pair_count == obj_size[pair_o]) & real_obj[pair_o]
    perfect = int(np.count_nonzero(perfect_pair))  # at most one such pair per rock

    return {
        "rock_purity": rock_purity,
        "cluster_purity": cluster_purity,
        "average_purity": 0.5 * (rock_purity + cluster_purity),
        "coverage": coverage,
        "perfect_one_to_one": perfect,
        "perfect_one_to_one_share": 100.0 * perfect / n_r,
        "num_rocks": int(n_r),
        "num_objects": num_objects,
        "num_segments": num_segments,
        "num_unlabelled": num_unlabelled,
    }


def voxel_ari(true: np.ndarray, pred: np.ndarray) -> float:
    """Adjusted Rand index between predicted voxel clusters and voxel ground truth.

    Voxels whose true label is negative (no ground truth) are left out.  A negative
    predicted label (unclustered voxel) is a singleton cluster of its own, as for
    segments in :func:`segment_metrics`.  Uses
    :func:`sklearn.metrics.adjusted_rand_score` (1 = identical partitions, about 0
    for chance, may be negative).  Returns NaN when no voxel is scored.

    Parameters
    ----------
    true, pred : ndarray of shape (V,)
        Integer labels per voxel.

    Returns
    -------
    float
    """
    t = _int_labels(true, "true")
    p = _int_labels(pred, "pred")
    if t.shape != p.shape:
        raise ValueError(f"true and pred differ in length: {t.size} vs {p.size}")
    keep = t >= 0
    if not keep.any():
        return math.nan
    return float(adjusted_rand_score(t[keep], _singletons_for_unlabelled(p[keep])))


def summarize(metrics: Iterable[Mapping[str, object]]) -> dict[str, dict[str, float | int]]:
    """Aggregate per-scene metric dicts into ``{name: {"mean", "std", "n"}}``.

    Every key holding a real number (bool excluded) in any of the dicts is
    summarised over the dicts where it is present and finite; NaN values (an
    undefined metric for a scene) are skipped and not counted in ``n``.  ``std`` is
    the population standard deviation (``ddof=0``; 0 for a single value).  A key
    whose values are all NaN gets mean and std NaN and ``n = 0``.  Non-numeric
    entries are ignored.
    """
    values: dict[str, list[float]] = {}
    for scene in metrics:
        for key, val in scene.items():
            if isinstance(val, bool) or not isinstance(val, (int, float, np.integer, np.floating)):
                continue
            values.setdefault(key, []).append(float(val))
    out: dict[str, dict[str, float | int]] = {}
    for key, vals in values.items():
        arr = np.asarray(vals, dtype=np.float64)
        arr = arr[np.isfinite(arr)]
        if arr.size == 0:
            out[key] = {"mean": math.nan, "std": math.nan, "n": 0}
        else:
            out[key] = {"mean": float(arr.mean()), "std": float(arr.std()), "n": int(arr.size)}
    return out
