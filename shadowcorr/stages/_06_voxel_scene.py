"""Stage 6: shadows of all segments -> one voxel scene with network inputs (SPEC §2 steps 7-9).

Every voxel of the shared grid keeps the set of segments whose shadows reach it and
the summed confidence gamma.  Voxels below the ``gamma_percentile``-th percentile of
gamma are dropped: what survives is where shadows agree.  Per surviving voxel the
network gets 16 numbers: gamma min-max normalised over the scene, the voxel position
centred on the scene's bounding-box centre and divided by half its largest extent,
and the voxel's segment-id embedding (step 8).

Nothing here reads ground truth: ``VoxelScene.segment_truth`` is carried along for
metrics only and no feature is computed from it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..config import ShadowCorrConfig
from ..errors import SceneLimitError
from ..ops import pack_cell_keys, segment_max, segment_min, unique_keys
from ..result import ViewPoseCorrection
from ._02_segments import Segments
from ._03_surface_evidence import SurfaceEvidence
from ._04_shells import SegmentShells
from ._05_occupancy import ShadowOccupancy
from ._05_shadows import ShadowVoxels
from ._06_segment_embedding import cooccurrence, train_segment_embeddings, voxel_embeddings


@dataclass
class VoxelScene:
    """Everything later stages need, as plain numpy arrays (cheap to send between processes).

    Lengths are in the configuration's units (``config.units``); ``unit_scale`` converts
    bundle units to them.
    """

    name: str
    units: str  # the bundle's units
    unit_scale: float  # bundle units -> config units
    config: ShadowCorrConfig
    view_names: list[str]
    # per segment (S)
    segment_view: np.ndarray
    segment_instance: np.ndarray
    segment_component: np.ndarray
    segment_num_points: np.ndarray  # back-projected points before clean-up
    segment_centroid: np.ndarray  # (S, 3) mean of the cleaned points (config units); NaN if none
    segment_bbox_min: np.ndarray  # (S, 3)
    segment_bbox_max: np.ndarray  # (S, 3)
    segment_truth: np.ndarray | None  # ground truth for metrics only
    # per kept voxel (V)
    voxel_index: np.ndarray  # (V, 3) int64 grid index; centre = index * voxel_size
    gamma: np.ndarray  # (V,)
    features: np.ndarray  # (V, 16) float32 network input
    # kept (voxel, segment, confidence) memberships (M)
    member_voxel: np.ndarray
    member_segment: np.ndarray
    member_confidence: np.ndarray
    # shadow voxels of segments that have no kept voxel (fallback assignment)
    orphan_segment: np.ndarray
    orphan_index: np.ndarray  # (K, 3) int64
    warnings: list[str] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)
    # cross-view surface evidence (methods 'projection' and 'fused'); None otherwise
    surface: SurfaceEvidence | None = None
    poses: list[ViewPoseCorrection] | None = None  # pose refinement report, when it ran
    # each segment's cleaned points (stage 04), float32, sorted by segment, for the objects' geometry (stage 11)
    shell_points: np.ndarray | None = None  # (P, 3) config units
    shell_count: np.ndarray | None = None  # (S,)
    # the solid share of the shadow voxels (stage 05 occupancy); None when no shadow was cast or no depth image read
    occupancy: ShadowOccupancy | None = None
    view_poses: np.ndarray | None = None  # (V, 4, 4) camera-to-world poses of the views (refined where refined)
    # (S,) the blob a segment was cut from at a depth step, shared by its pieces (stage 02, Segments.cut); None: no cut
    segment_cut: np.ndarray | None = None

    @property
    def num_segments(self) -> int:
        return int(self.segment_view.shape[0])

    @property
    def num_voxels(self) -> int:
        return int(self.voxel_index.shape[0])

    @property
    def positions(self) -> np.ndarray:
        return self.voxel_index * self.config.voxel_size


def build_voxel_scene(
    name: str,
    units: str,
    unit_scale: float,
    segments: Segments,
    shells: SegmentShells,
    shadows: ShadowVoxels,
    config: ShadowCorrConfig,
    timings_ms: dict[str, float] | None = None,
) -> VoxelScene:
    """Steps 7-9: consensus filter, segment-id embeddings, network features."""
    s = segments.num_segments
    timings_ms = dict(timings_ms or {})
    t0 = time.perf_counter()

    key, unpack = pack_cell_keys(np.zeros_like(shadows.segment), shadows.cell)
    uniq, voxel_of_member = unique_keys(key, return_inverse=True)
    gamma_all = np.bincount(voxel_of_member, weights=shadows.confidence, minlength=uniq.size)
    if uniq.size:
        threshold = np.percentile(gamma_all, config.gamma_percentile)
        kept = gamma_all >= threshold
    else:
        kept = np.zeros(0, dtype=bool)
    new_id = np.cumsum(kept) - 1
    member_kept = kept[voxel_of_member]
    member_voxel = new_id[voxel_of_member[member_kept]]
    member_segment = shadows.segment[member_kept]
    member_conf = shadows.confidence[member_kept]
    v = int(np.count_nonzero(kept))
    if v > config.max_voxels:
        raise SceneLimitError("max_voxels", v, config.max_voxels)
    voxel_index = unpack(uniq[kept])[1]
    gamma = gamma_all[kept]

    # Segments left without a kept voxel are labelled in `assign` from their own shadow.
    orphan_member = ~np.isin(shadows.segment, np.unique(member_segment))
    timings_ms["consensus"] = (time.perf_counter() - t0) * 1e3

    t0 = time.perf_counter()
    centroid = np.where(shells.count[:, None] > 0, shells.mean, np.nan)
    canon = np.where(np.isfinite(centroid), centroid, 0.0)
    cooc = cooccurrence(member_voxel, member_segment, v, s)
    seg_vectors = train_segment_embeddings(cooc, canon, config)
    emb = voxel_embeddings(member_voxel, member_segment, v, seg_vectors)
    timings_ms["segment_embedding"] = (time.perf_counter() - t0) * 1e3

    t0 = time.perf_counter()
    features = np.zeros((v, config.feature_dim), dtype=np.float32)
    if v:
        span = gamma.max() - gamma.min()
        features[:, 0] = (gamma - gamma.min()) / span if span > 0 else 1.0
        pos = voxel_index * config.voxel_size
        lo, hi = pos.min(axis=0), pos.max(axis=0)
        half = max(float((hi - lo).max()) / 2.0, 1e-9)
        features[:, 1:4] = (pos - (lo + hi) / 2.0) / half
        features[:, 4:] = emb

    bbox_min = segment_min(shells.points, shells.segment, s, empty=np.nan)
    bbox_max = segment_max(shells.points, shells.segment, s, empty=np.nan)
    timings_ms["features"] = (time.perf_counter() - t0) * 1e3

    return VoxelScene(
        name=name,
        units=units,
        unit_scale=unit_scale,
        config=config,
        view_names=list(segments.view_names),
        segment_view=segments.view,
        segment_instance=segments.instance,
        segment_component=segments.component,
        segment_cut=segments.cut,
        segment_num_points=segments.lengths,
        segment_centroid=centroid,
        segment_bbox_min=bbox_min,
        segment_bbox_max=bbox_max,
        segment_truth=segments.truth,
        voxel_index=voxel_index,
        gamma=gamma,
        features=features,
        member_voxel=member_voxel,
        member_segment=member_segment,
        member_confidence=member_conf,
        orphan_segment=shadows.segment[orphan_member],
        orphan_index=shadows.cell[orphan_member],
        timings_ms=timings_ms,
        shell_points=shells.points.astype(np.float32),
        shell_count=shells.count,
    )
