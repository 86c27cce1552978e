"""The pipeline, composed: ``prepare`` -> ``embed`` -> ``assign``, and ``correspond`` running all three.

Each step below calls the stages of :mod:`shadowcorr.stages` in their order (the numbers
are the stage modules').  ``prepare`` and ``assign`` are per scene and CPU-bound (the HTTP
service runs them in worker processes); ``embed`` takes a list of prepared scenes and runs
the network once over all of them (the service batches concurrent requests through it).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from .bundle import SceneBundle, unit_scale
from .config import NETWORK_METHODS, SURFACE_METHODS, ShadowCorrConfig
from .errors import SceneLimitError
from .nn import Model, load_model
from .result import ModelInfo, Result
from .stages._01_poses import pose_warnings, refine_poses, unverified_poses
from .stages._02_segments import Segments, check_valid_depth, extract_segments
from .stages._03_surface_evidence import surface_evidence
from .stages._04_shells import raw_shells, segment_shells
from .stages._05_occupancy import shadow_occupancy
from .stages._05_shadows import ShadowVoxels, cast_shadows
from .stages._06_voxel_scene import VoxelScene, build_voxel_scene
from .stages._07_network import baseline_embeddings, check_compatible, embed, model_info
from .stages._09_clustering import cluster_voxels
from .stages._09_grouping import group_by_evidence
from .stages._09_support import segment_support
from .stages._10_assignment import evidence_labels, number_objects, object_summaries, orphan_warnings, segment_labels, vote
from .stages._11_geometry import ObjectPoints, fuse_object_points, object_geometry, with_geometry

__all__ = ["assign", "baseline_embeddings", "check_compatible", "correspond", "cut_segments", "embed", "model_info",
           "object_points", "prepare", "prepare_segments", "with_pose_corrections"]


def _ms_since(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def _check_stage_time(timings: dict[str, float], config: ShadowCorrConfig) -> None:
    """Raise :class:`SceneLimitError` when a stage timed so far ran beyond ``max_stage_seconds``.

    Called as each stage ends, so the scene is refused before its next stage starts.
    """
    if config.max_stage_seconds is None or not timings:
        return
    stage = max(timings, key=timings.get)
    if timings[stage] > config.max_stage_seconds * 1e3:
        raise SceneLimitError("max_stage_seconds", round(timings[stage] / 1e3, 3), config.max_stage_seconds,
                              f"seconds in stage {stage!r}")


def prepare(bundle: SceneBundle, config: ShadowCorrConfig | None = None) -> VoxelScene:
    """Pose refinement (when asked for), segments, then the evidence the configured method reads.

    ``shadowcorr``, ``meanshift`` and ``fused`` cast shadows and build the consensus voxels and
    network features; ``projection`` and ``fused`` project every segment into the other
    views (cross-view surface evidence).
    """
    config = config or ShadowCorrConfig()
    timings: dict[str, float] = {}
    poses = None
    if config.refine_poses:  # 01
        t0 = time.perf_counter()
        bundle, poses = refine_poses(bundle, config)
        timings["poses"] = _ms_since(t0)
        _check_stage_time(timings, config)
    segments, depth_warnings = cut_segments(bundle, config, timings)  # 02
    unverified = None if poses is None else unverified_poses(poses)
    scene = prepare_segments(bundle, segments, config, timings, unverified)  # 03-06
    scene.poses = poses
    # Segments without depth first: they say the most about whether the result can be trusted.
    scene.warnings[:0] = depth_warnings + list(bundle.warnings) + (pose_warnings(poses) if poses else [])
    return scene


def cut_segments(bundle: SceneBundle, config: ShadowCorrConfig, timings: dict[str, float] | None = None
                 ) -> tuple[Segments, list[str]]:
    """Stage 02 with the checks every scene passes: at least one segment, at most ``max_segments``,
    enough valid depth (:class:`DepthRangeError` otherwise).  Returns the segments and the depth warnings."""
    timings = {} if timings is None else timings
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
    timings["segments"] = _ms_since(t0)
    _check_stage_time(timings, config)
    return segments, depth_warnings


def prepare_segments(bundle: SceneBundle, segments: Segments, config: ShadowCorrConfig,
                     timings: dict[str, float] | None = None, unverified: np.ndarray | None = None) -> VoxelScene:
    """Stages 03-06 on segments already cut: surface evidence, shells, shadows, the voxel scene.

    ``bundle`` supplies what the cross-view evidence reads of every view of ``segments``
    (depth, intrinsics, pose), in the same order; the segments may come from elsewhere than its
    masks (the site map adds the stored segments of earlier scans).  ``segments.pixel_segment``
    is released once the surface evidence has read it.  ``unverified`` (per view of ``bundle``,
    :func:`~shadowcorr.stages.unverified_poses`) marks the views whose declared poses pose
    refinement could not bear out (None: no refinement ran).
    """
    timings = {} if timings is None else timings
    surface = None
    if config.method in SURFACE_METHODS:  # 03
        t0 = time.perf_counter()
        surface = surface_evidence(bundle, segments, config, unverified)
        timings["surface_evidence"] = _ms_since(t0)
        _check_stage_time(timings, config)
    segments.pixel_segment = None  # the label images serve the surface evidence only: free them now
    if config.method == "projection":
        shells, shadows = raw_shells(segments), ShadowVoxels.empty()
    else:
        t0 = time.perf_counter()  # 04
        shells = segment_shells(segments, config)
        timings["shells"] = _ms_since(t0)
        _check_stage_time(timings, config)
        t0 = time.perf_counter()  # 05
        shadows = cast_shadows(segments, shells, config)
        timings["shadows"] = _ms_since(t0)
        _check_stage_time(timings, config)
    t0 = time.perf_counter()  # 05 occupancy: what the depth images leave solid of the shadows
    occupancy = shadow_occupancy(bundle.views, shadows, unit_scale(bundle.units, config.units), config,
                                 segments.depth_noise)
    timings["occupancy"] = _ms_since(t0)
    _check_stage_time(timings, config)
    scene = build_voxel_scene(  # 06
        bundle.name, bundle.units, unit_scale(bundle.units, config.units), segments, shells, shadows, config, timings
    )
    _check_stage_time(timings, config)  # consensus, segment embeddings, features
    scene.surface = surface
    scene.occupancy = occupancy if occupancy.cell.size else None
    scene.view_poses = np.stack([v.pose for v in bundle.views])
    return scene


# embed (07) is the stage function itself: stages._07_network.embed


def assign(
    scene: VoxelScene,
    embeddings: np.ndarray,
    config: ShadowCorrConfig | None = None,
    *,
    model: ModelInfo | None = None,
    metrics: bool = False,
) -> Result:
    """Group the segments or cluster the voxel embeddings, and label every segment.

    ``config`` defaults to the configuration the scene was prepared with; only its
    grouping and clustering fields (``method``, ``bandwidth``, ``baseline_bandwidth``,
    ``min_cluster_size``, ``orphan_max_gap``, ``fusion_*``) and ``max_stage_seconds`` matter here.  Metrics are added
    when ``metrics`` is true and the scene carries ground truth.
    """
    config = config or scene.config
    timings = dict(scene.timings_ms)
    t0 = time.perf_counter()
    if config.method in SURFACE_METHODS:  # 08-09: evidence between segments -> groups -> 10
        groups = group_by_evidence(scene, embeddings, config)
        seg_label, support = groups.labels, segment_support(groups, config)
        voxel_label, how = evidence_labels(scene, seg_label)
        timings["grouping"] = _ms_since(t0)
        _check_stage_time(timings, config)
        t0 = time.perf_counter()
    else:  # 09: MeanShift on the voxel embeddings -> 10: a vote per segment
        bandwidth = config.bandwidth if config.method == "shadowcorr" else config.baseline_bandwidth
        voxel_label = cluster_voxels(np.asarray(embeddings), bandwidth, config.min_cluster_size)
        timings["clustering"] = _ms_since(t0)
        _check_stage_time(timings, config)
        t0 = time.perf_counter()
        seg_label, support, how = vote(scene, voxel_label, config.orphan_max_gap)
    seg_object, voxel_object, num_objects = number_objects(seg_label, voxel_label)  # 10
    segments = segment_labels(scene, seg_object, support, how)
    objects = object_summaries(scene, seg_object, voxel_object, num_objects)
    timings["assign"] = _ms_since(t0)
    t0 = time.perf_counter()  # 11
    points = _fused_points(scene, seg_object, num_objects)
    if scene.shell_points is not None:  # a scene read back from a training cache carries no shells
        geometry = object_geometry(points, scene.occupancy, seg_object, scene.segment_view, scene.shell_count,
                                   scene.view_poses, scene.unit_scale, scene.config)
        objects = with_geometry(objects, geometry, support, seg_object)
    timings["geometry"] = _ms_since(t0)

    scores = None
    if metrics and scene.segment_truth is not None:
        from .evaluation import score_scene  # evaluation code is loaded only when asked for

        scores = score_scene(scene, seg_object, voxel_object)
    timings["total"] = sum(v for k, v in timings.items() if k != "total")
    result = Result(
        scene=scene.name,
        units=scene.units,
        method=config.method,
        segments=segments,
        objects=objects,
        model=model if config.method in NETWORK_METHODS else None,
        timings_ms={k: round(v, 3) for k, v in timings.items()},
        warnings=list(scene.warnings) + orphan_warnings(scene, how),
        metrics=scores,
        poses=scene.poses,
        config=config.model_dump(mode="json"),
    )
    result._object_points = points
    return result


def _fused_points(scene: VoxelScene, seg_object: np.ndarray, num_objects: int) -> ObjectPoints:
    """Stage 11's fused points from the shells the scene carries (none when it carries no shells)."""
    if scene.shell_points is None:
        return ObjectPoints(np.zeros((0, 3)), np.zeros(0, np.int64), num_objects, scene.units)
    shell_segment = np.repeat(np.arange(scene.num_segments), scene.shell_count)
    return fuse_object_points(scene.shell_points.astype(np.float64), shell_segment, seg_object, num_objects,
                              scene.unit_scale, scene.units, scene.config)


