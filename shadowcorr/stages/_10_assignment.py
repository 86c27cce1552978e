"""Stage 5: voxel embeddings -> one object label per segment (SPEC §2 steps 11-12).

Voxels are clustered with flat-kernel MeanShift in embedding space; clusters smaller
than ``min_cluster_size`` merge into the nearest larger one.  Each segment then takes
the cluster most of its kept voxels belong to, and ``support`` says how clear that
majority was.  Every segment gets a label, also the few whose voxels were all removed
by the consensus filter: their own unfiltered shadow voxels are placed next to the
nearest kept voxels, which vote instead (and a segment with no 3D point at all becomes
an object of its own) - the result says which way each label was found.
"""

from __future__ import annotations

import time

import numpy as np
from pykdtree.kdtree import KDTree

from .clustering import majority_vote, mean_shift, merge_small_clusters
from .config import NETWORK_METHODS, SURFACE_METHODS, ShadowCorrConfig
from .grouping import SegmentGraph, agglomerate, link_components, segment_confidence
from .metrics import segment_metrics, voxel_ari
from .result import ModelInfo, ObjectSummary, Result, SegmentLabel
from .shadows import segment_max, segment_min
from .volume_evidence import volume_pairs
from .voxel_scene import VoxelScene


def cluster_voxels(embeddings: np.ndarray, bandwidth: float, min_cluster_size: int) -> np.ndarray:
    """MeanShift + small-cluster merge; returns one cluster label per voxel."""
    if embeddings.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    labels, _ = mean_shift(np.ascontiguousarray(embeddings, dtype=np.float32), bandwidth)
    return merge_small_clusters(embeddings, labels, min_size=min_cluster_size)


