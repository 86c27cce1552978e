"""How close each object's oriented box and volume come to the true rock, on synthetic scenes.

Usage: python benchmarks/bench_geometry.py [--scenes 10] [--seed 0] [--cameras 4] [--method fused]
                                           [--condition NAME] [--misses] [--sample]
                                           [--docs [PATH]] [--docs-conditions clean,mixed-edges,field]

Every scene is generated (``shadowcorr.synth``, numpy rasteriser, exact images), optionally
perturbed (``--condition``: one of the quality benchmark's perturbations or combined error
levels by name, e.g. ``mixed-edges`` or ``field``, with the quality benchmark's fixed seeds;
``--list`` names them) and run through ``correspond``.  Each object is matched to the rock
most of its points come from (the bundle's ground truth of each segment) and compared with
that rock's mesh:

* **box ratio**: the volume of the object's oriented box over the volume of the same
  construction on the rock's mesh vertices (a box turned about z along a side of the
  smallest-area rectangle around the vertices' footprint, spanning the vertices), and over
  the rock's axis-aligned box;
* **volume ratio**: the object's ``volume`` over the rock's mesh volume, for rocks seen
  from at least ``--min-views`` views (default 3).  A rock sits up to ``sink_depth`` (5 cm)
  in uneven ground: the part below the ground surface is in the mesh volume but in no view.

It prints one row per scene and the distribution (min, 5 / 25 / 50 / 75 / 95 %, max) of
each ratio, with the share of objects within 1.5x (box) and within +-30 % (volume).
``--misses`` lists every object outside either tolerance with what may explain it: the
rock's diameter and its mask pixels in each view, the share of the object's points that
come from its rock (below 1: a merge), and how many objects share the rock (above 1: a
split), and for a volume outside its tolerance where the rock's volume went (:func:`volume_budget`:
the shares of the mesh volume that no shadow reaches, that one view's background alone rules out,
that the views rule out, and that another object owns, and the object's volume from outside the
mesh).  ``--sample`` also prints the sample scene's objects (no meshes there: boxes, volumes
and the volume / box ratio, which for a rock lies well below 1).

``--docs`` runs the scenes once per condition of ``--docs-conditions`` (``clean``: exact
images) instead of ``--condition`` and writes the distributions as a Markdown table (default
``docs/benchmarks/tables/geometry.md``, which the exports guide includes), with the release,
the machine and the command.  Nothing here is timed.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np

from shadowcorr import ShadowCorrConfig, __version__, assign, embed, load_model, prepare
from shadowcorr.bundle import unit_scale
from shadowcorr.ops import NOISE_ROW_STEP, pack_cell_keys, relative_depth_noise
from shadowcorr.config import NETWORK_METHODS
from shadowcorr.stages import baseline_embeddings, oriented_boxes
from shadowcorr.stages._05_occupancy import _background_counts
from shadowcorr.synth import SynthConfig, scene_seed
from shadowcorr.synth.generate import synthesize

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_quality  # noqa: E402  (the perturbation catalogue and its seeds)

CONDITIONS = (*bench_quality.PERTURBATIONS, *bench_quality.COMBINED)
DOCS_TABLE = REPO / "docs" / "benchmarks" / "tables" / "geometry.md"


def _quantiles(values: np.ndarray) -> str:
    if values.size == 0:
        return "(none)"
    q = np.quantile(values, [0.0, 0.05, 0.25, 0.5, 0.75, 0.95, 1.0])
    return " / ".join(f"{x:.2f}" for x in q)


def true_boxes(scene) -> tuple[np.ndarray, np.ndarray]:
    """Oriented-box and axis-aligned-box volumes of every rock's mesh, in the world frame."""
    vertices = [rock.vertices @ scene.rotations[i].T + scene.translations[i] for i, rock in enumerate(scene.rocks)]
    points = np.concatenate(vertices)
    owner = np.repeat(np.arange(len(vertices)), [len(v) for v in vertices])
    _, size, _ = oriented_boxes(points, owner, len(vertices), (2, 1.0))
    aligned = np.array([np.prod(v.max(axis=0) - v.min(axis=0)) for v in vertices])
    return size.prod(axis=1), aligned


def scene_bundle(seed: int, cameras: int, condition: str | None):
    """The generated scene, its bundle perturbed by ``condition`` (the quality benchmark's seed for
    it) and the masks the perturbation drew over several rocks."""
    scene = synthesize(SynthConfig(renderer="raster", cameras=cameras), seed)
    merged: dict = {}
    if condition is None:
        return scene, scene.bundle, merged
    key = f"syn:{cameras}v/{seed}"
    bundle = bench_quality.perturb(scene.bundle, condition, bench_quality.perturbation_seed(key, condition, 0), merged)
    return scene, bundle, merged


