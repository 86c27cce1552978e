"""Stage 6, step 8: segment-id embeddings learned per scene from voxel co-occurrence (SPEC §2 step 8).

Two segments of one object share many shadow voxels; two of different objects share
few.  Each scene learns one small vector per segment so that segments which
co-occur in voxels point the same way: with co-occurrence counts O (O_aa = 0),
weights w = O normalised per row (or raw counts), and s_ab = cos(z_a, z_b) / tau,

    L = - mean over segments a with a partner of
          log( sum_b w_ab exp(s_ab) / sum_{b != a, b in D(a)} exp(s_ab) )

minimised by Adam.  The result only says "which segments overlap with which" - it
carries no label.  To make the outcome independent of the order in which segments are
listed, the random initial vectors are handed out in a canonical order of the segments
(sorted by their centroid), not in listing order.

The denominator's domain ``D(a)`` is set by ``segment_embedding_scope``:

* ``"component"`` (default): the segments of ``a``'s connected component of the
  co-occurrence graph.  Segments of different components never share a voxel, so they
  only ever pushed each other apart; restricted, every component is an independent
  small problem (each with the loss averaged over its own segments) and the cost
  follows the sum of squared component sizes instead of the squared segment count.
  Components are trained together in padded batches, one per power-of-two size bucket;
  components of up to 64 segments share one bucket and are packed side by side into its
  problems (each with its own softmax domain and loss average), so the Python loop runs
  over buckets x steps, and a typical scene has one bucket.
* ``"scene"``: every other segment of the scene (the dense original; quadratic).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.sparse import csr_matrix, issparse
from scipy.sparse.csgraph import connected_components

from ..config import ShadowCorrConfig

_ADAM_BETA1, _ADAM_BETA2, _ADAM_EPS = 0.9, 0.999, 1e-8


def cooccurrence(voxel: np.ndarray, segment: np.ndarray, num_voxels: int, num_segments: int) -> csr_matrix:
    """Sparse O_ab = number of voxels holding both segment a and b, with an empty diagonal.

    Only pairs that share a voxel are stored, so the cost follows the voxel memberships.
    """
    m = csr_matrix((np.ones(voxel.size), (voxel, segment)), shape=(num_voxels, num_segments))
    o = (m.T @ m).tocsr()
    o.setdiag(0.0)
    o.eliminate_zeros()
    return o


def canonical_order(centroids: np.ndarray) -> np.ndarray:
    """A listing-order-independent order of segments: lexicographic by rounded centroid."""
    c = np.round(centroids, 3)
    return np.lexsort((c[:, 2], c[:, 1], c[:, 0]))


def initial_vectors(centroids: np.ndarray, config: ShadowCorrConfig) -> np.ndarray:
    """(S, dim) float64 random start vectors, handed out in canonical (centroid) order."""
    s = centroids.shape[0]
    gen = torch.Generator().manual_seed(config.seed)
    init = torch.randn(s, config.segment_embedding_dim, generator=gen, dtype=torch.float64).numpy()
    z = np.empty_like(init)
    z[canonical_order(centroids)] = init * config.segment_embedding_init_std
    return z


def _weights(cooc: csr_matrix, config: ShadowCorrConfig) -> csr_matrix:
    """The loss's pair weights w: co-occurrence counts, normalised per row unless 'raw'."""
    w = csr_matrix(cooc, dtype=np.float64)
    if config.segment_embedding_weights == "row_normalised":
        total = np.asarray(w.sum(axis=1)).ravel()
        w = csr_matrix(w.multiply(1.0 / np.maximum(total, 1e-300)[:, None]))
    return w


def train_segment_embeddings(cooc: np.ndarray | csr_matrix, centroids: np.ndarray, config: ShadowCorrConfig
                             ) -> np.ndarray:
    """Learn one ``segment_embedding_dim`` vector per segment from the co-occurrence matrix.

    ``cooc`` may be dense or sparse (see :func:`cooccurrence`).  The loss's gradient is
    written out (it is a pair of softmaxes over cosine similarities) and Adam is applied by
    hand: several times faster than autograd for these small problems.  Segments without a
    partner keep their start vector.
    """
    cooc = csr_matrix(cooc, dtype=np.float64) if not issparse(cooc) else cooc.tocsr()
    z = initial_vectors(centroids, config)
    if config.embedding_steps == 0 or cooc.nnz == 0:
        return z.astype(np.float32)
    w = _weights(cooc, config)
    if config.segment_embedding_scope == "scene":  # one problem: every segment, one domain
        batches = [(np.arange(z.shape[0])[None], np.zeros((1, z.shape[0]), dtype=np.int64))]
    else:
        batches = _packed_components(cooc)
    pairs = w.tocoo()
    slot = np.empty(z.shape[0], dtype=np.int64)  # a segment's problem within its batch
    local = np.empty(z.shape[0], dtype=np.int64)  # and its place in that problem
    for members, component in batches:  # (m, n) segment ids and their components, -1 padding
        valid = members >= 0
        slot[:] = -1
        slot[members[valid]] = np.nonzero(valid)[0]
        local[members[valid]] = np.nonzero(valid)[1]
        zb = np.where(valid[..., None], z[np.where(valid, members, 0)], 0.0)
        wb = np.zeros(members.shape + (members.shape[1],))
        inside = slot[pairs.row] >= 0  # both ends of a pair lie in one problem
        a, b = pairs.row[inside], pairs.col[inside]
        wb[slot[a], local[a], local[b]] = pairs.data[inside]
        zb = _train_batch(zb, wb, component, config)
        z[members[valid]] = zb[valid]
    return z.astype(np.float32)


