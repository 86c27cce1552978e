"""Scores of one labelled scene against its ground truth, and the per-voxel truth behind them.

Ground truth enters here and in training targets only: nothing that produces a
prediction imports this module (the pipeline imports it only when metrics are asked for).
"""

from __future__ import annotations

import numpy as np

from ..stages import VoxelScene
from ._metrics import segment_metrics, voxel_ari


def voxel_truth(scene: VoxelScene) -> np.ndarray:
    """Ground-truth object per kept voxel: the object whose segments give it the most confidence.

    For metrics and training targets only; never an input feature.  Sparse: confidence is
    summed per (voxel, object) pair that occurs, so the cost follows the memberships rather
    than voxels times objects.
    """
    if scene.num_voxels == 0:
        return np.zeros(0, dtype=np.int64)
    truth = scene.segment_truth[scene.member_segment]
    objects, obj_idx = np.unique(truth, return_inverse=True)
    pair, pair_of_member = np.unique(scene.member_voxel * objects.size + obj_idx, return_inverse=True)
    score = np.bincount(pair_of_member, weights=scene.member_confidence, minlength=pair.size)
    voxel, obj = np.divmod(pair, objects.size)
    # Per voxel the highest score wins; ties go to the lowest object index (as argmax did).
    order = np.lexsort((obj, -score, voxel))
    first = order[np.r_[True, voxel[order][1:] != voxel[order][:-1]]]
    out = np.zeros(scene.num_voxels, dtype=np.int64)
    out[voxel[first]] = objects[obj[first]]
    return out


def score_scene(scene: VoxelScene, seg_object: np.ndarray, voxel_object: np.ndarray) -> dict[str, float | int]:
    """Segment-level purities (SPEC §5), voxel ARI and coverage against the scene's ground truth."""
    m = dict(segment_metrics(scene.segment_truth, seg_object))
    if scene.num_voxels:
        m["voxel_ari"] = float(voxel_ari(voxel_truth(scene), voxel_object))
    return m
