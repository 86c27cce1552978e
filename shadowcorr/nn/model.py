"""The ShadowCorr voxel embedding network (SPEC §2 step 10): per-voxel layers and k-NN attention.

What the shipped model (neighbourhood ``"reference"``) computes per voxel::

    input_bn -> linear 16->32 -> bn1 -> ReLU -> local_attn1 (k=16 nearest voxels, 4 heads)
             -> linear 32->64 -> bn2 -> ReLU -> local_attn2 (k=32 nearest voxels, 8 heads)
             -> linear 64->32 (+ bias)

The only layers that mix voxels are the two attention layers; everything else is a
per-voxel map.  Submodule names match the reference checkpoint (SPEC §3).

Two neighbourhood modes (``NetConfig.neighbourhood``):

* ``"reference"`` reproduces the reference checkpoint.  The reference was built as a sparse
  3D CNN with 3^3 and 5^3 submanifold convolutions, but it fed them voxel *positions in
  scene units* (grid index x voxel size, multiples of 8), so no kernel offset of reach 1
  or 2 ever finds another voxel and only the centre tap acts: both "convolutions" are
  per-voxel linear maps.  This mode builds them as such (:class:`PointwiseConv3d`, weight
  ``(in, out)``) and keeps only those weights; the full reference-layout kernels
  ``(27 | 125, in, out)`` of a checkpoint are reduced to their centre tap when it is
  loaded (:mod:`.checkpoint`), which gives the same embeddings bit for bit.
* ``"grid"`` gives submanifold convolutions (:class:`SubmanifoldConv3d`) the true grid
  indices, so the 3^3 and 5^3 kernels see real neighbours.

In both modes attention neighbourhoods are the Euclidean k-NN of the voxel positions
``voxel_index * voxel_size``.  A uniform scale does not change distance order, so the
search runs on the integer indices themselves (:func:`knn_on_grid`, linear time), where
equal distances are exact ties (with float positions such as ``i * 0.08`` rounding would
break ties arbitrarily).
Ties are broken by row order, see :mod:`.local_attention`; the reference left them to
its k-NN backend, so on voxels with several equidistant k-th neighbours this network
and the reference can pick different (equally near) neighbours.
"""

from __future__ import annotations

from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator
from torch import nn

from .local_attention import LocalAttention, knn_on_grid
from .sparse_conv import PointwiseConv3d, SubmanifoldConv3d, neighbour_index

__all__ = ["NetConfig", "ShadowCorrNet"]


