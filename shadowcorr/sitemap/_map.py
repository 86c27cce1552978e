"""``SiteMap``: a map of a site's objects that grows scan by scan, with stable ids and a history."""

from __future__ import annotations

import dataclasses
import json
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..bundle import SceneBundle, View, unit_scale
from ..config import ShadowCorrConfig
from ..nn import Model, load_model
from ..pipeline import cut_segments, embed, prepare_segments
from ..result import ViewPoseCorrection
from ..stages import (Segments, VoxelScene, group_by_evidence, pose_warnings, refine_poses, segment_support,
                      support_features, unverified_poses)
from ._linking import (FOOTPRINT_MARGIN_VOXELS, corrected_report, footprints, rank_views, registered_corrections,
                       revisits)
from ._models import MapEvent, MapObject, MapScan, MapSegment, MapState, MapUpdate, MapViewRef
from ._revision import revise
from ._store import CELL_VOXELS, MapConflictError, MapStore, cell_keys, unpack_array
from ._summaries import StoredViews, ViewSummary, join_segments, segment_points, stored_views, summarize_views

__all__ = ["ScanPlan", "SiteMap", "add_to_map"]

#: Settings that only say how a computation runs or what it may cost, not what it computes: they
#: may differ from the map's own.
_RUNTIME_FIELDS = frozenset({"num_threads", "max_stage_seconds", "max_segments", "max_voxels"})


@dataclass
class MovedView:
    """A stored view whose pose a new scan's registration corrects, and its segments' points moved along."""

    view: int  # map id
    pose: np.ndarray  # (4, 4) the corrected pose
    lo: np.ndarray | None  # its new footprint
    hi: np.ndarray | None
    segments: np.ndarray  # map ids of its segments
    points: list[np.ndarray]  # their points, moved


@dataclass
class ScanPlan:
    """A scan prepared for the map: the linking run's voxel scene and what the map will store.

    Plain data (picklable): the HTTP service prepares it in one worker process, embeds it in
    the inference thread and commits it in another.
    """

    name: str
    map_scan: int  # the map's last scan when it was prepared: a commit on a changed map is refused
    scene: VoxelScene  # the new segments first, then the stored segments of the linked views
    num_new: int
    new_view: np.ndarray  # (num_new,) view index of each new segment
    new_instance: np.ndarray
    new_component: np.ndarray
    new_pixels: np.ndarray
    new_cut: np.ndarray  # (num_new,) the blob of its view a depth step cut it from (-1: none)
    new_points: list[np.ndarray]  # what the map keeps of each new segment
    summaries: list[ViewSummary]
    stored_segments: np.ndarray  # map ids of the stored segments in the scene
    stored_objects: np.ndarray  # their objects when prepared
    linked_views: list[MapViewRef]
    repeats: np.ndarray  # (num_new,) the object of the stored segment each new one repeats (-1: none)
    seen_by: np.ndarray  # (stored segments, fresh views) bool: the scan's view sees the stored segment
    fresh_views: list[str]  # the scan's views that repeat no stored view
    revisited_views: list[MapViewRef]  # stored views the scan repeats (left out of the run)
    poses: list[ViewPoseCorrection] | None
    moved_views: list[MovedView]  # stored views whose pose the scan's registration corrected
    warnings: list[str] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)


