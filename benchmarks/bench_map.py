"""The site map (``shadowcorr.SiteMap``): scans added one by one against the scene labelled at once,
id stability, revisits, and the cost of an update as the map grows.

    python benchmarks/bench_map.py                                 # real scene and tiled field
    python benchmarks/bench_map.py --part real --field-seeds 5      # the real scene, more noise draws
    python benchmarks/bench_map.py --part field --tiles 25          # 500 rocks streamed in 50 scans
    python benchmarks/bench_map.py --part contiguous --stops 5x10   # one field, scans overlapping

**Real scene** (examples/ue_sample, set 2001, 8 cameras 45 degrees apart): the 8 views are added as
4 scans of 2 views, in several orders, to a new map each time, and the 8 views are labelled at
once (``correspond``), and once more with its views listed in the order the scans bring them
(the one-shot partition's own sensitivity to nothing but the order of its views).  Clean and
under the quality benchmark's combined ``field`` errors (``bench_quality.COMBINED["field"]``:
depth 1 %, poses 1 deg / 2.5 cm, eroded, split, merged and dropped masks, holes; the same
perturbed views for the map and for the one-shot run, one draw per
``--field-seeds``).  Printed per order: the map's average purity against the truth (a blob of a
merged mask scored by the rock under its own pixels, as the quality benchmark scores it), the one-shot
run's, their agreement (the average purity of the map's partition scored against the one-shot
partition: 100 is the same partition), the share of segments that still carry the id they got
when their scan was added, the share whose id changed without an event naming it (must be 0),
the events, and a revisit (the first scan's views added again): the share of its segments that
get the id their counterpart already has.

**Tiled field**: copies of the real scene 1 km apart (``bench_scale.tile_scene``; each tile's
rocks are distinct objects), optionally each under its own draw of ``--tile-noise``, streamed
as scans of 4 views (cameras 0, 2, 4, 6, then 1, 3, 5, 7 of each tile).  Printed: the update time
against the map's size (early and late updates, each kind of scan apart: a tile's first scan
links to no stored view, its second to the first's four), the map file's size, the process's
peak resident memory, and the map's average purity beside the tiles labelled one by one.  The
plot ``map_updates.png`` (update time against objects in the map) goes to ``--out``.

**Contiguous field** (``--part contiguous``): spheres on a jittered 1 m grid, scanned from a grid
of stops 3 m apart along rows (``--stops`` rows x columns), 4 views per stop looking along +x,
+y, -x and -y; neighbouring stops see the same rocks, so every scan after the first links to
stored views.  Exact depth and poses, masks are sphere ids.  Printed: the update time early and
late, stored views linked per scan, map file, peak memory, purity, and - where the whole field
fits one run (``max_segments``) - all views labelled at once and its agreement with the map.

Times are wall times of one process with ``--threads`` threads on a shared machine: they say how
the cost grows, not what a dedicated machine would take.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "examples" / "ue_sample"
sys.path[:0] = [str(REPO), str(Path(__file__).resolve().parent)]

#: Orders in which the real scene's 8 cameras are added, two per scan.
ORDERS = {
    "neighbours": [(0, 1), (2, 3), (4, 5), (6, 7)],
    "reversed": [(6, 7), (4, 5), (2, 3), (0, 1)],
    "opposite": [(0, 4), (2, 6), (1, 5), (3, 7)],
    "scattered": [(3, 6), (0, 5), (7, 2), (4, 1)],
}


def truth_of(bundle, view: str, instance: int) -> int:
    """The true rock of a segment (mask ids are rocks, or the perturbation's table of them)."""
    if bundle.ground_truth == "instance":
        return instance
    table = next(v for v in bundle.views if v.name == view).instance_objects or {}
    return table.get(instance, -1)


def purity(truth: np.ndarray, labels: np.ndarray) -> float:
    from shadowcorr.evaluation import segment_metrics

    return float(segment_metrics(truth, labels)["average_purity"])


def run_order(bundle, order, model, path: Path, one_shot: dict, truth_of_segments) -> dict:
    """Add the bundle's views scan by scan in ``order``; the figures of the finished map
    (``truth_of_segments``: the true rock of each of a list of segments)."""
    from shadowcorr import SiteMap

    first_id, seconds = {}, []
    with SiteMap(path, model=model) as site:
        for cams in order:
            t0 = time.perf_counter()
            update = site.add(dataclasses.replace(bundle, views=[bundle.views[c] for c in cams]))
            seconds.append(time.perf_counter() - t0)
            first_id.update({s.segment: s.object for s in update.segments})
        segments = site.segments()
        events = site.events()
        named = {}
        for e in events:
            for seg in e.segments + e.moved:
                named.setdefault(seg, set()).update({e.object, e.into})
        kept = [s.object == first_id[s.segment] for s in segments]
        unexplained = [s.object != first_id[s.segment] and first_id[s.segment] not in named.get(s.segment, set())
                       for s in segments]
        keys = [(s.view, s.instance, s.component) for s in segments]
        labels = np.array([s.object for s in segments])
        truth = truth_of_segments(segments)
        common = [i for i, k in enumerate(keys) if k in one_shot]
        agreement = purity(np.array([one_shot[keys[i]] for i in common]), labels[common])
        # A revisit: the first scan's views again.  Its segments should get the ids their counterparts
        # have; where the revisit's evidence revises them (events), the purity after it says whether
        # the revision was right.
        now = {(s.view, s.instance, s.component): s.object for s in segments}
        again = site.add(dataclasses.replace(bundle, views=[bundle.views[c] for c in order[0]]))
        revisit = [now.get((s.view, s.instance, s.component)) == s.object for s in again.segments]
        revised = sum(e.kind in ("merged", "split", "retired") for e in again.events)
        after = [s for s in site.segments() if s.scan <= len(order)]
        after_purity = purity(truth_of_segments(after), np.array([s.object for s in after]))
    kinds = {k: sum(e.kind == k for e in events) for k in ("created", "observed", "merged", "split", "retired")}
    return {"purity": purity(truth, labels), "agreement": agreement, "kept": 100 * float(np.mean(kept)),
            "unexplained": int(np.sum(unexplained)), "revisit": 100 * float(np.mean(revisit)), "revisit_revisions": revised,
            "purity_after_revisit": after_purity, "events": kinds,
            "seconds": seconds, "segments": len(segments)}


def real_scene(model, field_seeds: int, work: Path) -> list[dict]:
    from shadowcorr import correspond
    from shadowcorr.convert import load_ue_scene
    from tests.harness import load_bench_quality

    quality = load_bench_quality()
    clean = load_ue_scene(SAMPLE, 2001, list(range(8)))
    draws = [("clean", clean, {})]
    for k in range(field_seeds):
        merged: dict = {}  # the masks the perturbation drew over several rocks
        draws.append((f"field#{k}", quality.perturb(clean, "field", quality.perturbation_seed("real:all8", "field", k),
                                                    merged), merged))
    rows = []
    for condition, bundle, merged in draws:
        # As the quality benchmark scores: a blob of a merged mask by the rock under its own pixels.
        def truth_of_segments(segments, bundle=bundle, merged=merged):
            return quality.segment_truth(bundle, SimpleNamespace(segments=segments), clean, merged)

        result = correspond(bundle, model)
        one_shot = {(s.view, s.instance, s.component): s.object for s in result.segments}
        truth = truth_of_segments(result.segments)
        one_purity = purity(truth, np.array([s.object for s in result.segments]))
        for name, order in ORDERS.items():
            path = work / f"{condition}-{name}.map"
            # The one-shot run itself, its views listed in the order the scans bring them: how far
            # the one-shot partition moves with nothing but the order of its views.
            listed = correspond(dataclasses.replace(bundle, views=[bundle.views[c] for cams in order for c in cams]),
                                model)
            reordered = {(s.view, s.instance, s.component): s.object for s in listed.segments}
            keys = [k for k in one_shot if k in reordered]
            self_agreement = purity(np.array([one_shot[k] for k in keys]), np.array([reordered[k] for k in keys]))
            row = {"condition": condition, "order": name, "one_shot": one_purity, "one_shot_reordered": self_agreement,
                   **run_order(bundle, order, model, path, one_shot, truth_of_segments)}
            rows.append(row)
            print(f"{condition:9} {name:10} map {row['purity']:6.2f}  one-shot {one_purity:6.2f}  agreement "
                  f"{row['agreement']:6.2f} (one-shot reordered {self_agreement:6.2f})\n{'':21}ids kept "
                  f"{row['kept']:6.2f} %  unexplained {row['unexplained']}  revisit "
                  f"{row['revisit']:6.2f} % ({row['revisit_revisions']} revisions, purity then "
                  f"{row['purity_after_revisit']:6.2f})  events {row['events']}  updates "
                  f"{' '.join(f'{s:.2f}' for s in row['seconds'])} s", flush=True)
    return rows


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def tiled_field(model, tiles: int, tile_noise: str | None, work: Path, out: Path) -> dict:
    import math

    from bench_scale import place_tile

    from shadowcorr import SiteMap, correspond
    from shadowcorr.convert import load_ue_scene
    from tests.harness import load_bench_quality

    base = load_ue_scene(SAMPLE, 2001, list(range(8)))
    quality = load_bench_quality() if tile_noise else None
    side = math.ceil(math.sqrt(tiles))
    path = work / "field.map"
    records, alone, truth = [], [], {}
    with SiteMap(path, model=model) as site:
        for t in range(tiles):
            tile = base
            if tile_noise:
                tile = quality.perturb(base, tile_noise, quality.perturbation_seed(f"tile{t}", tile_noise, 0))
            # One tile at a time at its place in the field: the process never holds more than its images.
            placed = place_tile(tile, t, side, TILE_SPACING, TILE_IDS)
            for half, cams in enumerate(((0, 2, 4, 6), (1, 3, 5, 7))):
                scan = dataclasses.replace(tile, views=[placed[c] for c in cams], name=f"tile{t}-{half}",
                                           ground_truth="none")
                t0 = time.perf_counter()
                update = site.add(scan)
                seconds = time.perf_counter() - t0
                for s in update.segments:  # the rock, made distinct per tile
                    truth[s.segment] = truth_of(tile, s.view.split("_", 1)[1], s.instance - t * TILE_IDS) + t * TILE_IDS
                records.append({"tile": t, "half": half, "seconds": seconds, "objects": len(site.objects()),
                                "linked": len(update.linked_views),
                                **{k: update.timings_ms.get(k, 0.0) for k in ("map_read", "map_write", "total")}})
            if t < 3:  # tiles labelled alone, for comparison
                result = correspond(tile, model)
                alone.append(purity(np.array([truth_of(tile, s.view, s.instance) for s in result.segments]),
                                    np.array([s.object for s in result.segments])))
            print(f"tile {t + 1}/{tiles}: {records[-1]['objects']} objects, updates "
                  f"{records[-2]['seconds']:.2f} / {records[-1]['seconds']:.2f} s, peak RSS {_peak_rss_mb():.0f} MB",
                  flush=True)
        labels = {s.segment: s.object for s in site.segments()}
    keys = sorted(labels)
    summary = summarize_field(records)
    summary.update(map_mb=sum(p.stat().st_size for p in work.glob("field.map*")) / 2**20,
                   peak_rss_mb=_peak_rss_mb(), tiles=tiles, rocks=tiles * 20, scans=len(records),
                   purity=purity(np.array([truth[k] for k in keys]), np.array([labels[k] for k in keys])),
                   tiles_alone=float(np.mean(alone)))
    plot(records, out / "map_updates.png")
    return {"records": records, "summary": summary}


def contiguous_field(model, stops: tuple[int, int], work: Path, out: Path, max_linked_views: int = 32) -> dict:
    """A field of spheres on the ground, scanned stop by stop along rows: each scan is 4 views from one
    stop (looking along +x, +y, -x, -y, tilted down), and neighbouring stops see the same rocks, so
    every scan after the first links to stored views.  Exact depth and poses; masks are sphere ids."""
    from shadowcorr import ShadowCorrConfig, SiteMap, correspond
    from shadowcorr.bundle import Intrinsics, SceneBundle, View
    from shadowcorr.poses import look_at_pose
    from shadowcorr.synth.spheres import render_spheres

    rng = np.random.default_rng(7)
    rows, cols = stops
    step, spacing = 300.0, 100.0  # cm between stops, between rocks
    lo, hi = np.array([-400.0, -400.0]), np.array([(cols - 1) * step + 400.0, (rows - 1) * step + 400.0])
    grid = np.stack(np.meshgrid(np.arange(lo[0], hi[0], spacing), np.arange(lo[1], hi[1], spacing)), -1).reshape(-1, 2)
    radii = rng.uniform(18.0, 32.0, len(grid))
    centres = np.c_[grid + rng.uniform(-25.0, 25.0, grid.shape), radii]
    width, height = 320, 180
    f = 1615.0 / 1920.0 * width
    k = Intrinsics(fx=f, fy=f, cx=width / 2, cy=height / 2, width=width, height=height)
    order = [(r, c if r % 2 == 0 else cols - 1 - c) for r in range(rows) for c in range(cols)]
    scans = []
    for r, c in order:
        eye = np.array([c * step, r * step, 220.0])
        views = []
        for name, direction in (("e", (1, 0)), ("n", (0, 1)), ("w", (-1, 0)), ("s", (0, -1))):
            pose = look_at_pose(eye, eye + np.array([*direction, 0.0]) * 450.0 - np.array([0.0, 0.0, 220.0]))
            depth, mask = render_spheres(centres, radii, pose, k)
            views.append(View(name=f"s{r}_{c}_{name}", pose=pose, intrinsics=k, depth=depth, mask=mask))
        scans.append(SceneBundle(units="cm", views=views, name=f"stop{r}_{c}", ground_truth="instance"))
    records = []
    with SiteMap(work / "contiguous.map", model=model, max_linked_views=max_linked_views) as site:
        for scan in scans:
            t0 = time.perf_counter()
            update = site.add(scan)
            records.append({"seconds": time.perf_counter() - t0, "objects": len(site.objects()),
                            "linked": len(update.linked_views), "half": 1 if update.linked_views else 0})
        segments = site.segments()
    labels = np.array([s.object for s in segments])
    truth = np.array([s.instance for s in segments])
    seen_rocks = len(np.unique(truth))
    times = [r["seconds"] for r in records[1:]]
    kk = max(1, min(5, len(times) // 3))
    summary = {"stops": rows * cols, "views": 4 * rows * cols, "segments": len(segments),
               "rocks_placed": len(radii), "rocks_seen": seen_rocks,
               "early_s": float(np.mean(times[:kk])), "late_s": float(np.mean(times[-kk:])),
               "linked_mean": float(np.mean([r["linked"] for r in records[1:]])), "purity": purity(truth, labels),
               "peak_rss_mb": _peak_rss_mb(),
               "map_mb": sum(p.stat().st_size for p in work.glob("contiguous.map*")) / 2**20}
    summary["ratio"] = summary["late_s"] / summary["early_s"]
    # The first scans link fewer stored views than later ones (max_linked_views caps them): the same
    # comparison among the scans that link the most.
    most = max(r["linked"] for r in records)
    full = [r["seconds"] for r in records if r["linked"] == most]
    kk = max(1, min(5, len(full) // 3))
    summary.update(full_linked=most, full_early_s=float(np.mean(full[:kk])), full_late_s=float(np.mean(full[-kk:])))
    summary["full_ratio"] = summary["full_late_s"] / summary["full_early_s"]
    summary.update(one_shot=None, agreement=None, peak_rss_mb_with_one_shot=None)
    if len(segments) <= ShadowCorrConfig().max_segments:  # the whole field at once, where one run may take it
        whole = SceneBundle(units="cm", views=[v for s in scans for v in s.views], name="field",
                            ground_truth="instance")
        result = correspond(whole, model)
        summary["one_shot"] = purity(np.array([s.instance for s in result.segments]),
                                     np.array([s.object for s in result.segments]))
        one = {(s.view, s.instance, s.component): s.object for s in result.segments}
        keys = [(s.view, s.instance, s.component) for s in segments]
        common = [i for i, key in enumerate(keys) if key in one]
        summary["agreement"] = purity(np.array([one[keys[i]] for i in common]), labels[common])
        summary["peak_rss_mb_with_one_shot"] = _peak_rss_mb()
    plot(records, out / "map_contiguous.png")
    return {"records": records, "summary": summary}


#: Tiles lie 1 km apart (no view sees another tile) and a tile's mask ids are shifted by this much.
TILE_SPACING = 100_000.0
TILE_IDS = 1000


def summarize_field(records: list[dict]) -> dict:
    out = {}
    for half, name in ((0, "first"), (1, "second")):
        times = [r["seconds"] for r in records if r["half"] == half]
        k = max(1, min(5, len(times) // 3))
        out[f"{name}_early_s"], out[f"{name}_late_s"] = float(np.mean(times[:k])), float(np.mean(times[-k:]))
        out[f"{name}_ratio"] = out[f"{name}_late_s"] / out[f"{name}_early_s"]
        out[f"{name}_slope_ms_per_100_objects"] = float(np.polyfit(
            [r["objects"] for r in records if r["half"] == half], times, 1)[0] * 1e5) if len(times) > 1 else 0.0
    return out


def plot(records: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for half, label in ((0, "a tile's first scan (no stored view linked)"), (1, "its second scan (4 linked)")):
        rows = [r for r in records if r["half"] == half]
        ax.plot([r["objects"] for r in rows], [r["seconds"] for r in rows], "o-", ms=3, label=label)
    ax.set_xlabel("objects in the map after the update")
    ax.set_ylabel("update time (s, wall)")
    ax.set_ylim(bottom=0)
    ax.set_title("SiteMap.add: 4-view scans of a tiled field")
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--part", choices=["real", "field", "both", "contiguous"], default="both")
    p.add_argument("--stops", default="5x10", help="contiguous field: rows x columns of stops (4 views each)")
    p.add_argument("--max-linked", type=int, default=32, help="contiguous field: SiteMap max_linked_views")
    p.add_argument("--field-seeds", type=int, default=2, help="draws of the field errors on the real scene")
    p.add_argument("--tiles", type=int, default=25, help="tiles of the field (20 rocks each)")
    p.add_argument("--tile-noise", default=None, help="a bench_quality perturbation per tile (e.g. mild); default none")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default="out/bench_map")
    args = p.parse_args(argv)

    import torch

    from shadowcorr import load_model

    torch.set_num_threads(args.threads)
    model = load_model()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if args.part in ("real", "both"):
            rows = real_scene(model, args.field_seeds, work)
            report["real"] = rows
            for condition in dict.fromkeys(r["condition"] for r in rows):
                mine = [r for r in rows if r["condition"] == condition]
                print(f"{condition}: map purity min {min(r['purity'] for r in mine):.2f} / mean "
                      f"{np.mean([r['purity'] for r in mine]):.2f}, one-shot {mine[0]['one_shot']:.2f}, agreement min "
                      f"{min(r['agreement'] for r in mine):.2f} / mean {np.mean([r['agreement'] for r in mine]):.2f} "
                      f"(one-shot reordered: min {min(r['one_shot_reordered'] for r in mine):.2f}),\n  ids kept min "
                      f"{min(r['kept'] for r in mine):.2f} %, "
                      f"unexplained id changes {sum(r['unexplained'] for r in mine)}, revisit min "
                      f"{min(r['revisit'] for r in mine):.2f} %")
        if args.part in ("field", "both"):
            field = tiled_field(model, args.tiles, args.tile_noise, work, out)
            report["field"] = field
            s = field["summary"]
            print(f"field: {s['rocks']} rocks, {s['scans']} scans; first scans {s['first_early_s']:.2f} -> "
                  f"{s['first_late_s']:.2f} s (x{s['first_ratio']:.2f}), second scans {s['second_early_s']:.2f} -> "
                  f"{s['second_late_s']:.2f} s (x{s['second_ratio']:.2f}); map file {s['map_mb']:.1f} MB; peak RSS "
                  f"{s['peak_rss_mb']:.0f} MB; purity {s['purity']:.2f} (tiles alone {s['tiles_alone']:.2f}); "
                  f"plot {out / 'map_updates.png'}")
        if args.part == "contiguous":
            rows, cols = (int(x) for x in args.stops.split("x"))
            field = contiguous_field(model, (rows, cols), work, out, args.max_linked)
            report["contiguous"] = field
            s = field["summary"]
            print(f"contiguous field: {s['rocks_seen']} rocks seen ({s['rocks_placed']} placed), {s['views']} views in "
                  f"{s['stops']} scans of 4 ({s['segments']} segments), {s['linked_mean']:.1f} stored views linked per "
                  f"scan; updates {s['early_s']:.2f} -> {s['late_s']:.2f} s (x{s['ratio']:.2f}), those linking "
                  f"{s['full_linked']} views {s['full_early_s']:.2f} -> {s['full_late_s']:.2f} s "
                  f"(x{s['full_ratio']:.2f}); map file "
                  f"{s['map_mb']:.1f} MB; peak RSS {s['peak_rss_mb']:.0f} MB; purity {s['purity']:.2f}")
            if s["one_shot"] is not None:
                print(f"  all views at once: purity {s['one_shot']:.2f}, agreement with the map {s['agreement']:.2f}, "
                      f"peak RSS then {s['peak_rss_mb_with_one_shot']:.0f} MB")
            else:
                print("  all views at once: more segments than one run takes (max_segments); not run")
    (out / "bench_map.json").write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
