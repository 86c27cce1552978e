"""Stage 10: cluster or group labels -> one object per segment, and the objects (SPEC §2 step 12).

Under ``shadowcorr`` and ``meanshift`` each segment takes the cluster most of its kept
voxels belong to (:func:`vote`), and ``support`` says how clear that majority was.  Every
segment gets a label, also the few whose voxels were all removed by the consensus filter:
their own unfiltered shadow voxels are placed next to the nearest kept voxels, which vote
instead (and a segment with no 3D point at all becomes an object of its own) - the result
says which way each label was found.  Under ``fused`` and ``projection`` the segments are
already grouped (stage 9); each kept voxel takes the group of the segment that gives it the
most confidence (:func:`label_voxels_by_segment`).

Objects are then numbered in order of their first segment (:func:`number_objects`) and
summarised (:func:`segment_labels`, :func:`object_summaries`).  Nothing here reads ground
truth; scoring against it lives in :mod:`shadowcorr.evaluation`.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from ..ops import segment_max, segment_min
from ..result import ObjectSummary, SegmentLabel
from ._06_voxel_scene import VoxelScene
from ._09_clustering import majority_vote


def evidence_labels(scene: VoxelScene, seg_label: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Voxel labels and how each segment was labelled, for segments grouped by evidence.

    A segment without a single valid 3D point has no surface or volume evidence of its own.
    Alone in its group it is an object of its own (``own_object``); in a group with a blob of
    its own mask (same view, same mask value) ``same_mask`` (under ``fused`` the same-mask
    constraint joins them); in a group without one, ``evidence`` (other views landed on it).
    """
    how = np.where(scene.segment_num_points == 0, "own_object", "evidence").astype(object)
    empty = np.flatnonzero(scene.segment_num_points == 0)
    if empty.size:
        _, group, size = np.unique(seg_label, return_inverse=True, return_counts=True)
        mask_key = scene.segment_view.astype(np.int64) * (int(scene.segment_instance.max()) + 1) + scene.segment_instance
        _, blobs_of_mask_in_group = np.unique(group * (int(mask_key.max()) + 1) + mask_key, return_inverse=True)
        siblings = np.bincount(blobs_of_mask_in_group)[blobs_of_mask_in_group] - 1
        grouped = size[group[empty]] > 1
        how[empty[grouped]] = np.where(siblings[empty[grouped]] > 0, "same_mask", "evidence")
    return label_voxels_by_segment(scene, seg_label), how.tolist()


def vote(scene: VoxelScene, voxel_label: np.ndarray, max_gap: float) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Label, support and how it was found for every segment, from the cluster label of every kept voxel."""
    s = scene.num_segments
    seg_label, support = majority_vote(voxel_label[scene.member_voxel], scene.member_segment, s)
    seg_label = seg_label.astype(np.int64)
    support = support.astype(np.float64)
    how = ["vote"] * s
    _label_orphans(scene, voxel_label, seg_label, support, how, max_gap)
    return seg_label, support, how


def number_objects(seg_label: np.ndarray, voxel_label: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Objects numbered 0..K-1 in order of their first segment: (per segment, per voxel, K).

    Clusters no segment chose map to -1.
    """
    _, first = np.unique(seg_label, return_index=True)
    used = seg_label[np.sort(first)]
    object_of_cluster = np.full(int(max(seg_label.max(initial=-1), voxel_label.max(initial=-1))) + 2, -1, np.int64)
    object_of_cluster[used] = np.arange(used.size)
    # label -1 reads the last slot, which stays -1
    return object_of_cluster[seg_label], object_of_cluster[voxel_label], int(used.size)


def segment_labels(scene: VoxelScene, seg_object: np.ndarray, support: np.ndarray, how: list[str]) -> list[SegmentLabel]:
    """One result row per segment."""
    return [
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
        for i in range(scene.num_segments)
    ]


def label_voxels_by_segment(scene: VoxelScene, seg_label: np.ndarray) -> np.ndarray:
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
    "same_mask": "joined the other blobs of its mask",
}


def orphan_warnings(scene: VoxelScene, how: list[str]) -> list[str]:
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


def object_summaries(scene: VoxelScene, seg_object: np.ndarray, voxel_object: np.ndarray, k: int) -> list[ObjectSummary]:
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