class SiteMap:
    """A site's objects, kept in one SQLite file, revised scan by scan.

    Each :meth:`add` links a new scan (a bundle of views) to the map's views that see the same
    ground - found by their footprints and frusta, at most ``max_linked_views`` of them - and
    runs the ``fused`` method's evidence over the scan's segments and the linked views' stored
    segments together: the scan's views and the stored views (read back from their summaries:
    coarse depth and segment images, points on the downsampling grid) are registered
    together when ``refine_poses`` is on (from their declared poses, as one run of them would
    be; stored views move with their segments), every segment lands in
    the other views (surface evidence), their shadows meet in one voxel grid (volumetric
    evidence through the network), and the per-view constraints apply.  The run's groups are
    then read against the map's objects: the scan's segments take the ids of the objects they
    join, and a stored segment changes object only where the scan brings new evidence about it -
    its group holds new segments, or a view of the scan sees it - and, where ``min_margin`` is set,
    its evidence margin exceeds it (``shadowcorr.sitemap._revision`` has the rules).  Every revision is an event -
    ``created``, ``observed``, ``merged``, ``split``, ``retired`` - naming the scan, views and
    segments that caused it and the weakest evidence margin among them.  One update is one
    transaction: a writer killed mid-update leaves the map as the last update left it.

    ``path``: the map file, created when absent (``create=False`` refuses a missing one).
    ``config``: the method's settings (``fused``); a new map stores them, an existing one keeps
    its own (a ``config`` that sets anything but run-time limits and threads to another value is
    refused).
    ``model``: the network; the packaged model by default, loaded on the first update.
    ``min_margin``: None (the default) lets a stored segment follow the run wherever the scan
    brings new evidence about it, as one run of all the views would place it; a number keeps a
    stored segment whose evidence margin in the run does not exceed it where it is (fewer id
    changes, at the cost of agreeing less with that one run).
    ``wait_s``: how long :meth:`add` waits for another writer before :class:`MapBusyError`.
    """

    def __init__(self, path: str | Path, config: ShadowCorrConfig | None = None, *, model: Model | None = None,
                 create: bool = True, max_linked_views: int = 32, min_margin: float | None = None,
                 wait_s: float = 0.0):
        if not isinstance(max_linked_views, int) or max_linked_views < 1:
            raise ValueError(f"max_linked_views must be a whole number >= 1, got {max_linked_views!r}")
        if min_margin is not None and not np.isfinite(min_margin):
            raise ValueError(f"min_margin must be finite or None, got {min_margin!r}")
        if wait_s < 0:
            raise ValueError(f"wait_s must be >= 0, got {wait_s!r}")
        if config is not None and config.method != "fused":
            raise ValueError(f"a site map links scans with the 'fused' method's evidence, not {config.method!r}")
        self.max_linked_views = max_linked_views
        self.min_margin = None if min_margin is None else float(min_margin)
        self.wait_s = float(wait_s)
        self._model = model
        self._store = MapStore(path, create=create)
        try:
            self.config = self._settle_config(config)
        except Exception:
            self._store.close()
            raise

    def _settle_config(self, config: ShadowCorrConfig | None) -> ShadowCorrConfig:
        """The map's configuration: stored with a new map; an existing map's own, with the run-time
        settings of ``config``.  Settings ``config`` sets explicitly must agree with the map's."""
        stored = self._store.meta("config")
        if stored is None:
            with self._store.writing(wait_s=max(self.wait_s, 5.0)):
                if self._store.meta("config") is None:
                    self._store.set_meta("config", (config or ShadowCorrConfig()).model_dump_json())
            stored = self._store.meta("config")
        mine = ShadowCorrConfig.model_validate_json(stored)
        if config is None:
            return mine
        differ = sorted(k for k in config.model_fields_set - _RUNTIME_FIELDS if getattr(mine, k) != getattr(config, k))
        if differ:
            raise ValueError(f"{self.path}: the map was made with other settings ({', '.join(differ)}); open it "
                             "without them, or with the map's own")
        return mine.with_options(**{k: getattr(config, k) for k in _RUNTIME_FIELDS & config.model_fields_set})

    # ------------------------------------------------------------------ basics
    @property
    def path(self) -> Path:
        return self._store.path

    @property
    def units(self) -> str:
        return self.config.units

    def close(self) -> None:
        self._store.close()

    def __enter__(self) -> "SiteMap":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def model(self) -> Model:
        if self._model is None:
            self._model = load_model()
        return self._model

    # ------------------------------------------------------------------ updates
    def add(self, bundle: SceneBundle, name: str | None = None) -> MapUpdate:
        """Add one scan: link it to the map, revise the objects, record the events (one transaction)."""
        t0 = time.perf_counter()
        with self._store.writing(wait_s=self.wait_s):
            plan = self.prepare_scan(bundle, name)
            t1 = time.perf_counter()
            (embeddings,) = embed(self.model, [plan.scene])
            plan.timings_ms["network"] = (time.perf_counter() - t1) * 1e3
            update = self.commit_scan(plan, embeddings, model_sha256=self.model.sha256)
        update.timings_ms["total"] = round((time.perf_counter() - t0) * 1e3, 3)
        return update

    def prepare_scan(self, bundle: SceneBundle, name: str | None = None) -> ScanPlan:
        """Everything of :meth:`add` before the network: cut the scan, link it, build the run's voxel scene.

        Reads one snapshot of the map; :meth:`commit_scan` refuses the plan if the map has
        changed since (:class:`MapConflictError`).
        """
        config = self.config
        timings: dict[str, float] = {}
        _check_views(bundle)
        local = _in_map_units(bundle, config)
        new, depth_warnings = cut_segments(local, config, timings)
        t0 = time.perf_counter()
        with self._store.reading():
            map_scan = self._store.last_scan()
            linked = self._linked_views(local, new)
            stored = stored_views(self._store.view_rows(linked), self._store.segment_rows(linked)) if linked else None
        timings["map_read"] = (time.perf_counter() - t0) * 1e3
        poses, stored_moves = None, []
        declared = [v.pose for v in local.views]
        if config.refine_poses:
            t0 = time.perf_counter()
            local, new, poses, stored_moves = _register(local, new, stored, config)
            timings["poses"] = (time.perf_counter() - t0) * 1e3
        moved_views = _stored_moves(stored, stored_moves)
        images = list(new.pixel_segment or [])
        summaries = summarize_views(local, new, images, config.max_depth, declared, config.pose_depth_window)
        points = segment_points(new, config.downsample_size)
        repeats, revisited, repeating = np.full(new.num_segments, -1, dtype=np.int64), [], []
        if stored is not None:
            twins, repeating, repeats = revisits(summaries, new.view, stored, config.voxel_size)
            revisited = [MapViewRef(scan=int(stored.view_scans[w]), view=stored.view_names[w]) for w in twins]
            stored = stored.subset([w for w in range(len(stored.views)) if w not in twins])
        # The scan's views whose poses the registration could not bear out (its reports come first); the
        # stored views count as borne out.
        unverified = None if poses is None else unverified_poses(poses[:len(local.views)])
        if stored is not None:
            run = SceneBundle(units=config.units, views=[*local.views, *stored.views], name=local.name)
            if unverified is not None:
                unverified = np.r_[unverified, np.zeros(len(stored.views), dtype=bool)]
            scene = prepare_segments(run, join_segments(new, stored.segments), config, timings, unverified)
        else:
            scene = prepare_segments(local, new, config, timings, unverified)
        # Which stored segments the scan's own views see (their surface is visible there): the
        # scan is new evidence about them.  A view that repeats a stored one is not.
        fresh = [j for j in range(len(local.views)) if j not in repeating]
        seen_by = (scene.surface.visible[new.num_segments:, fresh] > 0 if scene.surface is not None and fresh
                   else np.zeros((scene.num_segments - new.num_segments, len(fresh)), dtype=bool))
        return ScanPlan(
            name=name or bundle.name, map_scan=map_scan, scene=scene, num_new=new.num_segments,
            new_view=new.view.copy(), new_instance=new.instance.copy(), new_component=new.component.copy(),
            new_pixels=new.num_pixels.copy(),
            new_cut=np.full(new.num_segments, -1, np.int64) if new.cut is None else new.cut.copy(),
            new_points=points, summaries=summaries,
            stored_segments=stored.segment_ids if stored else np.zeros(0, np.int64),
            stored_objects=stored.segment_objects if stored else np.zeros(0, np.int64),
            linked_views=[MapViewRef(scan=int(s), view=v) for s, v in zip(stored.view_scans, stored.view_names)]
            if stored else [],
            repeats=repeats,
            seen_by=seen_by,
            fresh_views=[local.views[j].name for j in fresh],
            revisited_views=revisited,
            poses=poses,
            moved_views=moved_views,
            warnings=depth_warnings + list(bundle.warnings) + (pose_warnings(poses) if poses else []),
            timings_ms=timings,
        )

    def _linked_views(self, local: SceneBundle, new) -> list[int]:
        """Stored views that see the ground of the new views (see ``_linking``)."""
        config = self.config
        boxes = footprints(new.points, new.view, new.lengths, len(local.views))
        margin = FOOTPRINT_MARGIN_VOXELS * config.voxel_size
        keys = [cell_keys(lo - margin, hi + margin, CELL_VOXELS * config.voxel_size) for lo, hi in filter(None, boxes)]
        if not keys:
            return []
        candidates = self._store.views_in_cells(np.concatenate(keys))
        if not candidates:
            return []
        cams = {r["view"]: _camera(r) for r in self._store.view_rows(candidates, with_images=False)}
        centroids: dict[int, list] = {}
        for r in self._store.segment_rows(candidates, with_points=False):
            if r["cx"] is not None:
                centroids.setdefault(r["view"], []).append((r["cx"], r["cy"], r["cz"]))
        new_centroids = np.stack([p.mean(axis=0) for p in np.split(new.points, np.cumsum(new.lengths)[:-1]) if len(p)]) \
            if new.points.size else np.zeros((0, 3))
        new_cams = [(v.pose, v.intrinsics.fx, v.intrinsics.fy, v.intrinsics.cx, v.intrinsics.cy, v.intrinsics.width,
                     v.intrinsics.height) for v in local.views]
        return sorted(rank_views(new_cams, new_centroids, cams, {k: np.asarray(v) for k, v in centroids.items()},
                                 config.max_depth, self.max_linked_views))

    def commit_scan(self, plan: ScanPlan, embeddings: np.ndarray, *, model_sha256: str | None = None) -> MapUpdate:
        """Group the run's segments, revise the map's objects and store the scan (one transaction).

        ``embeddings``: the network's output for ``plan.scene``; ``model_sha256`` names the model
        that gave them (recorded with the scan)."""
        config = self.config
        timings = dict(plan.timings_ms)
        t0 = time.perf_counter()
        groups = group_by_evidence(plan.scene, embeddings, config)
        support = segment_support(groups, config)
        margin = support_features(groups, config)[:, 0]
        timings["grouping"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        store = self._store
        with nullcontext() if store.db.in_transaction else store.writing(wait_s=self.wait_s):
            if store.last_scan() != plan.map_scan:
                raise MapConflictError(f"{self.path}: the map changed after this scan was prepared (scan "
                                       f"{store.last_scan()} was added); prepare it again")
            n = plan.num_new
            is_new = np.arange(plan.scene.num_segments) < n
            stored_object = np.r_[np.full(n, -1, dtype=np.int64), plan.stored_objects]
            repeats = np.r_[plan.repeats, np.full(len(plan.stored_segments), -1, dtype=np.int64)]
            sizes = store.object_sizes(np.unique(np.r_[plan.stored_objects, plan.repeats[plan.repeats >= 0]]).tolist())
            seen = np.r_[np.zeros(n, dtype=bool), plan.seen_by.any(axis=1)]
            revision = revise(groups.labels, is_new, stored_object, margin, sizes, store.next_object(), self.min_margin,
                              repeats, seen)
            scan = store.add_scan(plan.name, len(plan.summaries), n, model_sha256)
            store.add_objects(revision.created, scan)
            view_ids = [store.add_view(scan, s.name, s.pose, s.declared, s.intrinsics, s.stride, s.depth, s.labels,
                                       s.labels_top, s.labels_left, s.labels_stride, s.grid_stride, s.grid_depth,
                                       s.grid_mask, s.lo, s.hi, CELL_VOXELS * config.voxel_size)
                        for s in plan.summaries]
            for moved_view in plan.moved_views:
                store.move_view(moved_view.view, moved_view.pose, moved_view.lo, moved_view.hi,
                                CELL_VOXELS * config.voxel_size, moved_view.segments.tolist(), moved_view.points)
            local_index = np.arange(n) - np.searchsorted(plan.new_view, plan.new_view)
            new_ids = store.add_segments([
                (scan, view_ids[plan.new_view[i]], int(local_index[i]), int(plan.new_instance[i]),
                 int(plan.new_component[i]), int(plan.new_pixels[i]), int(plan.new_cut[i]),
                 int(revision.segment_object[i]),
                 float(support[i]), float(margin[i]), plan.new_points[i]) for i in range(n)])
            run_ids = np.r_[np.asarray(new_ids, dtype=np.int64), plan.stored_segments]
            merged_moves = {obj: store.merge_object(obj, into) for obj, into in revision.merged_into.items()}
            moved = np.flatnonzero(~is_new & (revision.segment_object != stored_object))
            store.move_segments(run_ids[moved].tolist(), revision.segment_object[moved].tolist(),
                                support[moved].tolist(), margin[moved].tolist())
            for obj in revision.retired:
                store.retire_object(obj, scan, revision.merged_into.get(obj))
            events = []
            view_names = [s.name for s in plan.summaries]
            for e in revision.events:
                named = np.asarray(e.segments, dtype=np.int64)
                seeing = plan.seen_by[np.asarray(e.moved, dtype=np.int64) - n].any(axis=0) if e.moved else []
                views = sorted({view_names[plan.new_view[i]] for i in named.tolist()}
                               | {v for v, saw in zip(plan.fresh_views, seeing) if saw})
                moved_ids = merged_moves[e.object] if e.kind == "merged" else run_ids[e.moved].tolist()
                number = store.add_event(scan, e.kind, e.object, e.into, views, run_ids[named].tolist(), moved_ids,
                                         e.margin)
                events.append(MapEvent(event=number, kind=e.kind, object=e.object, into=e.into, scan=scan, views=views,
                                       segments=run_ids[named].tolist(), moved=moved_ids, margin=e.margin))
        timings["map_write"] = (time.perf_counter() - t0) * 1e3
        timings["total"] = sum(v for k, v in timings.items() if k != "total")
        segments = [MapSegment(segment=new_ids[i], scan=scan, view=view_names[plan.new_view[i]],
                               instance=int(plan.new_instance[i]), component=int(plan.new_component[i]),
                               num_points=len(plan.new_points[i]), object=int(revision.segment_object[i]),
                               support=round(float(support[i]), 6), margin=round(float(margin[i]), 6))
                    for i in range(n)]
        return MapUpdate(scan=scan, name=plan.name, units=config.units, segments=segments, events=events,
                         linked_views=plan.linked_views, revisited_views=plan.revisited_views, poses=plan.poses,
                         timings_ms={k: round(v, 3) for k, v in timings.items()}, warnings=plan.warnings)

    # ------------------------------------------------------------------ reads
    def segments(self, scan: int | None = None) -> list[MapSegment]:
        """Every segment of the map (or of one scan) with its current object."""
        with self._store.reading():
            rows = self._store.segment_table(scan)
        return [MapSegment(segment=r[0], scan=r[1], view=r[2], instance=r[3], component=r[4], num_points=r[5],
                           object=r[6], support=r[7], margin=r[8]) for r in rows]

    def objects(self) -> list[MapObject]:
        """The map's current objects (those with segments), with their scans, views, centroid and box."""
        with self._store.reading():
            rows, seen = self._store.object_table(), self._store.object_views()
        views: dict[int, list[MapViewRef]] = {}
        for obj, scan, name in seen:
            views.setdefault(obj, []).append(MapViewRef(scan=scan, view=name))
        out = []
        for obj, created, count, *geometry in rows:
            centroid, lo, hi = geometry[0:3], geometry[3:6], geometry[6:9]
            refs = views.get(obj, [])
            out.append(MapObject(object=obj, created_scan=created, scans=sorted({r.scan for r in refs}), views=refs,
                                 num_segments=count, centroid=_rounded(centroid), bbox_min=_rounded(lo),
                                 bbox_max=_rounded(hi)))
        return out

    def events(self, since: int = 0) -> list[MapEvent]:
        """The history after event ``since`` (0: all of it)."""
        with self._store.reading():
            rows = self._store.event_table(since)
        return [MapEvent(event=e, kind=k, object=o, into=i, scan=s, views=json.loads(v), segments=json.loads(g),
                         moved=json.loads(m), margin=margin) for e, k, o, i, s, v, g, m, margin in rows]

    def scans(self) -> list[MapScan]:
        with self._store.reading():
            rows, views = self._store.scan_table(), self._store.scan_views()
        names: dict[int, list[str]] = {}
        for scan, name in views:
            names.setdefault(scan, []).append(name)
        return [MapScan(scan=s, name=n, added_at=t, views=names.get(s, []), num_segments=c, model=m)
                for s, n, t, c, m in rows]

    def state(self) -> MapState:
        """The whole map in one snapshot: scans, objects, segments, events."""
        with self._store.reading():
            return MapState(units=self.units, scans=self.scans(), objects=self.objects(), segments=self.segments(),
                            events=self.events())


def add_to_map(path: str | Path, bundle: SceneBundle, config: ShadowCorrConfig | None = None, *,
               model: Model | None = None, name: str | None = None) -> MapUpdate:
    """Add one scan to the map at ``path`` (created when absent): ``SiteMap(path, config).add(bundle)``."""
    with SiteMap(path, config, model=model) as site:
        return site.add(bundle, name)


# ---------------------------------------------------------------------- helpers
def _check_views(bundle: SceneBundle) -> None:
    if bundle.point_segments is not None:
        raise ValueError("a site map needs views with depth and masks (it keeps their summaries to link later scans); "
                         "this bundle gives its segments as points")
    missing = [v.name for v in bundle.views if v.depth is None or v.mask is None or v.intrinsics is None]
    if missing:
        raise ValueError(f"views without depth, mask or intrinsics: {missing[:5]}")


def _in_map_units(bundle: SceneBundle, config: ShadowCorrConfig) -> SceneBundle:
    """The bundle in the map's units (depth and pose translations scaled; the same arrays when they agree)."""
    scale = unit_scale(bundle.units, config.units)
    if scale == 1.0:
        return dataclasses.replace(bundle, units=config.units, ground_truth="none", point_segments=None)
    views = []
    for v in bundle.views:
        pose = v.pose.copy()
        pose[:3, 3] *= scale
        views.append(dataclasses.replace(v, pose=pose, depth=np.asarray(v.depth, dtype=np.float32) * scale))
    return dataclasses.replace(bundle, units=config.units, views=views, ground_truth="none", point_segments=None)


def _register(local: SceneBundle, new: Segments, stored: StoredViews | None, config: ShadowCorrConfig):
    """Register the new views together with the linked stored views (``_linking``): every view at the
    pose its scan declared, stored views on the pose stage's own sampling grid, all in one order that
    does not depend on when they were added; views and segments move to the poses found.  Returns
    the scan, its segments, the pose reports (new views, then the stored views that moved) and the
    stored views' corrections relative to their poses in the map (None: kept)."""
    n = len(local.views)
    grid = stored.grid_views if stored is not None else []
    current = [*local.views, *(stored.views if stored is not None else [])]
    latest = np.iinfo(np.int64).max  # the scan being added comes after every stored one
    keys = [(v.name, latest) for v in local.views] + (
        [(name, int(scan)) for name, scan in zip(stored.view_names, stored.view_scans)] if stored is not None else [])
    order = sorted(range(len(keys)), key=keys.__getitem__)
    _, ordered = refine_poses(dataclasses.replace(local, views=[[*local.views, *grid][k] for k in order]), config,
                              view_order="listed")
    reports: list[ViewPoseCorrection] = [ordered[0]] * len(order)
    for k, report in zip(order, ordered):
        reports[k] = report
    corrections = registered_corrections(reports, [v.pose for v in current], [v.pose for v in [*local.views, *grid]])
    out_reports = [corrected_report(r, v, c) for k, (r, v, c) in enumerate(zip(reports, current, corrections))
                   if k < n or c is not None]
    local = dataclasses.replace(local, views=_moved_views(local.views, corrections[:n]))
    new = _moved_segments(new, corrections[:n])
    if stored is not None:
        stored.views = _moved_views(stored.views, corrections[n:])
        stored.segments = _moved_segments(stored.segments, corrections[n:])
    return local, new, out_reports, corrections[n:]


def _stored_moves(stored: StoredViews | None, corrections: list[np.ndarray | None]) -> list[MovedView]:
    """What the map rewrites of the stored views that registration corrected."""
    out = []
    for j, c in enumerate(corrections):
        if c is None or stored is None:
            continue
        mine = np.flatnonzero(stored.segments.view == j)
        ends = np.cumsum(stored.segments.lengths)
        points = [stored.segments.points[e - n:e].astype(np.float32) for e, n in
                  zip(ends[mine], stored.segments.lengths[mine])]
        every = np.concatenate(points) if points else np.zeros((0, 3), np.float32)
        lo, hi = (every.min(axis=0), every.max(axis=0)) if every.size else (None, None)
        out.append(MovedView(int(stored.view_ids[j]), stored.views[j].pose.copy(), lo, hi, stored.segment_ids[mine],
                             points))
    return out


def _moved_views(views: list[View], corrections: list[np.ndarray | None]) -> list[View]:
    return [v if c is None else dataclasses.replace(v, pose=c @ v.pose) for v, c in zip(views, corrections)]


def _moved_segments(segments: Segments, corrections: list[np.ndarray | None]) -> Segments:
    """The segments with each view's points, camera centre and axis moved by its correction."""
    if all(c is None for c in corrections):
        return segments
    points = segments.points.copy()
    centres, axes = segments.camera_center.copy(), segments.optical_axis.copy()
    point_view = np.repeat(segments.view, segments.lengths)
    for j, c in enumerate(corrections):
        if c is None:
            continue
        r, t = c[:3, :3], c[:3, 3]
        on = point_view == j
        points[on] = points[on] @ r.T + t
        mine = segments.view == j
        centres[mine] = centres[mine] @ r.T + t
        axes[mine] = axes[mine] @ r.T
    return dataclasses.replace(segments, points=points, camera_center=centres, optical_axis=axes)


def _camera(row) -> tuple:
    pose = unpack_array(row["pose"], "float64", "4,4")
    return pose, row["fx"], row["fy"], row["cx"], row["cy"], row["width"], row["height"]


def _rounded(values) -> list[float] | None:
    return None if values[0] is None else [round(float(x), 4) for x in values]
