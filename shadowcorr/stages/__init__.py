"""The pipeline's stages, one module per stage, numbered in the order they run.

::

    01 poses             SceneBundle -> SceneBundle with corrected poses   (optional: refine_poses)
    01 mask_alignment    views + masks -> poses of the unregistered views turned onto the others' masks
    02 segments          SceneBundle -> Segments: one 3D point shell per mask blob
    03 surface_evidence  Segments -> SurfaceEvidence: where each segment lands in the other views
    03 seams             Segments + depth images -> Seams: neighbours of one view on one smooth surface
    04 shells            Segments -> SegmentShells: cleaned points, error ellipsoid, viewing direction
    05 shadows           SegmentShells -> ShadowVoxels: confidence-weighted voxels behind each shell
    05 occupancy         ShadowVoxels + depth images -> ShadowOccupancy: the solid share of each shadow voxel
    06 voxel_scene       ShadowVoxels -> VoxelScene: consensus voxels, segment-id embeddings, features
    07 network           VoxelScene -> per-voxel embeddings (the model is in shadowcorr.nn)
    08 volume_evidence   embeddings -> evidence between segments whose shadows meet
    09 grouping          surface + volume evidence -> groups of segments   (fused, projection)
    09 clustering        embeddings -> voxel clusters (MeanShift)          (shadowcorr, meanshift)
    10 assignment        groups or clusters -> one object per segment, object summaries
    11 geometry          objects -> fused points, oriented box, volume, seen extent per object

Stage 03 runs beside 04-06 (methods ``fused`` and ``projection``); the two stages 09 are
alternatives, chosen by ``ShadowCorrConfig.method``.  :mod:`shadowcorr.pipeline` composes
them.  Every stage works on a ragged batch: all segments (or voxels) of a scene in flat
arrays with explicit lengths, never a Python loop per point.  No stage reads ground truth.

The modules are private; the names below are what the stages offer.  They are imported
lazily, so that importing one stage does not load torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

_EXPORTS = {
    # 01 poses
    "refine_poses": "_01_poses",
    "pose_warnings": "_01_poses",
    "unverified_poses": "_01_poses",
    "align_to_masks": "_01_mask_alignment",
    # 02 segments
    "Segments": "_02_segments",
    "Blobs": "_02_segments",
    "SegmentImage": "_02_segments",
    "find_blobs": "_02_segments",
    "cut_at_depth_steps": "_02_segments",
    "view_blobs": "_02_segments",
    "back_project": "_02_segments",
    "extract_segments": "_02_segments",
    "check_valid_depth": "_02_segments",
    # 03 surface evidence
    "SurfaceEvidence": "_03_surface_evidence",
    "sample_segment_points": "_03_surface_evidence",
    "surface_evidence": "_03_surface_evidence",
    "Seams": "_03_seams",
    "smooth_seams": "_03_seams",
    # 04 shells
    "SegmentShells": "_04_shells",
    "voxel_downsample": "_04_shells",
    "remove_statistical_outliers": "_04_shells",
    "segment_shells": "_04_shells",
    "raw_shells": "_04_shells",
    # 05 shadows
    "ShadowVoxels": "_05_shadows",
    "beta_profile": "_05_shadows",
    "cast_shadows": "_05_shadows",
    # 05 occupancy
    "ShadowOccupancy": "_05_occupancy",
    "shadow_occupancy": "_05_occupancy",
    # 06 voxel scene
    "VoxelScene": "_06_voxel_scene",
    "build_voxel_scene": "_06_voxel_scene",
    "cooccurrence": "_06_segment_embedding",
    "segment_embedding_loss": "_06_segment_embedding",
    "train_segment_embeddings": "_06_segment_embedding",
    # 07 network
    "baseline_embeddings": "_07_network",
    "check_compatible": "_07_network",
    "embed": "_07_network",
    "model_info": "_07_network",
    # 08 volume evidence
    "segment_embeddings": "_08_volume_evidence",
    "volume_pairs": "_08_volume_evidence",
    # 09 grouping / clustering
    "SegmentGraph": "_09_grouping",
    "agglomerate": "_09_grouping",
    "group_by_evidence": "_09_grouping",
    "link_components": "_09_grouping",
    "merged_mask_segments": "_09_grouping",
    "join_isolated": "_09_grouping",
    "join_lone_pieces": "_09_grouping",
    "join_nearest_surface": "_09_grouping",
    "segment_confidence": "_09_grouping",
    "EvidenceGroups": "_09_grouping",
    "SUPPORT_FEATURES": "_09_support",
    "SupportCalibration": "_09_support",
    "SupportTrees": "_09_support",
    "segment_support": "_09_support",
    "support_calibration": "_09_support",
    "support_features": "_09_support",
    "split_mask_ids": "_09_grouping",
    "thin_cover_pairs": "_09_grouping",
    "without_landings": "_09_grouping",
    "without_landings_on": "_09_grouping",
    "cluster_voxels": "_09_clustering",
    "majority_vote": "_09_clustering",
    "mean_shift": "_09_clustering",
    "merge_small_clusters": "_09_clustering",
    # 10 assignment
    "evidence_labels": "_10_assignment",
    "number_objects": "_10_assignment",
    "object_summaries": "_10_assignment",
    "orphan_warnings": "_10_assignment",
    "segment_labels": "_10_assignment",
    "vote": "_10_assignment",
    # 11 geometry
    "ObjectGeometry": "_11_geometry",
    "ObjectPoints": "_11_geometry",
    "fuse_object_points": "_11_geometry",
    "object_geometry": "_11_geometry",
    "object_volumes": "_11_geometry",
    "oriented_boxes": "_11_geometry",
    "with_geometry": "_11_geometry",
}

__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from ._01_mask_alignment import align_to_masks
    from ._01_poses import pose_warnings, refine_poses, unverified_poses
    from ._02_segments import (Blobs, SegmentImage, Segments, back_project, check_valid_depth, cut_at_depth_steps,
                               extract_segments, find_blobs, view_blobs)
    from ._03_seams import Seams, smooth_seams
    from ._03_surface_evidence import SurfaceEvidence, sample_segment_points, surface_evidence
    from ._04_shells import SegmentShells, raw_shells, remove_statistical_outliers, segment_shells, voxel_downsample
    from ._05_occupancy import ShadowOccupancy, shadow_occupancy
    from ._05_shadows import ShadowVoxels, beta_profile, cast_shadows
    from ._06_segment_embedding import cooccurrence, segment_embedding_loss, train_segment_embeddings
    from ._06_voxel_scene import VoxelScene, build_voxel_scene
    from ._07_network import baseline_embeddings, check_compatible, embed, model_info
    from ._08_volume_evidence import segment_embeddings, volume_pairs
    from ._09_clustering import cluster_voxels, majority_vote, mean_shift, merge_small_clusters
    from ._09_grouping import (
        EvidenceGroups, SegmentGraph, agglomerate, group_by_evidence, join_isolated, join_lone_pieces,
        join_nearest_surface, link_components, merged_mask_segments, segment_confidence, split_mask_ids,
        thin_cover_pairs, without_landings, without_landings_on,
    )
    from ._09_support import (SUPPORT_FEATURES, SupportCalibration, SupportTrees, segment_support, support_calibration,
                              support_features)
    from ._10_assignment import (
        evidence_labels, number_objects, object_summaries, orphan_warnings, segment_labels, vote,
    )
    from ._11_geometry import (
        ObjectGeometry, ObjectPoints, fuse_object_points, object_geometry, object_volumes, oriented_boxes, with_geometry,
    )
