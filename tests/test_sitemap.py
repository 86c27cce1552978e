"""The site map: scans added one by one reach the one-shot partition, ids stay unless an event names
them, a revisit keeps every id, and the map file survives a writer killed with SIGKILL mid-update
(a second writer meanwhile is refused, readers keep reading)."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import sqlite3
import subprocess
import sys
import time

import numpy as np
import pytest

from shadowcorr import ShadowCorrConfig, correspond, load_model
from shadowcorr.bundle import PointSegments
from shadowcorr.convert import load_ue_scene
from shadowcorr.evaluation import segment_metrics
from shadowcorr.io import write_bundle
from shadowcorr.sitemap import MapBusyError, MapConflictError, MapFileError, SiteMap
from shadowcorr.sitemap._revision import revise
from shadowcorr.sitemap import _store, _summaries
from shadowcorr.sitemap._store import FORMAT_VERSION, pack_array, unpack_array
from shadowcorr.stages import refine_poses
from shadowcorr.synth.noise import perturbed_pose

from .paths import REPO, SAMPLE_DIR
from .scenes import sphere_scene

CENTRES = np.array([[0, 0, 45], [140, 20, 40], [-100, 110, 42], [40, -150, 38], [-90, -80, 40], [110, 150, 44]], float)


@pytest.fixture(scope="module")
def model():
    return load_model()


@pytest.fixture(scope="module")
def ring():
    """Six spheres seen by eight cameras on a ring (exact depth, masks: sphere index + 1)."""
    return sphere_scene(CENTRES, CENTRES[:, 2], cameras=8, width=320, height_px=180)


def views(bundle, *names):
    return dataclasses.replace(bundle, views=[v for v in bundle.views if v.name in names])


def key(s) -> tuple:
    return s.view, s.instance, s.component


def contents(site: SiteMap) -> tuple[list[dict], list[dict]]:
    """Every segment and event of the map, as plain data."""
    return [s.model_dump() for s in site.segments()], [e.model_dump() for e in site.events()]


def test_scans_in_any_order_give_the_one_shot_partition(tmp_path, model, ring) -> None:
    one_shot = {key(s): s.object for s in correspond(ring, model).segments}
    pairs = [("cam0", "cam1"), ("cam2", "cam3"), ("cam4", "cam5"), ("cam6", "cam7")]
    for k, order in enumerate(([0, 1, 2, 3], [3, 0, 2, 1])):
        with SiteMap(tmp_path / f"order{k}.map", model=model) as site:
            first = {}
            for i in order:
                update = site.add(views(ring, *pairs[i]))
                assert {s.view for s in update.segments} == set(pairs[i])
                first.update({s.segment: s.object for s in update.segments})
            segments = site.segments()
            assert len(segments) == len(one_shot)
            ours = np.array([s.object for s in segments])
            theirs = np.array([one_shot[key(s)] for s in segments])
            assert segment_metrics(theirs, ours)["average_purity"] == 100.0
            # Every id is the one its segment got when its scan was added: no event revised one.
            assert all(first[s.segment] == s.object for s in segments)
            assert {e.kind for e in site.events()} == {"created", "observed"}
            assert len(site.objects()) == len(CENTRES)
            assert len(site.scans()) == 4


def test_a_revisit_gives_every_segment_its_id(tmp_path, model, ring) -> None:
    with SiteMap(tmp_path / "site.map", model=model) as site:
        site.add(views(ring, "cam0", "cam2", "cam5"))
        before = {key(s): s.object for s in site.segments(scan=1)}
        again = site.add(views(ring, "cam0", "cam2", "cam5"))
        assert {key(s): s.object for s in again.segments} == before
        assert {e.kind for e in again.events} == {"observed"}
        # The repeated views are recognised (and left out of the evidence: seen twice, it would count twice).
        assert sorted(r.view for r in again.revisited_views) == ["cam0", "cam2", "cam5"] and again.linked_views == []
        # A repeated view beside a new one: the repeat keeps its ids, the new view's spheres get them too.
        mixed = site.add(views(ring, "cam2", "cam7"))
        assert {(r.scan, r.view) for r in mixed.revisited_views} == {(1, "cam2"), (2, "cam2")}
        assert {r.view for r in mixed.linked_views} <= {"cam0", "cam5"}
        sphere_id = {instance: obj for (_, instance, _), obj in before.items()}
        assert all(s.object == sphere_id[s.instance] for s in mixed.segments)
        assert {e.kind for e in site.events()} == {"created", "observed"}


def test_halves_of_a_split_mask_are_merged_when_a_later_scan_sees_the_whole(tmp_path, model, ring) -> None:
    cam0 = sphere_scene(CENTRES, CENTRES[:, 2], cameras=8, width=640, height_px=360).views[0]
    mask = cam0.mask.copy()
    _, cols = np.nonzero(mask == 1)
    column = np.arange(mask.shape[1])[None, :]
    middle = int(np.median(cols))
    # One sphere, two ids, with a gap between them wider than a seam is looked for across.
    config = ShadowCorrConfig()
    mask[(mask == 1) & (column >= middle)] = 7
    mask[((mask == 1) | (mask == 7)) & (np.abs(column - middle) <= config.fusion_seam_gap // 2 + 1)] = 0
    # Seen by one view only, two mask ids are two objects (the per-view constraint); once other views
    # show the two masks landing together (a split mask), the constraint no longer holds - as in one
    # run of the four views.  (With a much stronger constraint, fusion_cannot_link=3, that one run
    # keeps them apart too.)
    split = dataclasses.replace(cam0, mask=mask)
    one_shot = {s.instance: s.object for s in correspond(dataclasses.replace(
        ring, views=[split, *views(ring, "cam2", "cam3", "cam4").views]), model, config).segments if s.view == "cam0"}
    assert one_shot[1] == one_shot[7]
    with SiteMap(tmp_path / "site.map", config, model=model) as site:
        first = site.add(dataclasses.replace(ring, views=[split]))
        halves = {s.instance: s for s in first.segments if s.instance in (1, 7)}
        assert halves[1].object != halves[7].object
        update = site.add(views(ring, "cam2", "cam3", "cam4"))
        merged = [e for e in update.events if e.kind == "merged"]
        assert len(merged) == 1
        event = merged[0]
        assert {event.object, event.into} == {halves[1].object, halves[7].object}
        assert event.scan == update.scan and event.segments and event.views and event.margin > 0
        # The retired id is gone from the map, every segment of it carries the survivor's id, and the
        # history says so.
        now = {s.segment: s.object for s in site.segments()}
        assert now[halves[1].segment] == now[halves[7].segment] == event.into
        assert event.object not in {o.object for o in site.objects()}
        assert [e.event for e in site.events(since=event.event - 1)] == [event.event]


def test_revisions_follow_the_new_evidence_only() -> None:
    # Run segments: 0-1 new; 2-6 stored.  Objects: 10 (2, 3, 4), 11 (5), 12 (6).
    stored = np.array([-1, -1, 10, 10, 10, 11, 12])
    new = np.array([True, True, False, False, False, False, False])
    sizes = {10: 3, 11: 1, 12: 2}  # object 12 has a segment in a view the run did not load
    margin = np.full(7, 0.5)
    # Group 0: new 0 + 10's (2, 3) + 11 -> 11 merges into 10.  Group 1: new 1 + 10's 4 -> split off
    # into a new object.  Group 2: 12 alone, no new segment -> untouched.
    plan = revise(np.array([0, 1, 0, 0, 1, 0, 2]), new, stored, margin, sizes, first_new_object=13)
    assert plan.segment_object.tolist() == [10, 13, 10, 10, 13, 10, 12]
    assert plan.created == [13] and plan.merged_into == {11: 10} and plan.retired == [11]
    kinds = [(e.kind, e.object, e.into, e.segments, e.moved) for e in plan.events]
    assert ("observed", 10, None, [0], []) in kinds and ("created", 13, None, [1], []) in kinds
    assert ("merged", 11, 10, [0], [5]) in kinds and ("split", 10, 13, [1], [4]) in kinds
    # With min_margin, a stored segment without that margin stays, and the new segment joins the
    # object it lies with.
    weak = margin.copy()
    weak[4] = -0.1
    plan = revise(np.array([0, 1, 0, 0, 1, 0, 2]), new, stored, weak, sizes, first_new_object=13, min_margin=0.0)
    assert plan.segment_object.tolist()[:5] == [10, 10, 10, 10, 10] and plan.created == []
    # Without it (the default) the run's group decides, whatever the margin: as one run of all the views.
    plan = revise(np.array([0, 1, 0, 0, 1, 0, 2]), new, stored, weak, sizes, first_new_object=13)
    assert plan.segment_object.tolist() == [10, 13, 10, 10, 13, 10, 12] and plan.created == [13]
    # An object without a home whose segments go two ways is split twice and, left empty, retired.
    group = np.array([0, 1, 0, 1, 0, 0, 1, 1])
    new = np.array([True, True, False, False, False, False, False, False])
    stored = np.array([-1, -1, 40, 40, 41, 41, 42, 42])
    plan = revise(group, new, stored, np.full(8, 0.5), {40: 2, 41: 2, 42: 2}, first_new_object=43)
    assert plan.segment_object.tolist() == [41, 42, 41, 42, 41, 41, 42, 42]
    assert plan.retired == [40] and plan.merged_into == {}
    kinds = [(e.kind, e.object, e.into, e.moved) for e in plan.events if e.kind not in ("observed", "created")]
    assert kinds == [("split", 40, 41, [2]), ("split", 40, 42, [3]), ("retired", 40, None, [2, 3])]


def test_a_stored_segment_the_scan_sees_is_revised_without_new_segments_in_its_group() -> None:
    # Run segments: 0 new; 1-4 stored.  Object 20 (1, 2, 3), object 21 (4).  The run puts 1, 2 with the
    # new segment and 3 with 4: only the scan's views seeing 3 (or 4) lets it revise that group.
    group = np.array([0, 0, 0, 1, 1])
    new = np.array([True, False, False, False, False])
    stored = np.array([-1, 20, 20, 20, 21])
    margin = np.full(5, 0.5)
    unseen = revise(group, new, stored, margin, {20: 3, 21: 1}, first_new_object=22)
    assert unseen.segment_object.tolist() == [20, 20, 20, 20, 21]
    seen = revise(group, new, stored, margin, {20: 3, 21: 1}, first_new_object=22,
                  seen=np.array([False, False, False, True, False]))
    assert seen.segment_object.tolist() == [20, 20, 20, 21, 21]
    kinds = [(e.kind, e.object, e.into, e.moved) for e in seen.events if e.kind != "observed"]
    assert kinds == [("split", 20, 21, [3])]
    # Seen, but in a group of its own without an owner: split off into a new object, created by it.
    alone = revise(np.array([0, 0, 0, 1, 2]), new, stored, margin, {20: 3, 21: 1}, first_new_object=22,
                   seen=np.array([False, False, False, True, False]))
    assert alone.segment_object.tolist() == [20, 20, 20, 22, 21] and alone.created == [22]
    kinds = [(e.kind, e.object, e.into, e.moved) for e in alone.events if e.kind != "observed"]
    assert kinds == [("created", 22, None, [3]), ("split", 20, 22, [3])]


def test_poses_after_the_last_scan_are_one_registration_of_all_views_whatever_the_order(tmp_path, model) -> None:
    truth = load_ue_scene(SAMPLE_DIR, "2001", [0, 2, 4, 6])
    rng = np.random.default_rng(5)
    noisy = dataclasses.replace(truth, views=[dataclasses.replace(v, pose=perturbed_pose(rng, v.pose, 1.0, 2.5))
                                              for v in truth.views])
    at_once = {v.name: v.pose for v in refine_poses(noisy)[0].views}
    assert any(not np.allclose(at_once[v.name], v.pose) for v in noisy.views)  # registration corrected some
    for k, order in enumerate(([(0, 1), (2, 3)], [(3,), (0, 2), (1,)])):
        with SiteMap(tmp_path / f"order{k}.map", model=model) as site:
            for cams in order:
                site.add(dataclasses.replace(noisy, views=[noisy.views[c] for c in cams]))
            rows = site._store.view_rows(list(range(1, 5)), with_images=False)
        ours = {r["name"]: unpack_array(r["pose"], "float64", "4,4") for r in rows}
        assert sorted(ours) == sorted(at_once)
        for name, pose in ours.items():
            assert np.allclose(pose, at_once[name], atol=1e-6), name


def test_the_map_file_keeps_arrays_as_raw_bytes_and_reopens_intact(tmp_path, model, ring) -> None:
    path = tmp_path / "site.map"
    with SiteMap(path, model=model) as site:
        site.add(views(ring, "cam0", "cam3"))
        before = contents(site)
    with SiteMap(path, create=False) as site:
        assert contents(site) == before
    db = sqlite3.connect(path)
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    dtypes = {r[0] for r in db.execute("SELECT points_dtype FROM segments")}
    assert dtypes == {"float32"}
    blob, dtype, shape = db.execute("SELECT points, points_dtype, points_shape FROM segments LIMIT 1").fetchone()
    assert unpack_array(blob, dtype, shape).shape[1] == 3
    assert not any(b[:1] == b"\x80" for (b,) in db.execute("SELECT points FROM segments"))  # no pickle protocol header
    db.close()
    with pytest.raises(MapFileError, match="dtype 'object'"):
        unpack_array(b"", "object", "0")
    with pytest.raises(MapFileError, match="holds 4 bytes"):
        unpack_array(*pack_array(np.zeros(1, np.float32))[:2], "2")
    (tmp_path / "junk.map").write_bytes(b"not a database at all, just text" * 10)
    with pytest.raises(MapFileError, match="not a site map"):
        SiteMap(tmp_path / "junk.map")
    with pytest.raises(FileNotFoundError):
        SiteMap(tmp_path / "absent.map", create=False)


def _as_format_2(path) -> None:
    """Rewrite a map file as format 2 wrote it: segment images on the depth's grid, no labels_stride, no cut."""
    db = sqlite3.connect(path)
    rows = db.execute("SELECT view, stride, depth_shape, labels, labels_dtype, labels_shape, labels_top, labels_left "
                      "FROM views").fetchall()
    for view, f, depth_shape, blob, dtype, shape, top, left in rows:
        window = unpack_array(blob, dtype, shape, compressed=True)
        h, w = (int(x) for x in depth_shape.split(","))
        grid = np.full((h, w), -1, dtype=np.int64)
        rr, cc = np.arange(h) * f + f // 2 - top, np.arange(w) * f + f // 2 - left
        inside_r, inside_c = (rr >= 0) & (rr < window.shape[0]), (cc >= 0) & (cc < window.shape[1])
        grid[np.ix_(inside_r, inside_c)] = window[np.ix_(rr[inside_r], cc[inside_c])]
        on = np.argwhere(grid >= 0)
        (r0, c0), (r1, c1) = on.min(axis=0), on.max(axis=0) + 1
        data, dtype, shape = pack_array(grid[r0:r1, c0:c1].astype(np.int16), compress=True)
        db.execute("UPDATE views SET labels = ?, labels_dtype = ?, labels_shape = ?, labels_top = ?, labels_left = ? "
                   "WHERE view = ?", (data, dtype, shape, int(r0), int(c0), view))
    db.execute("ALTER TABLE views DROP COLUMN labels_stride")
    db.execute("ALTER TABLE segments DROP COLUMN cut")
    db.execute("UPDATE meta SET value = '2' WHERE key = 'format'")
    db.commit()
    db.close()


