"""Training ShadowCorr networks (``shadowcorr train``): cached voxel scenes, the paper's loss, the loop.

* :mod:`.dataset` - bundles -> prepared voxel scenes + per-voxel targets, cached as ``.npz``.
* :mod:`.losses` - discriminative + prototypical + graph loss on ragged batches.
* :mod:`.trainer` - Adam loop, validation through ``assign()``, checkpoints, model export.
"""

from .dataset import TrainScene, find_bundles, load_scene, prepare_scenes, save_scene
from .losses import LossConfig, multi_objective_loss
from .trainer import TrainConfig, Trainer, evaluate_scenes, train

__all__ = [
    "LossConfig",
    "TrainConfig",
    "TrainScene",
    "Trainer",
    "evaluate_scenes",
    "find_bundles",
    "load_scene",
    "multi_objective_loss",
    "prepare_scenes",
    "save_scene",
    "train",
]
