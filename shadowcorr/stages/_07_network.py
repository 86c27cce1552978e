"""Stage 7: voxel features -> per-voxel embeddings (SPEC §2 step 10).

The network itself (architecture, checkpoint files, the packaged model) lives in
:mod:`shadowcorr.nn`; this stage checks that a scene was voxelised as the model was
trained and runs the model once over a ragged batch of scenes.  The paper's MeanShift
baseline uses no network: its "embeddings" are the voxels' normalised confidence and
position (:func:`baseline_embeddings`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..config import ShadowCorrConfig
from ..nn import Model, run_batched
from ..result import ModelInfo
from ._06_voxel_scene import VoxelScene


def check_compatible(model: Model, config: ShadowCorrConfig) -> None:
    """The scene must be voxelised as the model was trained (same voxel size and units)."""
    card = model.card
    if card.units != config.units or abs(card.voxel_size - config.voxel_size) > 1e-9:
        raise ValueError(
            f"model {card.name!r} expects voxel_size {card.voxel_size} {card.units}, "
            f"the configuration has {config.voxel_size} {config.units}"
        )
    if len(card.features) != config.feature_dim:
        raise ValueError(f"model {card.name!r} takes {len(card.features)} features, the configuration makes {config.feature_dim}")


def embed(model: Model, scenes: Sequence[VoxelScene]) -> list[np.ndarray]:
    """Network embeddings of several prepared scenes in one forward pass (ragged batch)."""
    for scene in scenes:
        check_compatible(model, scene.config)
    return run_batched(model, [s.features for s in scenes], [s.voxel_index for s in scenes])


def baseline_embeddings(scene: VoxelScene) -> np.ndarray:
    """The paper's MeanShift baseline clusters normalised confidence and position, no network."""
    return np.ascontiguousarray(scene.features[:, :4])


def model_info(model: Model) -> ModelInfo:
    """The model's name, version and file hash, as the result reports them."""
    return ModelInfo(name=model.name, version=model.version, sha256=model.sha256)