def test_segment_images_are_kept_at_full_resolution_and_format_2_maps_are_upgraded(tmp_path, model, ring,
                                                                                   monkeypatch) -> None:
    monkeypatch.setattr(_summaries, "SUMMARY_SIDE", 160)  # depth every 2nd pixel of the 320 x 180 views
    one_shot = {key(s): s.object for s in correspond(ring, model).segments}
    final = {}
    for old in (False, True):
        path = tmp_path / f"site{int(old)}.map"
        with SiteMap(path, model=model) as site:
            site.add(views(ring, "cam0", "cam3"))
            rows = site._store.view_rows([1, 2])
            assert {(r["stride"], r["labels_stride"]) for r in rows} == {(2, 1)}
            stored = _summaries.stored_views(rows, site._store.segment_rows([1, 2]))
            image = stored.segments.pixel_segment[0]
            assert image.shape == (180, 320) and image.view_stride == 2 and image.pixel_scale == 1
            # The mask registration reads is the image on the depth's grid.
            on_grid = _summaries.grid_labels(image, 2, (90, 160))
            assert np.array_equal(stored.views[0].mask > 0, on_grid >= 0)
        if old:
            _as_format_2(path)
            with monkeypatch.context() as patched, pytest.raises(MapFileError, match="format '2'"):
                patched.setattr(_store, "_UPGRADABLE", frozenset())  # a version that cannot upgrade it refuses it
                SiteMap(path)
        with SiteMap(path, model=model) as site:
            assert site._store.meta("format") == FORMAT_VERSION
            assert {r["labels_stride"] for r in site._store.view_rows([1, 2])} == ({2} if old else {1})
            before = {key(s): s.object for s in site.segments()}
            again = site.add(views(ring, "cam0"))  # a revisit keeps every id, on either kind of stored image
            assert {r.view for r in again.revisited_views} == {"cam0"}
            assert all(before[key(s)] == s.object for s in again.segments)
            for pair in (("cam1", "cam2"), ("cam4", "cam5"), ("cam6", "cam7")):
                site.add(views(ring, *pair))
            final[old] = {key(s): s.object for s in site.segments() if s.scan != 2}
    for got in final.values():
        ours = np.array(list(got.values()))
        theirs = np.array([one_shot[k] for k in got])
        assert segment_metrics(theirs, ours)["average_purity"] == 100.0