#: Components up to this size are packed together into problems as wide as the largest of
#: them: each Adam step costs a fixed Python overhead per batch, which dominates small
#: problems (the sample scene: 2 batches x 200 steps took 64 ms, one batch 30 ms).
_PACK_WIDTH = 64


def _packed_components(cooc: csr_matrix) -> list[tuple[np.ndarray, np.ndarray]]:
    """Connected components of the co-occurrence graph with two or more segments, as batches
    of problems: per batch an (m, n) array of segment ids and one of their components'
    numbers within the problem, both -1 where padded.

    Components are taken largest first into power-of-two size classes, every size up to
    ``_PACK_WIDTH`` in one class; a class's problems are as wide as its largest component and
    filled next-fit (a larger class holds one component per problem).
    """
    _, comp = connected_components(cooc, directed=False)
    order = np.argsort(comp, kind="stable")
    starts = np.r_[0, np.flatnonzero(np.diff(comp[order])) + 1]
    sizes = np.diff(np.r_[starts, order.size])
    by_size = np.argsort(-sizes, kind="stable")
    by_size = by_size[sizes[by_size] >= 2]
    size_class = np.ceil(np.log2(np.maximum(sizes[by_size], _PACK_WIDTH))).astype(np.int64)
    out = []
    for c in np.unique(size_class):
        picked = by_size[size_class == c]
        width = int(sizes[picked[0]])
        # Next fit: a problem's first free slot for each component (sequential, one step per
        # component, not per point).
        problem = np.empty(picked.size, dtype=np.int64)
        offset = np.empty(picked.size, dtype=np.int64)
        p, used = 0, 0
        for i, size in enumerate(sizes[picked].tolist()):
            if used + size > width:
                p, used = p + 1, 0
            problem[i], offset[i] = p, used
            used += size
        members = np.full((p + 1, width), -1, dtype=np.int64)
        component = np.full((p + 1, width), -1, dtype=np.int64)
        length = sizes[picked]
        row = np.repeat(problem, length)
        col = np.repeat(offset, length) + np.arange(length.sum()) - np.repeat(np.cumsum(length) - length, length)
        members[row, col] = order[np.repeat(starts[picked], length) + (col - np.repeat(offset, length))]
        component[row, col] = np.repeat(np.arange(picked.size), length)
        out.append((members, component))
    return out


