"""The stage API: ``prepare`` -> ``embed`` -> ``assign``, and ``correspond`` composing them.

``prepare`` and ``assign`` are per scene and CPU-bound (the HTTP service runs them in
worker processes); ``embed`` takes a list of prepared scenes and runs the network
once over all of them (the service batches concurrent requests through it).
"""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from .assignment import assign
from .bundle import SceneBundle, unit_scale
from .config import NETWORK_METHODS, SURFACE_METHODS, ShadowCorrConfig
from .errors import SceneLimitError
from .nn import Model, load_model, run_batched
from .pose_refinement import pose_warnings, refine_poses
from .result import ModelInfo, Result
from .segments import check_valid_depth, extract_segments
from .shadows import ShadowVoxels, cast_shadows, raw_shells, segment_shells
from .surface_evidence import surface_evidence
from .voxel_scene import VoxelScene, build_voxel_scene


def prepare(bundle: SceneBundle, config: ShadowCorrConfig | None = None) -> VoxelScene:
    """Pose refinement (when asked for), segments, then the evidence the configured method reads.

    ``shadowcorr``, ``meanshift`` and ``fused`` cast shadows and build the consensus voxels and
    network features; ``projection`` and ``fused`` project every segment into the other
    views (cross-view surface evidence).
    """
    config = config or ShadowCorrConfig()
    timings: dict[str, float] = {}
    poses = None
    if config.refine_poses:
        t0 = time.perf_counter()
        bundle, poses = refine_poses(bundle, config)
        timings["poses"] = (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    segments = extract_segments(bundle, config)
    if segments.num_segments == 0:
        raise ValueError(
            "the scene has no segments: every mask is empty, or every blob is smaller than "
            f"min_blob_pixels = {config.min_blob_pixels}"
        )
    if segments.num_segments > config.max_segments:
        raise SceneLimitError("max_segments", segments.num_segments, config.max_segments)
    depth_warnings = check_valid_depth(segments, bundle.units, config)  # DepthRangeError when nearly all are empty
    timings["segments"] = (time.perf_counter() - t0) * 1e3
    surface = None
    if config.method in SURFACE_METHODS:
        t0 = time.perf_counter()
        surface = surface_evidence(bundle, segments, config)
        timings["surface_evidence"] = (time.perf_counter() - t0) * 1e3
    segments.pixel_segment = None  # the label images serve the surface evidence only: free them now
    if config.method == "projection":
        shells, shadows = raw_shells(segments), ShadowVoxels.empty()
    else:
        t0 = time.perf_counter()
        shells = segment_shells(segments, config)
        timings["shells"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        shadows = cast_shadows(segments, shells, config)
        timings["shadows"] = (time.perf_counter() - t0) * 1e3
    scene = build_voxel_scene(
        bundle.name, bundle.units, unit_scale(bundle.units, config.units), segments, shells, shadows, config, timings
    )
    scene.surface = surface
    scene.poses = poses
    # Segments without depth first: they say the most about whether the result can be trusted.
    scene.warnings[:0] = depth_warnings + list(bundle.warnings) + (pose_warnings(poses) if poses else [])
    return scene


def check_compatible(model: Model, config: ShadowCorrConfig) -> None:
    """The scene must be voxelised as the model was trained (same voxel size and units)."""
    card = model.card
    if card.units != config.units or abs(card.voxel_size - config.voxel_size) > 1e-9:
        raise ValueError(
            f"model {card.name!r} expects voxel_size {card.voxel_size} {card.units}, "
            f"the configuration has {config.voxel_size} {config.units}"
        )
    if len(card.features) != config.feature_dim:
        raise ValueError(f"model {card.name!r} takes {len(card.features)} features, the configuration makes {config.feature_dim}")


def embed(model: Model, scenes: Sequence[VoxelScene]) -> list[np.ndarray]:
    """Network embeddings of several prepared scenes in one forward pass (ragged batch)."""
    for scene in scenes:
        check_compatible(model, scene.config)
    return run_batched(model, [s.features for s in scenes], [s.voxel_index for s in scenes])


def baseline_embeddings(scene: VoxelScene) -> np.ndarray:
    """The paper's MeanShift baseline clusters normalised confidence and position, no network."""
    return np.ascontiguousarray(scene.features[:, :4])


def model_info(model: Model) -> ModelInfo:
    return ModelInfo(name=model.name, version=model.version, sha256=model.sha256)


def correspond(
    bundle: SceneBundle,
    model: Model | None = None,
    config: ShadowCorrConfig | None = None,
    *,
    metrics: bool = True,
) -> Result:
    """Label every segment of one scene: ``assign(prepare(bundle), embed(model, [scene])[0])``.

    ``model`` defaults to the packaged default model.  With ``config.method ==
    'meanshift'`` the paper's baseline runs instead and no model is used.  Metrics are
    added when ``metrics`` is true and the bundle carries ground truth.
    """
    config = config or ShadowCorrConfig()
    scene = prepare(bundle, config)
    if config.method not in NETWORK_METHODS:
        return assign(scene, baseline_embeddings(scene), config, metrics=metrics)
    model = model or load_model()
    t0 = time.perf_counter()
    (embeddings,) = embed(model, [scene])
    scene.timings_ms["network"] = (time.perf_counter() - t0) * 1e3
    return assign(scene, embeddings, config, model=model_info(model), metrics=metrics)