def test_settings_and_inputs_a_map_refuses(tmp_path, model, ring) -> None:
    path = tmp_path / "site.map"
    SiteMap(path, ShadowCorrConfig(refine_poses=False), model=model).close()
    with pytest.raises(ValueError, match="other settings .*refine_poses"):
        SiteMap(path, ShadowCorrConfig(refine_poses=True))
    with SiteMap(path, ShadowCorrConfig(num_threads=2)) as site:  # run-time settings may differ
        assert site.config.refine_poses is False and site.config.num_threads == 2
    with pytest.raises(ValueError, match="'fused'"):
        SiteMap(tmp_path / "other.map", ShadowCorrConfig(method="shadowcorr"))
    points = PointSegments(points=np.zeros((3, 3)), lengths=np.array([3]), view=np.array([0]), instance=np.array([1]))
    with SiteMap(path, model=model) as site, pytest.raises(ValueError, match="depth and masks"):
        site.add(dataclasses.replace(views(ring, "cam0"), point_segments=points))
    with SiteMap(path, model=model) as site:  # a plan prepared before another update is refused at commit
        plan = site.prepare_scan(views(ring, "cam1"))
        site.add(views(ring, "cam2"))
        with pytest.raises(MapConflictError, match="changed"):
            site.commit_scan(plan, np.zeros((plan.scene.num_voxels, 32), np.float32))


