"""Stage 9 (methods ``shadowcorr``, ``meanshift``): clustering of voxel embeddings into objects (SPEC §2 steps 11-12).

Three pieces, all vectorised:

* :func:`mean_shift` - flat-kernel MeanShift with every point a seed, written in
  torch so that all seeds move at once.  It reproduces the result of
  ``sklearn.cluster.MeanShift(bandwidth=bw)`` (same modes, same ordering of the
  modes, same labels up to floating-point ties) at a fraction of its run time.
* :func:`merge_small_clusters` - folds clusters with too few points into the
  nearest large cluster.
* :func:`cluster_voxels` - the two above, as the pipeline runs them.
* :func:`majority_vote` - turns per-point (per-voxel) labels into one label per
  group (per segment), with the share of votes it got.

Nothing here reads ground truth.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["cluster_voxels", "mean_shift", "merge_small_clusters", "majority_vote"]

# Upper bound on the number of entries of one (seeds x points) block.  Distance
# matrices are built block by block so that memory stays bounded (about 32 MiB in
# float64 plus the boolean mask) whatever the number of points.
_BLOCK_ELEMENTS = 1 << 22


# Spots (seed positions) compared with one slice of the points in mean shift: small enough that
# a block's slice is narrow, large enough for efficient matrix products.
_SPOTS_PER_BLOCK = 256

# Modes handled per step of the greedy suppression (see ``_greedy_suppress``).
_NMS_BLOCK = 256


def _rows_per_block(n_cols: int) -> int:
    """Number of rows of an ``(rows, n_cols)`` block holding at most ``_BLOCK_ELEMENTS``."""
    return max(1, _BLOCK_ELEMENTS // max(1, n_cols))


def _as_points(x: np.ndarray) -> np.ndarray:
    """Validate a 2-D finite float array; keep float32/float64, promote anything else."""
    arr = np.asarray(x)
    if arr.ndim != 2:
        raise ValueError(f"expected a 2-D array (N, D), got shape {arr.shape}")
    if arr.dtype not in (np.float32, np.float64):
        # float16 and integers are promoted: float32 keeps the scikit-learn
        # behaviour for half inputs close enough, float64 is exact for integers.
        arr = arr.astype(np.float32 if arr.dtype == np.float16 else np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError("points contain NaN or infinite values")
    return arr


def _sq_dist(a: torch.Tensor, a_sq: torch.Tensor, b: torch.Tensor, b_sq: torch.Tensor) -> torch.Tensor:
    """Squared Euclidean distances ``|a_i - b_j|^2`` through one matrix product.

    The expansion ``|a|^2 + |b|^2 - 2 a.b`` loses precision only relative to the
    squared norms; in float64 that is far below any distance that matters here.
    """
    return torch.addmm(a_sq[:, None] + b_sq[None, :], a, b.T, beta=1.0, alpha=-2.0)


def _shift_all_seeds(
    pts: torch.Tensor,
    bandwidth: float,
    max_iter: int,
    stop_thresh: float,
    round_dtype: torch.dtype | None,
    compute_dtype: torch.dtype = torch.float64,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Run the flat-kernel mean shift from every point until each seed converges.

    ``pts`` is float64.  Seed positions are kept in float64 (rounded to
    ``round_dtype`` after each update when given); the two large products per
    iteration run in ``compute_dtype`` on points centred on their mean, which keeps
    the squared-norm expansion well conditioned.

    Each iteration is two matrix products per block of moving seeds ``a``:

    * ``G = [a, 1] @ [-2 p, |p|^2]^T = |p|^2 - 2 a.p``, and ``p`` is within the
      ball of ``a`` when ``G <= r^2 - |a|^2``.  The comparison is done in place, so
      ``G`` becomes the 0/1 membership matrix without another allocation;
    * ``W @ [p, 1]`` gives, at once, the sum of the points in each ball and
      their number.

    Returns the final position of every seed and the number of points that were
    within ``bandwidth`` of the position it held before its last update (this is
    the "intensity" scikit-learn ranks modes by; 0 means its ball was empty).
    """
    n, dim = pts.shape
    dev = pts.device
    offset = pts.mean(0)
    centred = pts - offset
    # Points in the order of their projection on the principal axis: a ball of radius r
    # around a spot holds only points whose projection lies within r of the spot's, so a
    # block of spots (taken in the same order) is compared with one contiguous slice of the
    # points, not with all of them.  Slices are widened by a hair, so rounding in the
    # projections never leaves a point of the ball out (extra points only get the exact test).
    axis = torch.linalg.eigh(centred.T @ centred).eigenvectors[:, -1]
    by_axis = torch.argsort(centred @ axis)
    centred = centred[by_axis]
    projection = centred @ axis
    reach = bandwidth * (1 + 1e-9) + 1e-9 * float(projection.abs().max())
    ones = torch.ones(n, 1, dtype=torch.float64, device=dev)
    # (D+1, N) right-hand side of the distance product, and (N, D+1) points with a
    # column of ones for the sum/count product.
    dist_rhs = torch.cat([-2.0 * centred, (centred * centred).sum(1, keepdim=True)], 1).T.to(compute_dtype).contiguous()
    sum_rhs = torch.cat([centred, ones], 1).to(compute_dtype)
    means = pts.clone()
    counts = torch.zeros(n, dtype=torch.int64, device=dev)
    radius_sq = bandwidth * bandwidth
    active = torch.arange(n, device=dev)
    for iteration in range(max_iter + 1):
        if active.numel() == 0:
            break
        # Moving seeds that stand on the same spot move alike from here on (same ball, same
        # mean, same remaining iterations): each spot is computed once.  After one or two
        # iterations most seeds share a spot (the sample scene's 2,242 embeddings: 538 spots
        # at the second iteration, 91 at the third).
        spots, spot_of_seed = torch.unique(means[active], dim=0, return_inverse=True)
        spot_projection = (spots - offset) @ axis
        spot_order = torch.argsort(spot_projection)
        lo = torch.searchsorted(projection, spot_projection - reach, side="left")
        hi = torch.searchsorted(projection, spot_projection + reach, side="right")
        spot_new = torch.empty_like(spots)
        spot_count = torch.empty(spots.shape[0], dtype=torch.int64, device=dev)
        spot_done = torch.empty(spots.shape[0], dtype=torch.bool, device=dev)
        for block in torch.split(spot_order, _SPOTS_PER_BLOCK):
            first, last = int(lo[block].min()), int(hi[block].max())
            rows = _rows_per_block(last - first)
            for sub in torch.split(block, rows):
                old = spots[sub]
                a = old - offset
                a_aug = torch.cat([a, ones[: a.shape[0]]], 1).to(compute_dtype)
                threshold = (radius_sq - (a * a).sum(1, keepdim=True)).to(compute_dtype)
                within = (a_aug @ dist_rhs[:, first:last]).le_(threshold)  # float 0/1 membership, in place
                sums = (within @ sum_rhs[first:last]).to(torch.float64)
                cnt = sums[:, dim].round().to(torch.int64)
                new = sums[:, :dim] / cnt.clamp_min(1).to(torch.float64)[:, None] + offset
                if round_dtype is not None:
                    # scikit-learn keeps every mean in the input dtype (float32 for
                    # embeddings); rounding the same way keeps ball memberships, and so
                    # the labels, as close as possible to its result.
                    new = new.to(round_dtype).to(torch.float64)
                empty = cnt == 0
                # A seed whose ball is empty stops where it is (scikit-learn's break
                # before the update) and is later discarded for its zero intensity.
                new = torch.where(empty[:, None], old, new)
                shift = torch.linalg.vector_norm(new - old, dim=1)
                done = empty | (shift <= stop_thresh)
                if iteration == max_iter:
                    done = torch.ones_like(done)
                spot_new[sub], spot_count[sub], spot_done[sub] = new, cnt, done
        means[active] = spot_new[spot_of_seed]
        counts[active] = spot_count[spot_of_seed]
        # Converged seeds are frozen: later iterations only touch moving seeds.
        active = active[~spot_done[spot_of_seed]]
    return means, counts


