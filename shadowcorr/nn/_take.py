"""``take``: ``source[index]`` along the first dimension, for an index of any shape."""

from __future__ import annotations

import numpy as np
import torch


def take(source: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``source[index]`` (rows of ``source`` picked by an int64 ``index`` of any shape), the same
    values as advanced indexing.

    On the CPU numpy's ``take`` gathers 2-4x faster than torch's advanced indexing (the
    network's neighbour gathers and grid lookups: 2.0 -> 0.5 ms for 344,400 keys, 9 -> 3 ms for
    the (2,268, 32) neighbours of 64 features, one thread).  Tensors that need a gradient
    (training) and tensors on other devices gather with ``index_select``.
    """
    if source.device.type == "cpu" and not source.requires_grad:
        return torch.from_numpy(np.take(source.numpy(), index.numpy(), axis=0))
    return source.index_select(0, index.reshape(-1)).view(*index.shape, *source.shape[1:])
