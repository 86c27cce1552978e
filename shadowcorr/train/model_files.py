"""Model files around training: start a network from one (``--init``), re-export one with its card amended."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import torch

from ..nn import ModelCard, ShadowCorrNet, load_model, save_model

__all__ = ["copy_with_card_update", "init_from_model"]


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


def copy_with_card_update(src: str | Path, dst: str | Path, *, metrics: dict[str, Any] | None = None,
                          training: dict[str, Any] | None = None, notes: str | None = None,
                          name: str | None = None, version: str | None = None, license: str | None = None,
                          license_file: str | Path | None = None) -> str:
    """Re-export a model file with its card amended (e.g. real-scene figures measured afterwards).

    The weights are copied unchanged; ``metrics`` and ``training`` are merged into the
    card's dicts.  ``license_file``'s text is stored under the metadata key
    ``"license_text"`` (weights fine-tuned from the reference keep its MIT notice).
    Returns the new file's sha256.
    """
    m = load_model(src)
    card = copy.deepcopy(m.card)
    card.metrics = {**card.metrics, **(metrics or {})}
    card.training = {**card.training, **(training or {})}
    if notes is not None:
        card.notes = notes
    if name is not None:
        card.name = name
    if version is not None:
        card.version = version
    if license is not None:
        card.license = license
    extra = {"license_text": Path(license_file).read_text()} if license_file is not None else None
    return save_model(m.net, ModelCard.model_validate(card.model_dump()), dst, extra_metadata=extra)