def _train_batch(z: np.ndarray, weights: np.ndarray, component: np.ndarray, config: ShadowCorrConfig) -> np.ndarray:
    """Adam on a batch of problems, each holding one or more independent components.

    ``z``: (m, n, dim) start vectors (zeros where padded); ``weights``: (m, n, n) pair weights,
    row a holding w_ab; ``component``: (m, n) the component of each slot, -1 where padded.  A
    segment's row is in the loss when it has a partner (a positive weight); each component's
    loss is averaged over its own rows, and its softmax denominators run over its own segments.

    With E = exp(s - 1 / tau) (1 / tau is every row's maximum: a vector's similarity with
    itself), p = E w / sum(E w) and q = E / sum(E) over the domain share one exponential; as
    rows and columns index the same vectors, dL/du = (G + G^T) u with G = (q - p) / (rows tau).
    Padded slots get no gradient and stay at zero.
    """
    tau, lr = config.segment_embedding_tau, config.embedding_lr
    row_ok = weights.sum(axis=-1) > 0
    same = (component[:, :, None] == component[:, None, :]) & (component >= 0)[:, :, None]
    domain = (same & ~np.eye(component.shape[1], dtype=bool)[None]).astype(np.float64)
    rows_in_component = np.einsum("mab,mb->ma", same.astype(np.float64), row_ok.astype(np.float64))
    row_scale = (row_ok / np.maximum(rows_in_component, 1) / tau)[..., None]
    # The loop runs on small arrays (the sample scene: 3 problems of 27 segments), where
    # numpy's per-call cost is most of the cost: sums instead of einsum, and every step
    # writes into buffers allocated once (same arithmetic, in the same order, as the
    # plain expressions in the comments).
    z = z.copy()
    m, v = np.zeros_like(z), np.zeros_like(z)  # Adam's moments
    unit, grad, tmp = np.empty_like(z), np.empty_like(z), np.empty_like(z)
    norm, row_sum = np.empty(z.shape[:-1] + (1,)), np.empty(z.shape[:-1] + (1,))
    e, q = np.empty(weights.shape), np.empty(weights.shape)
    unit_t, q_t = unit.transpose(0, 2, 1), q.transpose(0, 2, 1)
    mul, div = np.multiply, np.divide

    def normalise_rows(x: np.ndarray) -> None:  # x /= max(x.sum(-1), 1e-300)
        np.add.reduce(x, axis=-1, keepdims=True, out=row_sum)
        np.maximum(row_sum, 1e-300, out=row_sum)
        div(x, row_sum, out=x)

    for step in range(1, config.embedding_steps + 1):
        mul(z, z, out=tmp)  # norm = max(|z|, 1e-12); unit = z / norm
        np.add.reduce(tmp, axis=-1, keepdims=True, out=norm)
        np.sqrt(norm, out=norm)
        np.maximum(norm, 1e-12, out=norm)
        div(z, norm, out=unit)
        np.matmul(unit, unit_t, out=e)  # e = exp((unit unit^T - 1) / tau)
        np.subtract(e, 1.0, out=e)
        mul(e, 1.0 / tau, out=e)
        np.exp(e, out=e)
        mul(e, domain, out=q)  # q: softmax over the domain; e: weighted by w
        normalise_rows(q)
        mul(e, weights, out=e)
        normalise_rows(e)
        np.subtract(q, e, out=q)  # G = (q - p) * row_scale; grad = (G + G^T) unit
        mul(q, row_scale, out=q)
        np.add(q, q_t, out=e)
        np.matmul(e, unit, out=grad)
        mul(unit, grad, out=tmp)  # grad -= unit (unit . grad); grad /= norm
        np.add.reduce(tmp, axis=-1, keepdims=True, out=row_sum)
        mul(unit, row_sum, out=tmp)
        np.subtract(grad, tmp, out=grad)
        div(grad, norm, out=grad)
        mul(m, _ADAM_BETA1, out=m)  # m = b1 m + (1 - b1) grad
        mul(grad, 1 - _ADAM_BETA1, out=tmp)
        np.add(m, tmp, out=m)
        mul(v, _ADAM_BETA2, out=v)  # v = b2 v + (1 - b2) grad^2
        mul(grad, grad, out=grad)
        mul(grad, 1 - _ADAM_BETA2, out=grad)
        np.add(v, grad, out=v)
        div(v, 1 - _ADAM_BETA2**step, out=tmp)  # z -= lr (m / (1 - b1^t)) / (sqrt(v / (1 - b2^t)) + eps)
        np.sqrt(tmp, out=tmp)
        np.add(tmp, _ADAM_EPS, out=tmp)
        div(m, 1 - _ADAM_BETA1**step, out=grad)
        mul(grad, lr, out=grad)
        div(grad, tmp, out=grad)
        np.subtract(z, grad, out=z)
    return z


def segment_embedding_loss(z: np.ndarray, cooc: np.ndarray | csr_matrix, config: ShadowCorrConfig) -> float:
    """The training loss of :func:`train_segment_embeddings` (for tests and diagnostics; dense).

    With scope ``"component"`` it is the mean over components of their own losses.
    """
    dense = cooc.toarray() if issparse(cooc) else np.asarray(cooc, dtype=np.float64)
    s = dense.shape[0]
    if config.segment_embedding_scope == "component":
        _, comp = connected_components(csr_matrix(dense), directed=False)
    else:
        comp = np.zeros(s, dtype=np.int64)
    zt = torch.nn.functional.normalize(torch.from_numpy(np.asarray(z, dtype=np.float64)), dim=1)
    rows = np.flatnonzero(dense.sum(axis=1) > 0)
    w = torch.from_numpy(_weights(csr_matrix(dense), config).toarray())[rows]
    sim = zt[rows] @ zt.T / config.segment_embedding_tau
    num = torch.logsumexp(sim + torch.where(w > 0, w.log(), torch.full_like(w, -torch.inf)), dim=1)
    domain = torch.from_numpy(comp[rows][:, None] == comp[None, :])
    domain[torch.arange(rows.size), torch.from_numpy(rows)] = False
    den = torch.logsumexp(sim.masked_fill(~domain, -torch.inf), dim=1)
    per_row = -(num - den)
    comp_rows = torch.from_numpy(comp[rows])
    per_comp = torch.zeros(s, dtype=torch.float64).index_add_(0, comp_rows, per_row)
    count = torch.bincount(comp_rows, minlength=s).to(torch.float64)
    return float((per_comp[count > 0] / count[count > 0]).mean())

def voxel_embeddings(
    voxel: np.ndarray, segment: np.ndarray, num_voxels: int, segment_vectors: np.ndarray
) -> np.ndarray:
    """L2-normalised mean of the vectors of the segments contributing to each voxel."""
    membership = csr_matrix((np.ones(voxel.size), (voxel, segment)), shape=(num_voxels, segment_vectors.shape[0]))
    total = membership @ segment_vectors.astype(np.float64)
    count = np.bincount(voxel, minlength=num_voxels)[:, None]
    mean = total / np.maximum(count, 1)
    norm = np.linalg.norm(mean, axis=1, keepdims=True)
    return (mean / np.maximum(norm, 1e-12)).astype(np.float32)