#: A writer that stops inside its update's transaction (after writing segments) until it is killed.
STALLED_WRITER = """
import sys, time
from shadowcorr import load_bundle
from shadowcorr.sitemap import SiteMap, _store

original = _store.MapStore.add_segments

def stall(self, rows):
    ids = original(self, rows)
    print("inside", flush=True)
    time.sleep(600)
    return ids

_store.MapStore.add_segments = stall
SiteMap(sys.argv[1]).add(load_bundle(sys.argv[2]))
"""


def test_a_writer_killed_mid_update_leaves_every_earlier_update(tmp_path, model, ring) -> None:
    path = tmp_path / "site.map"
    with SiteMap(path, model=model) as site:
        site.add(views(ring, "cam0", "cam1"))
        before = contents(site)
    second = write_bundle(views(ring, "cam4", "cam5"), tmp_path / "second")
    writer = subprocess.Popen([sys.executable, "-c", STALLED_WRITER, str(path), str(second)], cwd=REPO,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert writer.stdout.readline().strip() == "inside"
        with SiteMap(path, model=model) as site:
            t0 = time.monotonic()
            with pytest.raises(MapBusyError, match="another writer"):
                site.add(views(ring, "cam6"))
            assert time.monotonic() - t0 < 5.0  # refused, not queued
            assert contents(site) == before  # readers read the last commit
        os.kill(writer.pid, signal.SIGKILL)
        writer.wait(timeout=30)
    finally:
        if writer.poll() is None:
            writer.kill()
            writer.wait()
    assert writer.returncode == -signal.SIGKILL
    with SiteMap(path, model=model, create=False) as site:
        assert contents(site) == before
        assert [s.scan for s in site.scans()] == [1]
        update = site.add(views(ring, "cam4", "cam5"))  # the killed update, repeated
        assert update.scan == 2 and {s.view for s in update.segments} == {"cam4", "cam5"}
        assert json.loads(site.state().model_dump_json())["segments"][0]["object"] == before[0][0]["object"]


def test_map_commands_add_scans_and_show_the_map(tmp_path, ring, capsys) -> None:
    from shadowcorr.cli import main

    first = write_bundle(views(ring, "cam0", "cam1", "cam2"), tmp_path / "first")
    second = write_bundle(views(ring, "cam4", "cam5", "cam6"), tmp_path / "second")
    path, out = tmp_path / "site.map", tmp_path / "updates.jsonl"
    assert main(["map", "add", str(path), str(first), str(second), "--out", str(out), "--threads", "1"]) == 0
    updates = [json.loads(line) for line in out.read_text().splitlines()]
    assert [u["scan"] for u in updates] == [1, 2]
    segment = updates[1]["segments"][0]
    assert {"segment", "view", "instance", "component", "object", "support"} <= set(segment)
    assert {"kind", "object", "scan", "views"} <= set(updates[1]["events"][0]) and "total" in updates[1]["timings_ms"]
    assert {e["kind"] for e in updates[0]["events"]} == {"created"} and {e["kind"] for e in updates[1]["events"]} == {
        "observed"}
    assert main(["map", "show", str(path), "--out", str(tmp_path / "map.json")]) == 0
    state = json.loads((tmp_path / "map.json").read_text())
    assert [s["scan"] for s in state["scans"]] == [1, 2] and len(state["objects"]) == len(CENTRES)
    assert {"object", "scans", "views", "centroid"} <= set(state["objects"][0])
    assert {"scan", "view", "instance", "component", "object"} <= set(state["segments"][0])
    assert len(state["segments"]) == sum(len(u["segments"]) for u in updates)
    capsys.readouterr()
    assert main(["map", "show", str(tmp_path / "absent.map")]) == 2
    assert "no such map" in capsys.readouterr().err


def test_plain_correspond_labels_a_hundred_view_bundle(tmp_path) -> None:
    from shadowcorr.cli import main

    spheres = sphere_scene(CENTRES[:4], CENTRES[:4, 2], cameras=100, width=96, height_px=64)
    bundle = write_bundle(spheres, tmp_path / "hundred")  # 201 files, 100 views: beyond the service's limits
    assert main(["correspond", str(bundle), "--out", str(tmp_path / "result.json")]) == 0
    result = json.loads((tmp_path / "result.json").read_text())
    assert len({s["view"] for s in result["segments"]}) == 100
    assert result["metrics"]["average_purity"] == 100.0 and len(result["objects"]) == 4


def test_linked_views_cover_the_sides_a_scan_misses():
    """Past ``max_views`` a stored view that sees the new segments from another side comes before
    one that sees more of them from the side the new view already sees them from."""
    from shadowcorr.poses import look_at_pose
    from shadowcorr.sitemap._linking import rank_views

    rocks = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [-50.0, 0.0, 0.0]])

    def cam(eye):
        return (look_at_pose(np.asarray(eye, float), np.zeros(3)), 200.0, 200.0, 160.0, 90.0, 320, 180)

    new = [cam([-600.0, 0.0, 200.0])]
    stored = {1: cam([-500.0, 10.0, 200.0]), 2: cam([600.0, 0.0, 200.0])}
    centroids = {1: rocks.copy(), 2: rocks[:1].copy()}
    assert rank_views(new, rocks, stored, centroids, 5000.0, 2) == [1, 2]  # room for all: most shared first
    assert rank_views(new, rocks, stored, centroids, 5000.0, 1) == [2]
