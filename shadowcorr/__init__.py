"""ShadowCorr: which 3D segments, seen from different viewpoints, are the same object.

The library is a pipeline of stages with plain data between them::

    SceneBundle --prepare--> VoxelScene --embed--> embeddings --assign--> Result

``correspond(bundle)`` runs them all.  See ``docs/CONTRACTS.md`` and the README.

Public names are imported lazily (PEP 562), so that light users such as the HTTP
client can read ``shadowcorr.result`` without loading torch.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from ._version import __version__

_EXPORTS = {
    "assign": "assignment",
    "BundleError": "errors",
    "Problem": "errors",
    "SceneLimitError": "errors",
    "Manifest": "bundle",
    "PointSegments": "bundle",
    "SceneBundle": "bundle",
    "View": "bundle",
    "REQUEST_OPTIONS": "config",
    "ShadowCorrConfig": "config",
    "BundleLimits": "io",
    "load_bundle": "io",
    "load_bundle_from_parts": "io",
    "write_bundle": "io",
    "write_bundle_archive": "io",
    "Model": "nn",
    "ModelCard": "nn",
    "load_model": "nn",
    "save_model": "nn",
    "correspond": "pipeline",
    "embed": "pipeline",
    "prepare": "pipeline",
    "ObjectSummary": "result",
    "Result": "result",
    "SegmentLabel": "result",
    "VoxelScene": "voxel_scene",
}

__all__ = ["__version__", *sorted(_EXPORTS)]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'shadowcorr' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from .assignment import assign
    from .bundle import Manifest, PointSegments, SceneBundle, View
    from .config import REQUEST_OPTIONS, ShadowCorrConfig
    from .errors import BundleError, Problem, SceneLimitError
    from .io import BundleLimits, load_bundle, load_bundle_from_parts, write_bundle, write_bundle_archive
    from .nn import Model, ModelCard, load_model, save_model
    from .pipeline import correspond, embed, prepare
    from .result import ObjectSummary, Result, SegmentLabel
    from .voxel_scene import VoxelScene