def _greedy_within_block(adjacent: np.ndarray) -> np.ndarray:
    """Greedy suppression inside one block, given its (B, B) "within bandwidth" matrix.

    The sequential rule "keep mode i unless an earlier kept mode is adjacent" is
    solved in rounds of whole-block boolean operations instead of a loop over
    modes: an undecided mode with an adjacent earlier *kept* mode is dropped; an
    undecided mode whose adjacent earlier modes are all *dropped* is kept.  The
    first undecided mode has only decided earlier neighbours, so every round
    settles at least one mode, and the result equals the sequential greedy one.
    In practice two or three rounds suffice (modes of one cluster are all
    adjacent to its most popular mode).
    """
    b = adjacent.shape[0]
    earlier = np.tril(adjacent, k=-1)  # earlier[i, j]: j < i and within bandwidth
    kept = np.zeros(b, dtype=bool)
    dropped = np.zeros(b, dtype=bool)
    undecided = np.ones(b, dtype=bool)
    while undecided.any():
        dropped |= undecided & (earlier & kept[None, :]).any(1)
        undecided &= ~dropped
        newly_kept = undecided & ~(earlier & ~dropped[None, :]).any(1)
        kept |= newly_kept
        undecided &= ~newly_kept
    return kept


def _greedy_suppress(centers: torch.Tensor, bandwidth: float) -> np.ndarray:
    """Greedy non-maximum suppression of modes already sorted by popularity.

    Walks the modes in order and keeps a mode unless a kept, earlier (more
    popular) mode lies within ``bandwidth`` of it (scikit-learn's rule).  The modes
    are handled in blocks of ``_NMS_BLOCK``: distances inside a block decide the
    block's survivors (:func:`_greedy_within_block`), then every later mode within
    ``bandwidth`` of a survivor is suppressed with blocked matrix products, so the
    later blocks only see the modes still alive.  Returns the boolean "kept" mask.
    """
    u = centers.shape[0]
    radius_sq = bandwidth * bandwidth
    c_sq = (centers * centers).sum(1)
    suppressed = np.zeros(u, dtype=bool)
    kept = np.zeros(u, dtype=bool)
    block = _NMS_BLOCK
    for start in range(0, u, block):
        idx = np.arange(start, min(start + block, u))
        idx = idx[~suppressed[idx]]
        if idx.size == 0:
            continue
        t_idx = torch.as_tensor(idx, device=centers.device)
        local = (_sq_dist(centers[t_idx], c_sq[t_idx], centers[t_idx], c_sq[t_idx]) <= radius_sq).cpu().numpy()
        alive = _greedy_within_block(local)
        survivors = t_idx[torch.as_tensor(alive, device=centers.device)]
        kept[survivors.cpu().numpy()] = True
        rest = np.flatnonzero(~suppressed[start + block :]) + start + block
        if rest.size == 0:
            continue
        t_rest = torch.as_tensor(rest, device=centers.device)
        hit = torch.zeros(rest.size, dtype=torch.bool, device=centers.device)
        kept_c, kept_sq = centers[survivors], c_sq[survivors]
        step = _rows_per_block(survivors.numel())
        for off in range(0, rest.size, step):
            sub = t_rest[off : off + step]
            hit[off : off + step] = (_sq_dist(centers[sub], c_sq[sub], kept_c, kept_sq) <= radius_sq).any(1)
        suppressed[rest[hit.cpu().numpy()]] = True
    return kept