def compare(scene, bundle, result, seed: int, merged: dict | None = None) -> list[dict]:
    """One row per object of ``result``: its box and volume against its rock's mesh (``merged``: the
    masks drawn over several rocks, whose blobs are scored by the rock under their own pixels)."""
    box_true, box_aligned = true_boxes(scene)
    mesh_volume = np.array([r["volume"] for r in scene.truth["rocks"]])
    # Rock id (1-based) of every segment, -1 none.
    truth = bench_quality.segment_truth(bundle, result, scene.bundle, merged)
    points = np.array([s.num_points for s in result.segments], dtype=np.float64)
    objects_of_rock: dict[int, set[int]] = {}
    for s, seg in enumerate(result.segments):
        if seg.object >= 0 and truth[s] > 0:
            objects_of_rock.setdefault(int(truth[s]), set()).add(seg.object)
    rows = []
    for obj in result.objects:
        segs = np.asarray(obj.segments, dtype=np.int64)
        ids = truth[segs]
        weights = np.bincount(np.maximum(ids, 0), weights=points[segs])
        weights[0] = 0.0  # segments without a rock
        if weights.sum() == 0:
            continue  # an object of spurious segments only: no rock to compare with
        rock = int(np.argmax(weights)) - 1
        box = obj.oriented_box
        pixels = scene.truth["rocks"][rock]["pixels"]
        rows.append({
            "scene": seed, "object": obj.object, "rock": rock + 1, "views": obj.num_views,
            "diameter": scene.truth["rocks"][rock]["diameter"], "pixels": pixels,
            "purity": float(weights.max() / weights.sum()), "objects": len(objects_of_rock.get(rock + 1, ())),
            "box_ratio": np.prod(box.size) / box_true[rock] if box else np.nan,
            "aligned_ratio": np.prod(box.size) / box_aligned[rock] if box else np.nan,
            "volume_ratio": obj.volume / mesh_volume[rock] if obj.volume is not None else np.nan,
            "volume_z": (obj.volume - mesh_volume[rock]) / obj.volume_std if obj.volume_std else np.nan,
        })
    return rows


def measure(seed: int, cameras: int, method: str, condition: str | None = None,
            budget_min_views: int | None = None) -> list[dict]:
    """The rows of :func:`compare` for one generated scene; with ``budget_min_views``, every row of a
    rock seen from that many views whose volume misses the tolerance gets its :func:`volume_budget`."""
    scene, bundle, merged = scene_bundle(seed, cameras, condition)
    config = ShadowCorrConfig(method=method)
    prepared, result = labelled(bundle, config)
    rows = compare(scene, bundle, result, seed, merged)
    if budget_min_views is not None:
        for row in rows:
            if row["views"] >= budget_min_views and not _within_volume(np.array([row["volume_ratio"]]))[0]:
                row["budget"] = volume_budget(scene, bundle, prepared, result, row, config)
    return rows


def labelled(bundle, config: ShadowCorrConfig):
    """``correspond``, keeping the prepared scene (the volume budget reads its occupancy)."""
    prepared = prepare(bundle, config)
    if config.method in NETWORK_METHODS:
        (embeddings,) = embed(load_model(), [prepared])
    else:
        embeddings = baseline_embeddings(prepared)
    return prepared, assign(prepared, embeddings, config, metrics=False)


def inside_mesh(points: np.ndarray, triangles: np.ndarray, chunk: int = 512) -> np.ndarray:
    """Whether each point lies inside the closed, outward-wound triangle mesh (generalised winding
    number: the solid angles of the triangles seen from the point sum to 4 pi inside, 0 outside)."""
    inside = np.zeros(points.shape[0], dtype=bool)
    for lo in range(0, points.shape[0], chunk):
        a, b, c = (triangles[None, :, i] - points[lo:lo + chunk, None] for i in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        dot = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", b, c) * la
               + np.einsum("pfi,pfi->pf", c, a) * lb)
        inside[lo:lo + chunk] = np.arctan2(det, dot).sum(axis=1) > np.pi  # winding number > 1/2
    return inside


