"""Stage 8: network embeddings -> volumetric evidence between segments (method ``fused``).

Two segments whose shadows share consensus voxels may be one object (their shadows meet
inside it) or two touching ones; the network, which sees the overlap patterns of the whole
scene, tells them apart.  Each segment's embedding is the confidence-weighted mean of the
network's embeddings of its kept voxels; for every pair of segments that share at least one
kept voxel the evidence is

    value = tanh((fusion_volume_distance - |e_a - e_b|) / fusion_volume_scale)   in (-1, 1)
    mass  = min(shared voxels / fusion_volume_voxels, 1)

Only pairs that share voxels exist, so the cost follows the number of voxel memberships
(sparse product), never segments squared.  Nothing here reads ground truth.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix, triu

from ..config import ShadowCorrConfig
from ._06_voxel_scene import VoxelScene


def segment_embeddings(scene: VoxelScene, embeddings: np.ndarray) -> np.ndarray:
    """(S, D) confidence-weighted mean of each segment's kept voxel embeddings (zeros if none)."""
    s, w = scene.num_segments, scene.member_confidence
    weights = coo_matrix((w, (scene.member_segment, scene.member_voxel)), shape=(s, scene.num_voxels)).tocsr()
    total = weights @ np.asarray(embeddings, dtype=np.float64)
    return total / np.maximum(np.bincount(scene.member_segment, weights=w, minlength=s), 1e-12)[:, None]


def volume_pairs(scene: VoxelScene, embeddings: np.ndarray, config: ShadowCorrConfig
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(a, b, value, mass) for every pair a < b of segments sharing kept voxels."""
    s, v = scene.num_segments, scene.num_voxels
    none = np.zeros(0, dtype=np.int64)
    if v == 0 or s < 2:
        return none, none, np.zeros(0), np.zeros(0)
    membership = coo_matrix((np.ones(scene.member_voxel.size), (scene.member_voxel, scene.member_segment)),
                            shape=(v, s)).tocsr()
    shared = triu(membership.T @ membership, k=1).tocoo()
    a, b, count = shared.row.astype(np.int64), shared.col.astype(np.int64), shared.data
    seg_emb = segment_embeddings(scene, embeddings)
    distance = np.linalg.norm(seg_emb[a] - seg_emb[b], axis=1)
    value = np.tanh((config.fusion_volume_distance - distance) / config.fusion_volume_scale)
    mass = np.minimum(count / config.fusion_volume_voxels, 1.0)
    return a, b, value, mass