class NetConfig(BaseModel):
    """Architecture hyper-parameters; the defaults are the reference architecture."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    in_features: int = Field(16, ge=1, description="input features per voxel")
    embed_dim: int = Field(32, ge=1, description="output embedding width")
    widths: tuple[int, int] = Field((32, 64), description="channels after conv1 and conv2")
    kernel_sizes: tuple[int, int] = Field((3, 5), description="cube side of conv1 and conv2 (odd); 'grid' only, "
                                          "'reference' keeps the centre tap")
    attention_k: tuple[int, int] = Field((16, 32), description="neighbours (self included) of local_attn1/2")
    heads: tuple[int, int] = Field((4, 8), description="attention heads of local_attn1/2")
    neighbourhood: Literal["reference", "grid"] = Field(
        "reference", description="'reference': per-voxel linear layers where the reference's convolutions only ever used "
        "their centre tap; 'grid': 3^3 / 5^3 submanifold convolutions over true grid neighbours"
    )

    @model_validator(mode="after")
    def _check(self) -> "NetConfig":
        for i in range(2):
            if self.widths[i] < 1 or self.attention_k[i] < 1 or self.heads[i] < 1:
                raise ValueError("widths, attention_k and heads must be positive")
            if self.kernel_sizes[i] < 1 or self.kernel_sizes[i] % 2 == 0:
                raise ValueError(f"kernel_sizes[{i}] must be a positive odd integer, got {self.kernel_sizes[i]}")
            if self.widths[i] % self.heads[i] != 0:
                raise ValueError(f"widths[{i}] ({self.widths[i]}) must be divisible by heads[{i}] ({self.heads[i]})")
        return self


class ShadowCorrNet(nn.Module):
    """Per-voxel 32-dim embeddings from the 16 ShadowCorr voxel features (see the module docstring).

    Inputs are ragged batches: the voxels of all scenes concatenated, with ``batch``
    giving each voxel's scene.  Scenes never exchange information (convolution and
    attention neighbourhoods stay inside a scene; BatchNorm uses running statistics
    in eval mode), so in eval mode a batched pass equals per-scene passes.
    """

    def __init__(self, config: NetConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or NetConfig()
        (w1, w2), (s1, s2) = config.widths, config.kernel_sizes
        (k1, k2), (h1, h2) = config.attention_k, config.heads
        self.input_bn = nn.BatchNorm1d(config.in_features)
        if config.neighbourhood == "reference":  # the centre tap is all that acts: a per-voxel linear map
            self.conv1: PointwiseConv3d | SubmanifoldConv3d = PointwiseConv3d(config.in_features, w1, bias=False)
            self.conv2: PointwiseConv3d | SubmanifoldConv3d = PointwiseConv3d(w1, w2, bias=False)
        else:
            self.conv1 = SubmanifoldConv3d(config.in_features, w1, s1, bias=False)
            self.conv2 = SubmanifoldConv3d(w1, w2, s2, bias=False)
        self.bn1 = nn.BatchNorm1d(w1)
        self.local_attn1 = LocalAttention(w1, h1, k1)
        self.bn2 = nn.BatchNorm1d(w2)
        self.local_attn2 = LocalAttention(w2, h2, k2)
        self.conv3 = PointwiseConv3d(w2, config.embed_dim, bias=True)

    def forward(
        self,
        features: torch.Tensor,
        voxel_index: torch.Tensor,
        voxel_size: float,
        batch: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Embed every voxel.

        Args:
            features: (N, in_features) float voxel features (SPEC §2 step 9).
            voxel_index: (N, 3) int64 integer grid indices (position / voxel_size),
                unique within a scene.
            voxel_size: grid spacing in scene units; positions are
                ``voxel_index * voxel_size``.  Outputs do not depend on it (see the
                module docstring) but it is part of the contract so that positions
                are always well defined.
            batch: (N,) int64 scene id per voxel; ``None`` means one scene.

        Returns:
            (N, embed_dim) float embeddings.
        """
        n = features.shape[0]
        if features.ndim != 2 or features.shape[1] != self.config.in_features:
            raise ValueError(f"features must be (N, {self.config.in_features}), got {tuple(features.shape)}")
        if voxel_index.shape != (n, 3) or voxel_index.dtype.is_floating_point:
            raise ValueError(f"voxel_index must be ({n}, 3) integer grid indices, got {tuple(voxel_index.shape)} {voxel_index.dtype}")
        if not voxel_size > 0:
            raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
        if batch is None:
            batch = torch.zeros(n, dtype=torch.int64, device=features.device)
        if batch.shape != (n,):
            raise ValueError(f"batch must be ({n},), got {tuple(batch.shape)}")
        voxel_index = voxel_index.to(torch.int64)
        if n == 0:
            return features.new_zeros((0, self.config.embed_dim))

        # One k-NN search serves both attention layers: the table is ordered by
        # (distance, row), so its first k1 columns are the k1-NN.
        k1, k2 = self.local_attn1.k, self.local_attn2.k
        knn, valid = knn_on_grid(voxel_index, batch, max(k1, k2), return_valid=True)

        x = self.input_bn(features)
        x = self._conv(self.conv1, x, voxel_index, batch)
        x = torch.relu(self.bn1(x))
        x = self.local_attn1(x, neighbours=knn, valid=valid)
        x = self._conv(self.conv2, x, voxel_index, batch)
        x = torch.relu(self.bn2(x))
        x = self.local_attn2(x, neighbours=knn, valid=valid)
        return self.conv3(x)

    def _conv(self, conv: PointwiseConv3d | SubmanifoldConv3d, x: torch.Tensor, voxel_index: torch.Tensor,
              batch: torch.Tensor) -> torch.Tensor:
        if isinstance(conv, PointwiseConv3d):  # 'reference': what the reference computes (SPEC §3)
            return conv(x)
        return conv(x, voxel_index, batch, neighbour_index(voxel_index, batch, conv.offsets))