def correspond(
    bundle: SceneBundle,
    model: Model | None = None,
    config: ShadowCorrConfig | None = None,
    *,
    metrics: bool = True,
) -> Result:
    """Label every segment of one scene: ``assign(prepare(bundle), embed(model, [scene])[0])``.

    ``model`` defaults to the packaged default model.  With ``config.method`` ``meanshift``
    or ``projection`` no network runs and no model is loaded.  Metrics are added when
    ``metrics`` is true and the bundle carries ground truth.
    """
    config = config or ShadowCorrConfig()
    scene = prepare(bundle, config)
    if config.method not in NETWORK_METHODS:
        return assign(scene, baseline_embeddings(scene), config, metrics=metrics)
    model = model or load_model()
    t0 = time.perf_counter()
    (embeddings,) = embed(model, [scene])
    scene.timings_ms["network"] = _ms_since(t0)
    _check_stage_time(scene.timings_ms, config)
    return assign(scene, embeddings, config, model=model_info(model), metrics=metrics)


def object_points(bundle: SceneBundle, result: Result) -> ObjectPoints:
    """Each object's fused, deduplicated surface points (bundle units), as stage 11 measured them.

    A result made by this library in this process carries them already; a result read from
    JSON gets them again from ``bundle``: its segments are cut with the result's
    configuration and pose corrections and cleaned (stages 02 and 04), then fused by the
    result's labels.  Raises ``ValueError`` when the bundle's segments are not the result's.
    """
    if result._object_points is not None:
        return result._object_points
    config = ShadowCorrConfig.model_validate(result.config or {})
    bundle = with_pose_corrections(bundle, result)
    segments = extract_segments(bundle, config)
    cut = [(segments.view_names[v], int(i), int(c))
           for v, i, c in zip(segments.view.tolist(), segments.instance.tolist(), segments.component.tolist())]
    if cut != [(s.view, s.instance, s.component) for s in result.segments]:
        raise ValueError(f"the bundle {bundle.name!r} does not cut into the result's segments (scene "
                         f"{result.scene!r}: {len(result.segments)} segments, the bundle: {len(cut)}); export a "
                         "result with the bundle it was computed from")
    segments.pixel_segment = None
    shells = raw_shells(segments) if config.method == "projection" else segment_shells(segments, config)
    seg_object = np.asarray(result.labels, dtype=np.int64)
    points = fuse_object_points(shells.points.astype(np.float32).astype(np.float64), shells.segment, seg_object,
                                len(result.objects), unit_scale(bundle.units, config.units), bundle.units, config)
    result._object_points = points
    return points


def with_pose_corrections(bundle: SceneBundle, result: Result) -> SceneBundle:
    """``bundle`` with the pose corrections ``result`` reports applied (refined pose = correction @ declared)."""
    if not result.poses:
        return bundle
    correction = {p.view: np.asarray(p.correction, dtype=np.float64) for p in result.poses if p.status == "corrected"}
    views = [dataclasses.replace(v, pose=correction[v.name] @ v.pose) if v.name in correction else v
             for v in bundle.views]
    return dataclasses.replace(bundle, views=views)
