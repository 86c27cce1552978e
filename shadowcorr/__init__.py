"""ShadowCorr: which 3D segments, seen from different viewpoints, are the same object.

The library is a pipeline of stages with plain data between them::

    SceneBundle --prepare--> VoxelScene --embed--> embeddings --assign--> Result

``correspond(bundle)`` runs them all.  See ``docs/CONTRACTS.md`` and the README.
"""

from ._version import __version__
from .assign import assign
from .bundle import Manifest, PointSegments, SceneBundle, View
from .config import REQUEST_OPTIONS, ShadowCorrConfig
from .errors import BundleError, Problem
from .io import BundleLimits, load_bundle, load_bundle_from_parts, write_bundle, write_bundle_archive
from .nn import Model, ModelCard, load_model, save_model
from .pipeline import correspond, embed, prepare
from .result import ObjectSummary, Result, SegmentLabel
from .voxel_scene import VoxelScene

__all__ = [
    "BundleError",
    "BundleLimits",
    "Manifest",
    "Model",
    "ModelCard",
    "ObjectSummary",
    "PointSegments",
    "Problem",
    "REQUEST_OPTIONS",
    "Result",
    "SceneBundle",
    "SegmentLabel",
    "ShadowCorrConfig",
    "View",
    "VoxelScene",
    "__version__",
    "assign",
    "correspond",
    "embed",
    "load_bundle",
    "load_bundle_from_parts",
    "load_model",
    "prepare",
    "save_model",
    "write_bundle",
    "write_bundle_archive",
]