def _nearest(pts: torch.Tensor, centers: torch.Tensor) -> torch.Tensor:
    """Index of the nearest centre for every point (blocked; first index on ties)."""
    c_sq = (centers * centers).sum(1)
    out = []
    for block in torch.split(pts, _rows_per_block(centers.shape[0])):
        out.append(_sq_dist(block, (block * block).sum(1), centers, c_sq).argmin(1))
    return torch.cat(out)


def mean_shift(
    x: np.ndarray,
    bandwidth: float,
    *,
    max_iter: int = 300,
    tol: float = 1e-3,
    device: str | torch.device = "cpu",
) -> tuple[np.ndarray, np.ndarray]:
    """Flat-kernel MeanShift with every point as a seed (scikit-learn semantics).

    Algorithm
    ---------
    1. Every point starts a seed.  At each iteration a seed moves to the mean of
       all points within ``bandwidth`` of it (flat kernel, distance <= bandwidth).
       All moving seeds are updated together: their squared distances to the points
       come from one matrix product per block of seeds, and the new means from a
       second product of the boolean membership matrix with the points.  Seeds standing
       on the same spot are computed once (their paths coincide from there on), and a
       block of spots is compared only with the points whose projection on the data's
       principal axis lies within ``bandwidth`` of the spots' projections (the others
       cannot be in their balls).  Blocks keep memory bounded (a few tens of MiB) for
       tens of thousands of points.
    2. A seed stops when it moved by at most ``tol * bandwidth`` or after
       ``max_iter`` updates; stopped seeds are frozen and no longer computed.
    3. Each seed's *intensity* is the number of points within ``bandwidth`` of the
       position it held before its last update (as scikit-learn counts it).  Seeds
       with intensity 0 are discarded; seeds that ended on exactly the same mode are
       merged (the last one's intensity counts, as in scikit-learn's dict).
    4. Modes are sorted by intensity, descending; ties are broken by comparing the
       mode coordinates lexicographically, descending - exactly scikit-learn's
       ``sorted(..., key=(intensity, tuple(center)), reverse=True)``.
    5. Greedy suppression: walking that order, a mode is dropped when a kept, more
       popular mode lies within ``bandwidth`` (distance <= bandwidth).
    6. Every point is labelled with its nearest kept mode (``cluster_all=True``).

    Distances are computed in float64 like scikit-learn's tree search, and when the
    input is float32 each new mean is rounded to float32 like scikit-learn's
    ``np.mean`` on float32 data, so ball memberships (and labels) match
    ``sklearn.cluster.MeanShift(bandwidth=bandwidth)`` except for floating-point
    ties at the bandwidth boundary.

    Parameters
    ----------
    x : ndarray of shape (N, D)
        Points (e.g. voxel embeddings).  float32 or float64; other dtypes are promoted.
    bandwidth : float
        Radius of the flat kernel, > 0.  No estimation is done.
    max_iter : int, default=300
        Maximum number of updates per seed (scikit-learn's meaning).
    tol : float, default=1e-3
        Convergence threshold relative to ``bandwidth``: a seed stops when its shift
        is <= ``tol * bandwidth``.
    device : str or torch.device, default="cpu"
        Torch device for the computation.  Uses torch's current thread setting.

    Returns
    -------
    labels : ndarray of shape (N,), int64
        Index of the cluster of every point, into ``centers``; 0 is the most popular mode.
    centers : ndarray of shape (C, D), dtype of ``x``
        Kept modes, most popular first.

    Raises
    ------
    ValueError
        On a bad shape, non-finite values, ``bandwidth <= 0`` or ``max_iter < 0``.
    """
    arr = _as_points(x)
    if not (np.isfinite(bandwidth) and bandwidth > 0):
        raise ValueError(f"bandwidth must be a positive finite number, got {bandwidth!r}")
    if max_iter < 0:
        raise ValueError(f"max_iter must be >= 0, got {max_iter}")
    n, dim = arr.shape
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, dim), dtype=arr.dtype)

    dev = torch.device(device)
    pts = torch.as_tensor(arr, device=dev).to(torch.float64)
    round_dtype = torch.float32 if arr.dtype == np.float32 else None
    modes, counts = _shift_all_seeds(pts, float(bandwidth), int(max_iter), float(tol) * bandwidth, round_dtype)

    # --- modes -> unique modes with intensities (scikit-learn's dict keyed by mode)
    modes_np = modes.cpu().numpy().astype(arr.dtype) + 0.0  # +0.0 turns -0.0 into 0.0, as tuple keys compare
    counts_np = counts.cpu().numpy()
    keep = counts_np > 0
    if not keep.any():
        raise ValueError("no point was within bandwidth of any seed; bandwidth is too small")
    seed_ids = np.flatnonzero(keep)
    uniq, inverse = np.unique(modes_np[keep], axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    last_seed = np.full(uniq.shape[0], -1, dtype=np.int64)
    np.maximum.at(last_seed, inverse, seed_ids)  # later seeds overwrite earlier ones in a dict
    intensity = counts_np[last_seed]

    # --- popularity order: intensity desc, then coordinates lexicographically desc.
    # np.lexsort sorts ascending by its last key first; reversing gives descending
    # order on all keys (every row is unique, so there are no equal keys to keep stable).
    order = np.lexsort(tuple(uniq[:, j] for j in range(dim - 1, -1, -1)) + (intensity,))[::-1]
    sorted_modes = torch.as_tensor(uniq[order], device=dev).to(torch.float64)

    kept = _greedy_suppress(sorted_modes, float(bandwidth))
    centers = sorted_modes[torch.as_tensor(kept, device=dev)]
    labels = _nearest(pts, centers).cpu().numpy().astype(np.int64)
    return labels, centers.cpu().numpy().astype(arr.dtype)


def merge_small_clusters(x: np.ndarray, labels: np.ndarray, min_size: int = 5) -> np.ndarray:
    """Merge clusters with fewer than ``min_size`` points into the nearest large cluster.

    Algorithm
    ---------
    Centroids (mean embedding) of all clusters are computed once.  Every *small*
    cluster (size < ``min_size``) is reassigned, as a whole, to the *large* cluster
    (size >= ``min_size``) whose centroid is nearest to its own centroid (Euclidean,
    first such cluster on ties).  This is one pass: centroids are not updated after
    merging, so the result does not depend on the order clusters are visited.  If
    no cluster is large enough, labels are left as they are.

    Finally the labels are renumbered ``0 .. C-1`` by cluster size, largest first
    (ties: smaller original label first).  This order depends only on the partition
    and the original labels, not on the order the points are listed in.

    Parameters
    ----------
    x : ndarray of shape (N, D)
        Embeddings the clusters live in.
    labels : ndarray of shape (N,)
        Integer cluster labels.  Negative labels mean "no cluster": such points are
        neither merged nor counted, and stay -1 in the output.
    min_size : int, default=5
        Smallest size a cluster may keep on its own.

    Returns
    -------
    ndarray of shape (N,), int64
        New labels, consecutive from 0, largest cluster first.
    """
    arr = _as_points(x)
    lab = np.asarray(labels)
    if lab.shape != (arr.shape[0],):
        raise ValueError(f"labels must have shape ({arr.shape[0]},), got {lab.shape}")
    if lab.size and not np.issubdtype(lab.dtype, np.integer):
        raise ValueError("labels must be integers")
    lab = lab.astype(np.int64)
    out = np.full(lab.shape, -1, dtype=np.int64)
    valid = lab >= 0
    if not valid.any():
        return out

    # compact the valid labels to 0..K-1 (ascending original label)
    orig, compact = np.unique(lab[valid], return_inverse=True)
    k = orig.size
    sizes = np.bincount(compact, minlength=k)
    sums = np.zeros((k, arr.shape[1]), dtype=np.float64)
    np.add.at(sums, compact, arr[valid])
    centroids = sums / sizes[:, None]

    target = np.arange(k)
    large = np.flatnonzero(sizes >= min_size)
    small = np.flatnonzero(sizes < min_size)
    if large.size and small.size:
        d2 = ((centroids[small, None, :] - centroids[None, large, :]) ** 2).sum(-1)
        target[small] = large[d2.argmin(1)]

    merged_sizes = np.bincount(target, weights=sizes, minlength=k)
    # order clusters by size desc, then by original label asc (lexsort: last key primary)
    survivors = np.unique(target)
    rank_order = survivors[np.lexsort((survivors, -merged_sizes[survivors]))]
    new_id = np.full(k, -1, dtype=np.int64)
    new_id[rank_order] = np.arange(rank_order.size)
    out[valid] = new_id[target[compact]]
    return out


def majority_vote(
    point_labels: np.ndarray,
    point_group: np.ndarray,
    num_groups: int,
    weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Label of each group by (weighted) majority of its points' labels.

    Algorithm
    ---------
    Each point votes for its label in its group with its weight (1 by default).
    Votes are summed per (group, label) pair by encoding the pair as one integer
    key and accumulating with ``np.bincount`` over the unique keys, so memory is
    proportional to the number of distinct pairs, not groups x labels.  The pairs
    are then sorted by group, votes descending, label ascending, and the first pair
    of each group wins: ties therefore go to the smallest label.  ``support`` is the
    winner's votes divided by all votes of the group.

    Points with a negative label (unclustered) cast no vote.  Groups without any
    vote (no points, only unlabelled points, or zero total weight) get label -1 and
    support 0.

    Parameters
    ----------
    point_labels : ndarray of shape (N,)
        Integer cluster label per point.
    point_group : ndarray of shape (N,)
        Integer group (segment) per point, in ``0 .. num_groups-1``.
    num_groups : int
        Number of groups G.
    weights : ndarray of shape (N,), optional
        Non-negative vote weight per point.

    Returns
    -------
    group_label : ndarray of shape (G,), int64
    support : ndarray of shape (G,), float64 in [0, 1]
    """
    lab = np.asarray(point_labels)
    grp = np.asarray(point_group)
    if lab.ndim != 1 or grp.shape != lab.shape:
        raise ValueError("point_labels and point_group must be 1-D arrays of the same length")
    if num_groups < 0:
        raise ValueError("num_groups must be >= 0")
    for name, a in (("point_labels", lab), ("point_group", grp)):
        if a.size and not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"{name} must be integers")
    lab = lab.astype(np.int64)
    grp = grp.astype(np.int64)
    if grp.size and (grp.min() < 0 or grp.max() >= num_groups):
        raise ValueError(f"point_group values must lie in [0, {num_groups})")
    if weights is None:
        w = np.ones(lab.shape, dtype=np.float64)
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != lab.shape:
            raise ValueError("weights must have the same shape as point_labels")
        if not np.all(np.isfinite(w)) or (w.size and w.min() < 0):
            raise ValueError("weights must be finite and non-negative")

    group_label = np.full(num_groups, -1, dtype=np.int64)
    support = np.zeros(num_groups, dtype=np.float64)
    voting = lab >= 0
    if not voting.any():
        return group_label, support
    lab, grp, w = lab[voting], grp[voting], w[voting]

    n_labels = int(lab.max()) + 1
    keys, inverse = np.unique(grp * n_labels + lab, return_inverse=True)
    votes = np.bincount(inverse.reshape(-1), weights=w)
    pair_group, pair_label = keys // n_labels, keys % n_labels
    totals = np.bincount(pair_group, weights=votes, minlength=num_groups)

    # first entry per group after sorting by (group asc, votes desc, label asc)
    order = np.lexsort((pair_label, -votes, pair_group))
    first = np.ones(order.size, dtype=bool)
    first[1:] = pair_group[order][1:] != pair_group[order][:-1]
    win = order[first]
    g = pair_group[win]
    has_votes = totals[g] > 0
    g, win = g[has_votes], win[has_votes]
    group_label[g] = pair_label[win]
    support[g] = votes[win] / totals[g]
    return group_label, support


def cluster_voxels(embeddings: np.ndarray, bandwidth: float, min_cluster_size: int) -> np.ndarray:
    """MeanShift + small-cluster merge; returns one cluster label per voxel."""
    if embeddings.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    labels, _ = mean_shift(np.ascontiguousarray(embeddings, dtype=np.float32), bandwidth)
    return merge_small_clusters(embeddings, labels, min_size=min_cluster_size)
