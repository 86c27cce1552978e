"""ShadowCorr: which 3D segments, seen from different viewpoints, are the same object.

The library is a pipeline of stages with plain data between them::

    SceneBundle --prepare--> VoxelScene --embed--> embeddings --assign--> Result
                 segments, surface evidence,       (network)     evidence graph -> groups -> labels
                 shadows -> consensus voxels

The default method ``fused`` reads both the cross-view surface evidence and the network's
volumetric evidence; ``ShadowCorrConfig.method`` selects another.

``correspond(bundle)`` runs them all; ``SiteMap`` keeps a site's objects across scans.  The stages themselves are in :mod:`shadowcorr.stages`,
numbered in the order they run, and :mod:`shadowcorr.pipeline` composes them; see
``docs/ARCHITECTURE.md``, ``docs/CONTRACTS.md`` and the README.

Public names are imported lazily (PEP 562), so that light users such as the HTTP
client can read ``shadowcorr.result`` without loading torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ._lazy import lazy_exports
from ._version import __version__

_EXPORTS = {
    "assign": "pipeline",
    "BundleError": "errors",
    "Problem": "errors",
    "SceneLimitError": "errors",
    "DepthRangeError": "errors",
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
    "object_points": "pipeline",
    "export": "export",
    "ObjectPoints": "stages",
    "OrientedBox": "result",
    "embed": "pipeline",
    "prepare": "pipeline",
    "refine_poses": "stages",
    "ObjectSummary": "result",
    "Result": "result",
    "SegmentLabel": "result",
    "ViewPoseCorrection": "result",
    "VoxelScene": "stages",
    "SiteMap": "sitemap",
    "MapUpdate": "sitemap",
    "MapBusyError": "sitemap",
    "add_to_map": "sitemap",
}

__all__ = ["__version__", *sorted(_EXPORTS)]
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from .bundle import Manifest, PointSegments, SceneBundle, View
    from .config import REQUEST_OPTIONS, ShadowCorrConfig
    from .errors import BundleError, DepthRangeError, Problem, SceneLimitError
    from .io import BundleLimits, load_bundle, load_bundle_from_parts, write_bundle, write_bundle_archive
    from .nn import Model, ModelCard, load_model, save_model
    from .export import export
    from .pipeline import assign, correspond, embed, object_points, prepare
    from .result import ObjectSummary, OrientedBox, Result, SegmentLabel, ViewPoseCorrection
    from .sitemap import MapBusyError, MapUpdate, SiteMap, add_to_map
    from .stages import ObjectPoints, VoxelScene, refine_poses
