"""Run a model over a ragged list of scenes in one forward pass."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from .checkpoint import Model

__all__ = ["run_batched"]


def run_batched(
    model: Model,
    features_list: Sequence[np.ndarray],
    voxel_index_list: Sequence[np.ndarray],
    *,
    voxel_size: float | None = None,
) -> list[np.ndarray]:
    """Embed several scenes with one forward pass.

    The scenes' voxels are concatenated with a scene index (``batch``), the network runs
    once under ``torch.inference_mode``, and the output is split back by scene length.
    Since scenes never interact (eval mode), each result equals running that scene alone.

    Args:
        model: a loaded :class:`Model` (its net is in eval mode).
        features_list: per scene, (V_i, in_features) float voxel features.
        voxel_index_list: per scene, (V_i, 3) integer grid indices, unique per scene.
        voxel_size: grid spacing in the model's units; default ``model.card.voxel_size``.

    Returns:
        Per scene, a (V_i, embed_dim) float32 array (empty scenes give (0, embed_dim)).
    """
    if len(features_list) != len(voxel_index_list):
        raise ValueError(f"{len(features_list)} feature arrays but {len(voxel_index_list)} voxel index arrays")
    cfg = model.net.config
    feats, idxs, lengths = [], [], []
    for i, (f, v) in enumerate(zip(features_list, voxel_index_list)):
        f = np.asarray(f)
        v = np.asarray(v)
        if f.ndim != 2 or f.shape[1] != cfg.in_features:
            raise ValueError(f"scene {i}: features must be (V, {cfg.in_features}), got {f.shape}")
        if v.shape != (f.shape[0], 3):
            raise ValueError(f"scene {i}: voxel_index must be ({f.shape[0]}, 3), got {v.shape}")
        if not np.issubdtype(v.dtype, np.integer):
            raise ValueError(f"scene {i}: voxel_index must be integer grid indices, got dtype {v.dtype}")
        if not np.all(np.isfinite(f)):
            raise ValueError(f"scene {i}: features contain NaN or infinite values")
        feats.append(np.ascontiguousarray(f, dtype=np.float32))
        idxs.append(np.ascontiguousarray(v, dtype=np.int64))
        lengths.append(f.shape[0])
    total = sum(lengths)
    if total == 0:
        return [np.zeros((0, cfg.embed_dim), np.float32) for _ in lengths]

    dev = model.device
    features = torch.from_numpy(np.concatenate(feats)).to(dev)
    voxel_index = torch.from_numpy(np.concatenate(idxs)).to(dev)
    batch = torch.repeat_interleave(torch.arange(len(lengths)), torch.tensor(lengths)).to(dev)
    with torch.inference_mode():
        out = model.net(features, voxel_index, float(voxel_size or model.card.voxel_size), batch)
    out = out.float().cpu().numpy()
    return [a.copy() for a in np.split(out, np.cumsum(lengths)[:-1])]
