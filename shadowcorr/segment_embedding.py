"""Stage 3a: segment-id embeddings learned per scene from voxel co-occurrence (SPEC §2 step 8).

Two segments of one object share many shadow voxels; two of different objects share
few.  Each scene learns one small vector per segment so that segments which
co-occur in voxels point the same way: with co-occurrence counts O (O_aa = 0),
weights w = O normalised per row (or raw counts), and s_ab = cos(z_a, z_b) / tau,

    L = - mean over segments a with a partner of
          log( sum_b w_ab exp(s_ab) / sum_{b != a} exp(s_ab) )

minimised by full-batch Adam.  The result only says "which segments overlap with
which" - it carries no label.  To make the outcome independent of the order in
which segments are listed, the random initial vectors are handed out in a canonical
order of the segments (sorted by their centroid), not in listing order.
"""

from __future__ import annotations

import numpy as np
import torch

from .config import ShadowCorrConfig


def cooccurrence(voxel: np.ndarray, segment: np.ndarray, num_voxels: int, num_segments: int) -> np.ndarray:
    """O_ab = number of voxels holding both segment a and b, with a zero diagonal."""
    from scipy.sparse import csr_matrix

    m = csr_matrix((np.ones(voxel.size), (voxel, segment)), shape=(num_voxels, num_segments))
    o = (m.T @ m).toarray()
    np.fill_diagonal(o, 0.0)
    return o


def canonical_order(centroids: np.ndarray) -> np.ndarray:
    """A listing-order-independent order of segments: lexicographic by rounded centroid."""
    c = np.round(centroids, 3)
    return np.lexsort((c[:, 2], c[:, 1], c[:, 0]))


def train_segment_embeddings(
    cooc: np.ndarray, centroids: np.ndarray, config: ShadowCorrConfig
) -> np.ndarray:
    """Learn one ``segment_embedding_dim`` vector per segment from the co-occurrence matrix.

    The loss's gradient is written out (it is a pair of softmaxes over cosine
    similarities), and Adam is applied by hand: for a few dozen segments this is several
    times faster than autograd and avoids loading torch's optimiser machinery per request.
    """
    s = cooc.shape[0]
    dim = config.segment_embedding_dim
    gen = torch.Generator().manual_seed(config.seed)
    init = torch.randn(s, dim, generator=gen, dtype=torch.float64).numpy() * config.segment_embedding_init_std
    z = np.empty_like(init)
    z[canonical_order(centroids)] = init
    rows = np.flatnonzero(cooc.sum(axis=1) > 0)
    if s < 2 or rows.size == 0:
        return z.astype(np.float32)

    weights = cooc[rows].astype(np.float64)
    if config.segment_embedding_weights == "row_normalised":
        weights = weights / weights.sum(axis=1, keepdims=True)
    with np.errstate(divide="ignore"):
        log_w = np.log(weights)  # -inf where segments never co-occur
    self_mask = np.zeros((rows.size, s), dtype=bool)
    self_mask[np.arange(rows.size), rows] = True
    tau = config.segment_embedding_tau

    def softmax(logits: np.ndarray) -> np.ndarray:
        e = np.exp(logits - logits.max(axis=1, keepdims=True))
        return e / e.sum(axis=1, keepdims=True)

    beta1, beta2, eps, lr = 0.9, 0.999, 1e-8, config.segment_embedding_lr
    m = np.zeros_like(z)
    v = np.zeros_like(z)
    for step in range(1, config.segment_embedding_steps + 1):
        norm = np.maximum(np.linalg.norm(z, axis=1, keepdims=True), 1e-12)
        unit = z / norm
        sim = unit[rows] @ unit.T / tau
        # dL/dsim_ab = (q_ab - p_ab) / |rows|: q over b != a, p weighted by w_ab.
        p = softmax(sim + log_w)
        q = softmax(np.where(self_mask, -np.inf, sim))
        g_sim = (q - p) / rows.size
        g_unit = np.zeros_like(unit)
        g_unit[rows] += g_sim @ unit / tau
        g_unit += g_sim.T @ unit[rows] / tau
        grad = (g_unit - unit * np.sum(unit * g_unit, axis=1, keepdims=True)) / norm
        m = beta1 * m + (1 - beta1) * grad
        v = beta2 * v + (1 - beta2) * grad * grad
        z = z - lr * (m / (1 - beta1**step)) / (np.sqrt(v / (1 - beta2**step)) + eps)
    return z.astype(np.float32)


def segment_embedding_loss(z: np.ndarray, cooc: np.ndarray, config: ShadowCorrConfig) -> float:
    """The training loss of :func:`train_segment_embeddings` (for tests and diagnostics)."""
    zt = torch.nn.functional.normalize(torch.from_numpy(np.asarray(z, dtype=np.float64)), dim=1)
    rows = torch.from_numpy(np.flatnonzero(cooc.sum(axis=1) > 0))
    w = torch.from_numpy(cooc.astype(np.float64))[rows]
    if config.segment_embedding_weights == "row_normalised":
        w = w / w.sum(dim=1, keepdim=True)
    sim = zt[rows] @ zt.T / config.segment_embedding_tau
    num = torch.logsumexp(sim + torch.where(w > 0, w.log(), torch.full_like(w, -torch.inf)), dim=1)
    off = torch.ones_like(sim, dtype=torch.bool)
    off[torch.arange(rows.numel()), rows] = False
    den = torch.logsumexp(sim.masked_fill(~off, -torch.inf), dim=1)
    return float(-(num - den).mean())


def voxel_embeddings(
    voxel: np.ndarray, segment: np.ndarray, num_voxels: int, segment_vectors: np.ndarray
) -> np.ndarray:
    """L2-normalised mean of the vectors of the segments contributing to each voxel."""
    from scipy.sparse import csr_matrix

    membership = csr_matrix((np.ones(voxel.size), (voxel, segment)), shape=(num_voxels, segment_vectors.shape[0]))
    total = membership @ segment_vectors.astype(np.float64)
    count = np.bincount(voxel, minlength=num_voxels)[:, None]
    mean = total / np.maximum(count, 1)
    norm = np.linalg.norm(mean, axis=1, keepdims=True)
    return (mean / np.maximum(norm, 1e-12)).astype(np.float32)
