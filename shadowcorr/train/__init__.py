"""Training ShadowCorr networks (``shadowcorr train``): cached voxel scenes, the paper's loss, the loop.

* :mod:`.dataset` - bundles -> prepared voxel scenes + per-voxel targets, cached as ``.npz``.
* :mod:`.losses` - discriminative + prototypical + graph loss on ragged batches.
* :mod:`.trainer` - Adam loop, validation through ``assign()``, checkpoints, model export.
* :mod:`.model_files` - start from a model file (``--init``).
"""

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

_EXPORTS = {
    "TrainScene": "dataset",
    "find_bundles": "dataset",
    "load_scene": "dataset",
    "prepare_scenes": "dataset",
    "save_scene": "dataset",
    "LossConfig": "losses",
    "multi_objective_loss": "losses",
    "TrainConfig": "trainer",
    "Trainer": "trainer",
    "evaluate_scenes": "trainer",
    "train": "trainer",
}

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
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from .dataset import TrainScene, find_bundles, load_scene, prepare_scenes, save_scene
    from .losses import LossConfig, multi_objective_loss
    from .trainer import TrainConfig, Trainer, evaluate_scenes, train