def group_by_evidence(scene: VoxelScene, embeddings: np.ndarray | None, config: ShadowCorrConfig
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Group label and confidence of every segment from the evidence between segments.

    ``projection`` links segments by cross-view landings alone; ``fused`` adds the network's
    volumetric evidence (``embeddings``) and resolves both by signed average linkage.
    """
    if scene.surface is None:
        raise ValueError(f"method {config.method!r} needs a scene prepared with method {config.method!r} "
                         "(its cross-view surface evidence is missing)")
    s = scene.num_segments
    none = np.zeros(0, dtype=np.int64)
    volume = (none, none, np.zeros(0), np.zeros(0))
    if config.method == "fused":
        volume = volume_pairs(scene, embeddings, config)
    graph = SegmentGraph(scene.segment_view, scene.segment_instance, scene.surface, *volume)
    if config.method == "projection":
        labels = link_components(scene.surface, scene.segment_view, config)
    else:
        labels = agglomerate(graph, config)
    return labels[:s], segment_confidence(graph, labels, config)


def _strongest_member_label(scene: VoxelScene, seg_label: np.ndarray) -> np.ndarray:
    """Each kept voxel takes the label of the segment giving it the most confidence (-1 if none)."""
    out = np.full(scene.num_voxels, -1, dtype=np.int64)
    if scene.member_voxel.size:
        order = np.lexsort((-scene.member_confidence, scene.member_voxel))
        first = order[np.r_[True, scene.member_voxel[order][1:] != scene.member_voxel[order][:-1]]]
        out[scene.member_voxel[first]] = seg_label[scene.member_segment[first]]
    return out


def _label_orphans(scene: VoxelScene, voxel_label: np.ndarray, seg_label: np.ndarray, support: np.ndarray,
                   how: list[str], max_gap: float) -> None:
    """Give a label to segments without kept voxels (modifies the arrays in place).

    The segment's own (unfiltered) shadow voxels that lie within ``max_gap`` voxels of a
    kept voxel take that voxel's cluster, and vote.  A segment whose shadow comes near
    no kept voxel is nowhere near any object the consensus found - typically a rock seen
    from one view only - and becomes an object of its own rather than joining a far one.
    """
    orphans = np.flatnonzero(seg_label < 0)
    if orphans.size == 0:
        return
    next_label = int(max(voxel_label.max(initial=-1), seg_label.max(initial=-1))) + 1
    if scene.num_voxels:
        tree = KDTree(scene.voxel_index.astype(np.float64))
        pick = np.isin(scene.orphan_segment, orphans)
        if pick.any():
            gap, nearest = tree.query(scene.orphan_index[pick].astype(np.float64), k=1)
            near = gap <= max_gap
            lab, sup = majority_vote(voxel_label[nearest[near]], scene.orphan_segment[pick][near], scene.num_segments)
            voted = orphans[lab[orphans] >= 0]
            seg_label[voted] = lab[voted]
            support[voted] = sup[voted]
            for o in voted:
                how[o] = "unfiltered_voxels"
        for o in orphans[seg_label[orphans] < 0]:  # a handful at most: per segment, not per point
            centroid = scene.segment_centroid[o]
            if not np.isin(o, scene.orphan_segment) and np.all(np.isfinite(centroid)):
                gap, nearest = tree.query(np.atleast_2d(centroid / scene.config.voxel_size), k=1)
                gap, nearest = float(gap[0]), int(nearest[0])
                if gap <= max_gap:
                    seg_label[o], support[o], how[o] = voxel_label[nearest], 0.0, "nearest_object"
                    continue
            seg_label[o], support[o], how[o] = next_label, 0.0, "own_object"
            next_label += 1
    else:
        for o in orphans:
            seg_label[o], support[o], how[o] = next_label, 0.0, "own_object"
            next_label += 1


_HOW = {
    "unfiltered_voxels": "labelled by the kept voxels nearest to its own shadow",
    "nearest_object": "labelled by the kept voxel nearest to its centroid",
    "own_object": "given an object of its own",
}


def _orphan_warnings(scene: VoxelScene, how: list[str]) -> list[str]:
    out = []
    with_shadow = set(np.unique(scene.orphan_segment).tolist())
    for o, h in enumerate(how):
        if h in ("vote", "evidence"):
            continue
        if o in with_shadow:
            why = "no surviving voxel"
        elif np.all(np.isfinite(scene.segment_centroid[o])):
            why = "no shadow voxel"
        else:
            why = "no valid 3D point"
        out.append(f"segment {o} (view {scene.view_names[scene.segment_view[o]]}, instance "
                   f"{scene.segment_instance[o]}, component {scene.segment_component[o]}): {why}; {_HOW[h]}")
    return out


def assign(
    scene: VoxelScene,
    embeddings: np.ndarray,
    config: ShadowCorrConfig | None = None,
    *,
    model: ModelInfo | None = None,
    metrics: bool = False,
) -> Result:
    """Cluster the voxel embeddings and label every segment (see the module docstring).

    ``config`` defaults to the configuration the scene was prepared with; only its
    clustering fields (``bandwidth``, ``baseline_bandwidth``, ``min_cluster_size``,
    ``method``) matter here.
    """
    config = config or scene.config
    timings = dict(scene.timings_ms)
    s = scene.num_segments
    if config.method in SURFACE_METHODS:
        t0 = time.perf_counter()
        seg_label, support = group_by_evidence(scene, embeddings, config)
        voxel_label = _strongest_member_label(scene, seg_label)
        # A segment without a single valid 3D point has no evidence: an object of its own.
        how = ["own_object" if n == 0 else "evidence" for n in scene.segment_num_points.tolist()]
        warnings = list(scene.warnings) + _orphan_warnings(scene, how)
        timings["grouping"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
    else:
        t0 = time.perf_counter()
        bandwidth = config.bandwidth if config.method == "shadowcorr" else config.baseline_bandwidth
        voxel_label = cluster_voxels(np.asarray(embeddings), bandwidth, config.min_cluster_size)
        timings["clustering"] = (time.perf_counter() - t0) * 1e3

        t0 = time.perf_counter()
        seg_label, support = majority_vote(voxel_label[scene.member_voxel], scene.member_segment, s)
        seg_label = seg_label.astype(np.int64)
        support = support.astype(np.float64)
        how = ["vote"] * s
        _label_orphans(scene, voxel_label, seg_label, support, how, config.orphan_max_gap)
        warnings = list(scene.warnings) + _orphan_warnings(scene, how)

    # Objects are numbered 0..K-1 in order of their first segment; clusters no segment
    # chose map to -1.
    _, first = np.unique(seg_label, return_index=True)
    used = seg_label[np.sort(first)]
    object_of_cluster = np.full(int(max(seg_label.max(initial=-1), voxel_label.max(initial=-1))) + 2, -1, np.int64)
    object_of_cluster[used] = np.arange(used.size)
    seg_object = object_of_cluster[seg_label]
    voxel_object = object_of_cluster[voxel_label]  # label -1 reads the last slot, which stays -1

    segments = [
        SegmentLabel(
            segment=i,
            view=scene.view_names[scene.segment_view[i]],
            instance=int(scene.segment_instance[i]),
            component=int(scene.segment_component[i]),
            num_points=int(scene.segment_num_points[i]),
            object=int(seg_object[i]),
            support=round(float(support[i]), 4),
            assignment=how[i],
        )
        for i in range(s)
    ]
    objects = _object_summaries(scene, seg_object, voxel_object, used.size)
    timings["assign"] = (time.perf_counter() - t0) * 1e3

    result_metrics = None
    if metrics and scene.segment_truth is not None:
        result_metrics = evaluate(scene, seg_object, voxel_object)
    timings["total"] = sum(v for k, v in timings.items() if k != "total")
    return Result(
        scene=scene.name,
        units=scene.units,
        method=config.method,
        segments=segments,
        objects=objects,
        model=model if config.method in NETWORK_METHODS else None,
        timings_ms={k: round(v, 3) for k, v in timings.items()},
        warnings=warnings,
        metrics=result_metrics,
        poses=scene.poses,
        config=config.model_dump(mode="json"),
    )


def _object_summaries(scene: VoxelScene, seg_object: np.ndarray, voxel_object: np.ndarray, k: int) -> list[ObjectSummary]:
    """Per object its segments, views, centroid and bounding box (bundle units).

    One sort of the voxels by object and one of the segments: the cost follows the voxel and
    segment counts, never objects times voxels.
    """
    to_bundle = 1.0 / scene.unit_scale
    half = scene.config.voxel_size / 2.0
    labelled = np.flatnonzero(voxel_object >= 0)
    order = labelled[np.argsort(voxel_object[labelled], kind="stable")]
    vox_obj, pos = voxel_object[order], scene.positions[order]
    n_vox = np.bincount(vox_obj, minlength=k)
    # (bincount of no voxels at all returns integers: divide, do not divide in place)
    vox_sum = np.stack([np.bincount(vox_obj, weights=pos[:, i], minlength=k) for i in range(3)], axis=1)
    vox_centroid = vox_sum / np.maximum(n_vox, 1)[:, None]
    vox_lo = segment_min(pos, vox_obj, k, empty=np.nan) - half
    vox_hi = segment_max(pos, vox_obj, k, empty=np.nan) + half
    seg_order = np.argsort(seg_object, kind="stable")
    segs_of = np.split(seg_order, np.cumsum(np.bincount(seg_object, minlength=k))[:-1])

    def fmt(a: np.ndarray | None) -> list[float] | None:
        return None if a is None else [round(float(x) * to_bundle, 4) for x in a]

    out = []
    for obj in range(k):  # one iteration per object, each touching only its own segments
        segs = segs_of[obj]
        if n_vox[obj]:
            centroid, lo, hi = vox_centroid[obj], vox_lo[obj], vox_hi[obj]
        else:
            c = scene.segment_centroid[segs]
            ok = np.all(np.isfinite(c), axis=1)
            if ok.any():
                weights = scene.segment_num_points[segs][ok].astype(np.float64)
                centroid = (c[ok] * weights[:, None]).sum(axis=0) / max(weights.sum(), 1.0)
                lo = np.nanmin(scene.segment_bbox_min[segs][ok], axis=0)
                hi = np.nanmax(scene.segment_bbox_max[segs][ok], axis=0)
            else:
                centroid = lo = hi = None
        out.append(
            ObjectSummary(
                object=obj,
                segments=segs.tolist(),
                views=sorted({scene.view_names[scene.segment_view[i]] for i in segs}),
                centroid=fmt(centroid),
                bbox_min=fmt(lo),
                bbox_max=fmt(hi),
                num_voxels=int(n_vox[obj]),
            )
        )
    return out


def voxel_truth(scene: VoxelScene) -> np.ndarray:
    """Ground-truth object per kept voxel: the object whose segments give it the most confidence.

    For metrics and training targets only; never an input feature.  Sparse: confidence is
    summed per (voxel, object) pair that occurs, so the cost follows the memberships rather
    than voxels times objects.
    """
    if scene.num_voxels == 0:
        return np.zeros(0, dtype=np.int64)
    truth = scene.segment_truth[scene.member_segment]
    objects, obj_idx = np.unique(truth, return_inverse=True)
    pair, pair_of_member = np.unique(scene.member_voxel * objects.size + obj_idx, return_inverse=True)
    score = np.bincount(pair_of_member, weights=scene.member_confidence, minlength=pair.size)
    voxel, obj = np.divmod(pair, objects.size)
    # Per voxel the highest score wins; ties go to the lowest object index (as argmax did).
    order = np.lexsort((obj, -score, voxel))
    first = order[np.r_[True, voxel[order][1:] != voxel[order][:-1]]]
    out = np.zeros(scene.num_voxels, dtype=np.int64)
    out[voxel[first]] = objects[obj[first]]
    return out


def evaluate(scene: VoxelScene, seg_object: np.ndarray, voxel_object: np.ndarray) -> dict[str, float | int]:
    """Segment-level purities (SPEC §5), voxel ARI and coverage against the scene's ground truth."""
    m = dict(segment_metrics(scene.segment_truth, seg_object))
    if scene.num_voxels:
        m["voxel_ari"] = float(voxel_ari(voxel_truth(scene), voxel_object))
    return m