def volume_budget(scene, bundle, prepared, result, row: dict, config: ShadowCorrConfig) -> dict[str, float]:
    """Where the rock's volume goes, as shares of its mesh volume (ground truth: a benchmark only).

    The occupancy's sub-cell samples that lie inside the rock's mesh are sorted into: reached by no
    shadow (``unreached``: the occupancy never tests them; most often the rock's lower part, below
    where its shadows end), ruled out by one view's background alone (``one_view``: that view sees
    ground or an unlabelled pixel in front of them, and they count half), ruled out (``ruled_out``:
    a view sees past them, or two views see background in front: the part sunk below the visible
    ground), and solid but owned by another object (``other``).  ``outside`` is the volume of the
    object's solid samples outside the mesh, over the mesh volume (space behind the rock that no
    view rules out).
    """
    occupancy = prepared.occupancy
    k = row["rock"] - 1
    rock = scene.rocks[k]
    vertices = rock.vertices @ scene.rotations[k].T + scene.translations[k]
    scale = config.voxel_size / unit_scale(bundle.units, config.units)
    n = config.volume_subdivisions
    offsets = (np.arange(n) + 0.5) / n - 0.5
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    axes = []
    for d in range(3):
        cells = np.arange(np.floor(lo[d] / scale) - 1, np.ceil(hi[d] / scale) + 2)
        coords = ((cells[:, None] + offsets[None]) * scale).ravel()
        axes.append(coords[(coords >= lo[d]) & (coords <= hi[d])])
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    points = grid[inside_mesh(grid, vertices[rock.faces])]
    if points.shape[0] == 0 or occupancy is None:
        return {}
    views = bundle.views
    noise = np.array([relative_depth_noise(v.depth[::NOISE_ROW_STEP]) for v in views])
    reach = config.max_depth / unit_scale(bundle.units, config.units)
    smoothed = noise * reach * reach > 0.1 * scale / n
    background = _background_counts(views, points, np.zeros((1, 3)), reach, noise, smoothed,
                                    config.volume_mask_margin)[:, 0]
    cell = np.floor(points / scale + 0.5).astype(np.int64)  # a sample's voxel (centre = cell * scale)
    both, _ = pack_cell_keys(np.zeros(occupancy.cell.shape[0] + cell.shape[0]), np.concatenate([occupancy.cell, cell]))
    occ_key, sample_key = both[:occupancy.cell.shape[0]], both[occupancy.cell.shape[0]:]
    order = np.argsort(occ_key)
    index = order[np.clip(np.searchsorted(occ_key[order], sample_key), 0, occ_key.size - 1)]
    in_occupancy = occ_key[index] == sample_key
    ruled_out = (background < 0) | (background >= 2)
    seg_object = np.array([s.object for s in result.segments])
    owner = np.where(in_occupancy, seg_object[occupancy.segment[index]], -1)
    kept = in_occupancy & ~ruled_out
    # the object's solid samples that lie outside the mesh
    owned = np.flatnonzero(seg_object[occupancy.segment] == row["object"])
    cell_row, which = np.nonzero(occupancy.solid_samples[owned])
    solid = (occupancy.cell[owned][cell_row] + occupancy.offsets[which]) * scale
    outside = (~inside_mesh(solid, vertices[rock.faces])).sum() * (scale / n) ** 3 / rock.volume
    return {
        "unreached": float(np.mean(~in_occupancy & ~ruled_out)),
        "one_view": float(np.mean(~ruled_out & (background == 1))),
        "ruled_out": float(np.mean(ruled_out)),
        "other": float(np.mean(kept & (owner != row["object"]))),
        "outside": float(outside),
    }


def sample(method: str) -> None:
    from shadowcorr.convert.ue import load_ue_scene

    _, result = labelled(load_ue_scene(REPO / "examples" / "ue_sample", "2001", [0, 2, 4, 6]),
                         ShadowCorrConfig(method=method))
    print(f"\nsample scene (Set2001, cameras 0,2,4,6, {method}): {len(result.objects)} objects")
    print("| object | views | points | box size cm | volume cm^3 | std | volume / box |")
    print("|---|---|---|---|---|---|---|")
    for o in result.objects:
        size = o.oriented_box.size if o.oriented_box else None
        ratio = o.volume / np.prod(size) if size and o.volume is not None else float("nan")
        print(f"| {o.object} | {o.num_views} | {o.num_points} | {size} | {o.volume} | {o.volume_std} | {ratio:.2f} |")


