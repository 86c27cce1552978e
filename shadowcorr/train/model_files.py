"""Model files around training: start a network from one (``--init``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from ..nn import ShadowCorrNet, load_model

__all__ = ["init_from_model"]


def init_from_model(net: ShadowCorrNet, path: str | Path) -> dict[str, Any]:
    """Copy the weights of a model file into ``net``; returns a provenance record.

    The architecture must match apart from the neighbourhood mode.  Starting a "grid"
    network from a "reference" model, the reference's per-voxel weights become the centre
    taps of the grid kernels and the other taps start at zero (a reference network has
    none: they never acted, SPEC §3), so the grid network starts out computing exactly the
    reference's function.
    """
    src = load_model(path)
    a, b = src.card.architecture, net.config
    if a.model_copy(update={"neighbourhood": b.neighbourhood}) != b:
        raise ValueError(f"--init {path}: architecture {a!r} does not fit {b!r}")
    state = {k: v.clone() for k, v in src.net.state_dict().items()}
    zeroed = []
    if a.neighbourhood == "reference" and b.neighbourhood == "grid":
        for name in ("conv1", "conv2"):
            conv = getattr(net, name)
            kernel = torch.zeros_like(conv.kernel)
            kernel[conv.centre] = state[f"{name}.kernel"]
            state[f"{name}.kernel"] = kernel
            zeroed.append(name)
    net.load_state_dict(state, strict=True)
    return {"path": str(path), "name": src.name, "version": src.version, "sha256": src.sha256,
            "neighbourhood": a.neighbourhood, "zeroed_off_centre_taps": zeroed}  # fmt: skip
