"""Evaluation: scores of a prediction against ground truth (SPEC §5).

Nothing that produces a prediction imports this package; ``shadowcorr.assign`` loads it
only when metrics are asked for and the scene carries ground truth.

- :func:`segment_metrics` - segment-level rock / cluster / average purity, one-to-one matches, coverage;
- :func:`voxel_ari` - adjusted Rand index of voxel labels;
- :func:`summarize` - mean and standard deviation of many scenes' metrics;
- :func:`voxel_truth`, :func:`score_scene` - the per-voxel ground truth of a prepared scene
  (also the training target) and all the metrics of one labelled scene;
- :func:`pose_errors` - rotation and camera-centre errors of refined poses.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

_EXPORTS = {
    "segment_metrics": "_metrics",
    "summarize": "_metrics",
    "voxel_ari": "_metrics",
    "score_scene": "_scene_scores",
    "voxel_truth": "_scene_scores",
    "pose_errors": ".stages._01_poses"  # (relative to this package: shadowcorr.stages),
}

__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from ..stages._01_poses import pose_errors
    from ._metrics import segment_metrics, summarize, voxel_ari
    from ._scene_scores import score_scene, voxel_truth