def misses(rows: list[dict], min_views: int) -> None:
    """Every object outside a tolerance, with the facts that may explain it."""
    print("\n| scene | rock | diameter | mask pixels per view | views | purity | objects of the rock | box ratio "
          "| volume ratio | of the mesh volume: no shadow · one view's background · ruled out · another object's "
          "| the object's solid volume outside the mesh |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        box_off = not (np.isfinite(r["box_ratio"]) and 1 / 1.5 <= r["box_ratio"] <= 1.5)
        vol_off = r["views"] >= min_views and not _within_volume(np.array([r["volume_ratio"]]))[0]
        if box_off or vol_off:
            pixels = ",".join(str(p) for p in r["pixels"].values()) or "0"
            budget = r.get("budget") or {}
            shares = (" · ".join(f"{budget[k]:.2f}" for k in ("unreached", "one_view", "ruled_out", "other"))
                      if budget else "")
            outside = f"{budget['outside']:.2f}" if budget else ""
            print(f"| {r['scene']} | {r['rock']} | {r['diameter']:.0f} | {pixels} | {r['views']} | {r['purity']:.2f} "
                  f"| {r['objects']} | {r['box_ratio']:.2f}{' *' if box_off else ''} "
                  f"| {r['volume_ratio']:.2f}{' *' if vol_off else ''} | {shares} | {outside} |")


def _within_box(ratio: np.ndarray) -> np.ndarray:
    return np.isfinite(ratio) & (ratio <= 1.5) & (ratio >= 1 / 1.5)


def _within_volume(ratio: np.ndarray) -> np.ndarray:
    return np.isfinite(ratio) & (np.abs(ratio - 1) <= 0.3)


def run(args: argparse.Namespace, condition: str | None) -> list[dict]:
    """Every object of ``args.scenes`` scenes under ``condition``, printing a row per scene."""
    rows = []
    print(f"\n{condition or 'clean'}")
    print("| scene seed | objects | box ratio median | volume ratio median (>= %d views) |" % args.min_views)
    print("|---|---|---|---|")
    for i in range(args.scenes):
        seed = scene_seed(args.seed, i)
        scene_rows = measure(seed, args.cameras, args.method, condition, args.min_views if args.misses else None)
        rows += scene_rows
        box = np.array([r["box_ratio"] for r in scene_rows])
        vol = np.array([r["volume_ratio"] for r in scene_rows if r["views"] >= args.min_views])
        print(f"| {seed} | {len(scene_rows)} | {np.nanmedian(box):.3f} | {np.nanmedian(vol):.3f} |", flush=True)
    return rows


def report(args: argparse.Namespace, condition: str | None, rows: list[dict]) -> None:
    """The distributions of the ratios over ``rows``."""
    box = np.array([r["box_ratio"] for r in rows])
    aligned = np.array([r["aligned_ratio"] for r in rows])
    seen = [r for r in rows if r["views"] >= args.min_views]
    vol = np.array([r["volume_ratio"] for r in seen])
    z = np.array([r["volume_z"] for r in seen])
    print(f"\n{len(rows)} objects in {args.scenes} scenes ({args.cameras} cameras, method {args.method}, "
          f"{condition or 'clean'}); {len(seen)} seen from >= {args.min_views} views")
    print("distribution: min / 5 % / 25 % / median / 75 % / 95 % / max")
    print(f"box volume / true oriented box     {_quantiles(box[np.isfinite(box)])}")
    print(f"box volume / true axis-aligned box {_quantiles(aligned[np.isfinite(aligned)])}")
    within = _within_box(box)
    print(f"objects with a box within 1.5x of the true oriented box: {within.mean():.1%} "
          f"({int(within.sum())} of {box.size}; without a box: {int((~np.isfinite(box)).sum())}); "
          f"of the true axis-aligned box: {_within_box(aligned).mean():.1%}")
    print(f"volume / mesh volume (>= {args.min_views} views) {_quantiles(vol[np.isfinite(vol)])}")
    near = _within_volume(vol)
    print(f"volumes within +-30 % of the mesh volume: {near.mean():.1%} ({int(near.sum())} of {vol.size}; "
          f"without a volume: {int((~np.isfinite(vol)).sum())})")
    zf = np.abs(z[np.isfinite(z)])
    print(f"|volume - mesh volume| within 1 / 2 volume_std: {np.mean(zf <= 1):.1%} / {np.mean(zf <= 2):.1%}")
    if args.misses:
        misses(rows, args.min_views)


def _spread(values: np.ndarray) -> str:
    values = values[np.isfinite(values)]
    if values.size == 0:
        return "–"
    return " · ".join(f"{x:.2f}" for x in np.quantile(values, [0.05, 0.5, 0.95]))


def docs_table(args: argparse.Namespace, results: dict[str, list[dict]]) -> str:
    """The conditions' distributions as Markdown, with what was measured where."""
    command = f"python benchmarks/bench_geometry.py --scenes {args.scenes} --docs"
    if Path(args.docs).resolve() != DOCS_TABLE:
        command += f" {args.docs}"
    if args.docs_conditions != DOCS_CONDITIONS:
        command += f" --docs-conditions {args.docs_conditions}"
    for flag, value, default in (("--seed", args.seed, 0), ("--cameras", args.cameras, 4),
                                 ("--method", args.method, "fused"), ("--min-views", args.min_views, 3)):
        if value != default:
            command += f" {flag} {value}"
    lines = [
        f"ShadowCorr {__version__}; {platform.machine()} with {os.cpu_count()} cores, "
        f"{platform.python_implementation()} {platform.python_version()}; method `{args.method}`, "
        f"{args.cameras} cameras, {args.scenes} generated scenes per row: `{command}`.  ",
        f"Ratios: 5 % · median · 95 % over the objects; volumes of the rocks seen from at least {args.min_views} "
        "views; the true box is the same construction on the rock's mesh.",
        "",
        f"| condition | objects (≥ {args.min_views} views) | box volume / true box | within 1.5× "
        "| box volume / true axis-aligned box | within 1.5× | volume / mesh volume | within ±30 % "
        "| within 1 · 2 `volume_std` |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, rows in results.items():
        box = np.array([r["box_ratio"] for r in rows])
        aligned = np.array([r["aligned_ratio"] for r in rows])
        seen = [r for r in rows if r["views"] >= args.min_views]
        vol = np.array([r["volume_ratio"] for r in seen])
        z = np.abs(np.array([r["volume_z"] for r in seen]))
        z = z[np.isfinite(z)]
        label = "exact images" if name == "clean" else f"`{name}` ({_describe(name)})"
        lines.append(
            f"| {label} | {len(rows)} ({len(seen)}) | {_spread(box)} | {_percent(_within_box(box))} "
            f"| {_spread(aligned)} | {_percent(_within_box(aligned))} | {_spread(vol)} "
            f"| {_percent(_within_volume(vol))} | {_percent(z <= 1, 0)} · {_percent(z <= 2, 0)} |")
    return "\n".join(lines) + "\n"


def _percent(flags: np.ndarray, digits: int = 1) -> str:
    return f"{100.0 * flags.mean():.{digits}f} %" if flags.size else "–"


def _describe(name: str) -> str:
    entry = bench_quality.PERTURBATIONS.get(name) or bench_quality.COMBINED[name]
    return entry[0]


DOCS_CONDITIONS = "clean,mixed-edges,field"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--method", default="fused", choices=["fused", "shadowcorr", "meanshift"])
    parser.add_argument("--condition", default=None, choices=CONDITIONS, metavar="NAME",
                        help="a perturbation or combined error level of benchmarks/bench_quality.py (--list)")
    parser.add_argument("--list", action="store_true", help="name the conditions and exit")
    parser.add_argument("--min-views", type=int, default=3)
    parser.add_argument("--misses", action="store_true", help="list the objects outside either tolerance")
    parser.add_argument("--sample", action="store_true", help="also list the sample scene's objects")
    parser.add_argument("--docs", nargs="?", const=str(DOCS_TABLE), default=None, metavar="PATH",
                        help=f"run --docs-conditions and write the table (default {DOCS_TABLE.relative_to(REPO)})")
    parser.add_argument("--docs-conditions", default=DOCS_CONDITIONS, metavar="NAMES",
                        help="comma-separated conditions of the --docs table (clean: exact images)")
    args = parser.parse_args()
    if args.list:
        for name in CONDITIONS:
            print(f"{name:<16} {_describe(name)}")
        return

    if args.docs:
        names = args.docs_conditions.split(",")
        unknown = [n for n in names if n != "clean" and n not in CONDITIONS]
        if unknown:
            parser.error(f"unknown conditions: {', '.join(unknown)} (--list names them)")
        results = {}
        for name in names:
            condition = None if name == "clean" else name
            results[name] = run(args, condition)
            report(args, condition, results[name])
        path = Path(args.docs)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(docs_table(args, results))
        print(f"wrote {path}")
    else:
        report(args, args.condition, run(args, args.condition))
    if args.sample:
        sample(args.method)


if __name__ == "__main__":
    sys.exit(main())
