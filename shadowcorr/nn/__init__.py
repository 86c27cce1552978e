"""ShadowCorr network: sparse convolution, local attention, the model and its files.

Pure PyTorch; runs on CPU (GPU optional).  Inputs are ragged batches: the voxels of
several scenes concatenated, with an explicit ``batch`` (scene index) per voxel.
"""

from .batch import run_batched
from .checkpoint import (
    DEFAULT_MODEL_PATH,
    Model,
    ModelCard,
    check_state_dict,
    convert_checkpoint,
    load_model,
    reference_card,
    save_model,
)
from .local_attention import LocalAttention, knn_on_grid, knn_within_scene
from .model import NetConfig, ShadowCorrNet
from .sparse_conv import PointwiseConv3d, SubmanifoldConv3d, VoxelHash, kernel_offsets, neighbour_index

__all__ = [
    "DEFAULT_MODEL_PATH",
    "LocalAttention",
    "Model",
    "ModelCard",
    "NetConfig",
    "PointwiseConv3d",
    "ShadowCorrNet",
    "SubmanifoldConv3d",
    "check_state_dict",
    "convert_checkpoint",
    "VoxelHash",
    "kernel_offsets",
    "knn_on_grid",
    "knn_within_scene",
    "load_model",
    "neighbour_index",
    "reference_card",
    "run_batched",
    "save_model",
]
