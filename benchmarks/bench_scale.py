"""How the default (``fused``) method's cost grows with the size of the field.

    python benchmarks/bench_scale.py [--copies 1,5,25,50] [--cameras 0,2,4,6] [--threads 1] [--out out]
    python benchmarks/bench_scale.py --source synthetic --copies 1,5,25   # distinct synthetic tiles
    python benchmarks/bench_scale.py --source synthetic --tile-rocks 50 --copies 10   # 500 rocks, 40 views
    python benchmarks/bench_scale.py --embedding --copies 1,5,25   # segment-id embedding scopes only

Large fields are built by tiling scenes on a square grid: every tile keeps its own views,
their poses shifted by the tile's offset, and its mask ids shifted so that each tile's rocks
are distinct objects.  Tiles lie ``--spacing`` apart (default 1 km), far enough that no
tile's views see another tile's rocks, so the ideal result is each tile's own.  The tiles
are copies of the real sample scene (``--source sample``: examples/ue_sample, ``--cameras``)
or distinct synthetic scenes (``--source synthetic``: ``shadowcorr synth`` defaults, 18-20
rocks seen by 4 cameras at 1080p, generator seeds 9101/i, cached under ``--cache``; needs
the ``synth`` extra; ``--tile-rocks N`` puts N rocks in each tile, on a disc and under a camera
ring grown to keep the density and viewing angles).  For synthetic fields the quality column compares the field with its
tiles labelled one by one.

Each field size runs in a fresh process (clean peak memory) with ``num_threads`` and torch's
threads = ``--threads`` (1 by default, as in the service's workers; ``--threads 2`` uses two
cores for the stages and the network).  Printed per size: rocks, views, segments, objects found,
wall time per stage (``result.timings_ms``), the CPU time of the whole call (less
sensitive than wall time to other work on a shared machine), peak resident memory of the process (and
of the decoded input alone), and the average purity next to the single scene's.  At the
end: the growth exponent (least-squares slope of log total time against log rocks, wall and CPU) and a
log-log plot ``scale.png`` under ``--out``.  ``--docs`` also writes the rows as a Markdown table
(default ``docs/benchmarks/tables/scale-sample.md`` or ``scale-synthetic.md``), which the
documentation's scaling page includes, so that no figure is typed by hand.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

SAMPLE = Path(__file__).resolve().parents[1] / "examples" / "ue_sample"  # ships with the repository
DOCS_TABLES = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "tables"  # scale-<source>.md


def tile_scene(bases: list, spacing: float):
    """The scenes ``bases`` on a square grid ``spacing`` (bundle units) apart, as one bundle."""
    from shadowcorr import SceneBundle

    side = math.ceil(math.sqrt(len(bases)))
    id_stride = 1 + max(int(v.mask.max()) for base in bases for v in base.views)
    views, seen = [], set()
    for c, base in enumerate(bases):
        # A scene tiled again gets its own copy of the depth (a field holds as much as it shows);
        # distinct scenes hand theirs over (no second copy of the input at the peak).
        views += place_tile(base, c, side, spacing, id_stride, copy_depth=id(base) in seen)
        seen.add(id(base))
    return SceneBundle(units=bases[0].units, views=views, name=f"field_x{len(bases)}",
                       ground_truth=bases[0].ground_truth)


def place_tile(base, c: int, side: int, spacing: float, id_stride: int, copy_depth: bool = False) -> list:
    """The views of ``base`` as tile ``c`` of a grid ``side`` tiles wide: poses shifted by the tile's
    offset, mask ids by ``c * id_stride`` (so each tile's rocks are objects of their own), names
    prefixed ``tile{c}_``."""
    from shadowcorr import View

    offset = np.array([(c % side) * spacing, (c // side) * spacing, 0.0])
    views = []
    for v in base.views:
        pose = v.pose.copy()
        pose[:3, 3] += offset
        # Widened first: masks come as stored (uint8 / uint16), and shifted ids outgrow them.
        mask = np.where(v.mask > 0, v.mask.astype(np.int32) + c * id_stride, 0)
        views.append(View(name=f"tile{c}_{v.name}", pose=pose, intrinsics=v.intrinsics,
                          depth=v.depth.copy() if copy_depth else v.depth, mask=mask))
    return views


#: Generator seed of the synthetic tiles (tile i: scene_seed(SYNTH_SEED, i)); training never saw it.
SYNTH_SEED = 9101


def tile_config(rocks: int | None):
    """The generator's settings for one synthetic tile: its defaults (18-20 rocks), or ``rocks``
    rocks with the field's disc, the camera ring and its height grown by sqrt(rocks / 19), so the
    rocks lie as densely and are seen from the same angles as in the default tile."""
    from shadowcorr.synth import SynthConfig

    if rocks is None:
        return SynthConfig()
    base, grow = SynthConfig(), math.sqrt(rocks / 19.0)
    return SynthConfig(n_rocks=(rocks, rocks), field_radius=base.field_radius * grow, radius=base.radius * grow,
                       camera_height=base.camera_height * grow)


def synthetic_tiles(count: int, cache: Path, rocks: int | None = None) -> list:
    """``count`` distinct synthetic scenes (``tile_config(rocks)``), generated once into ``cache``
    (a sub-folder per rock count)."""
    from shadowcorr import load_bundle
    from shadowcorr.synth import generate_scene, scene_seed
    from shadowcorr.io import write_bundle

    folder = cache if rocks is None else cache / f"rocks_{rocks}"
    tiles = []
    for i in range(count):
        path = folder / f"scene_{i:05d}"
        if not (path / "manifest.json").exists():
            write_bundle(generate_scene(tile_config(rocks), scene_seed(SYNTH_SEED, i)), path)
        tiles.append(load_bundle(path))
    return tiles


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux reports KiB


def run_one(copies: int, cameras: list[int], spacing: float, threads: int, data: str, source: str,
            cache: Path, tile_rocks: int | None = None) -> dict:
    """Label one tiled field in this process; returns its figures."""
    import torch

    from shadowcorr import ShadowCorrConfig, correspond, load_model
    from shadowcorr.convert import load_ue_scene
    from shadowcorr.ops import resolve_threads

    config = ShadowCorrConfig(num_threads=threads)
    torch.set_num_threads(resolve_threads(threads))
    model = load_model()
    if source == "sample":
        base = load_ue_scene(data, 2001, cameras)
        bases = [base] * copies
    else:
        bases = synthetic_tiles(copies, cache, tile_rocks)
        base = bases[0]
    correspond(base, model, config)  # warm-up: lazy imports and first-call allocations
    bundle = tile_scene(bases, spacing)
    del bases, base
    input_mb = sum(v.depth.nbytes + v.mask.nbytes for v in bundle.views) / 2**20
    rocks = len({int(i) for v in bundle.views for i in np.unique(v.mask) if i > 0})
    views = len(bundle.views)
    before = _peak_rss_mb()
    t0, cpu0 = time.perf_counter(), time.process_time()
    result = correspond(bundle, model, config, metrics=True)
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    peak = _peak_rss_mb()
    alone = None
    if source == "synthetic":  # the ideal: every tile labelled on its own (after the field: its peak is measured)
        del bundle
        alone = float(np.mean([correspond(b, model, config, metrics=True).metrics["average_purity"]
                               for b in synthetic_tiles(copies, cache, tile_rocks)]))
    return {
        "copies": copies,
        "rocks": rocks,
        "views": views,
        "segments": len(result.segments),
        "objects": len(result.objects),
        "wall_s": wall,
        "cpu_s": cpu,
        "stages_ms": result.timings_ms,
        "peak_rss_mb": peak,
        "rss_before_mb": before,
        "input_mb": input_mb,
        "average_purity": result.metrics["average_purity"],
        "tiles_alone_purity": alone,
    }


def compare_embedding_scopes(copies: list[int], cameras: list[int], data: str) -> None:
    """CPU time of the segment-id embeddings, per component and whole-scene, on the sample scene's
    co-occurrence repeated block-diagonally (what a tiled field's co-occurrence is)."""
    from scipy.sparse import block_diag

    from shadowcorr import ShadowCorrConfig, prepare
    from shadowcorr.convert import load_ue_scene
    from shadowcorr.stages import cooccurrence, train_segment_embeddings

    scene = prepare(load_ue_scene(data, 2001, cameras))
    cooc = cooccurrence(scene.member_voxel, scene.member_segment, scene.num_voxels, scene.num_segments)
    centroid = np.nan_to_num(scene.segment_centroid)
    for n in copies:
        field = block_diag([cooc] * n).tocsr()
        centroids = np.concatenate([centroid + [1e5 * i, 0.0, 0.0] for i in range(n)])
        for scope in ("component", "scene"):
            cpu0 = time.process_time()
            train_segment_embeddings(field, centroids, ShadowCorrConfig(segment_embedding_scope=scope))
            print(f"segment embeddings, {field.shape[0]:5d} segments, scope {scope:9s}: "
                  f"{time.process_time() - cpu0:.2f} s CPU", flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--copies", default="1,5,25,50", help="tiles per field")
    parser.add_argument("--source", choices=("sample", "synthetic"), default="sample",
                        help="tiles: copies of the real sample scene, or distinct synthetic scenes")
    parser.add_argument("--cache", default="out/scale_synth", help="generated synthetic tiles (--source synthetic)")
    parser.add_argument("--tile-rocks", type=int, default=None, help="rocks per synthetic tile (default: the "
                        "generator's 18-20; more spread the tile and its cameras to keep the density)")
    parser.add_argument("--cameras", default="0,2,4,6")
    parser.add_argument("--spacing", type=float, default=100000.0, help="distance between copies (bundle units)")
    parser.add_argument("--threads", type=int, default=1, help="num_threads of the configuration and torch's "
                        "threads (0: every core; the service's workers use 1)")
    parser.add_argument("--data", default=str(SAMPLE))
    parser.add_argument("--out", default="out")
    parser.add_argument("--embedding", action="store_true", help="only compare the segment-id embedding scopes")
    parser.add_argument("--docs", nargs="?", const="", default=None, metavar="PATH",
                        help="also write the rows as a Markdown table (default docs/benchmarks/tables/scale-<source>.md)")
    parser.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)  # child process mode
    args = parser.parse_args()
    cameras = [int(c) for c in args.cameras.split(",")]
    if args.embedding:
        compare_embedding_scopes([int(c) for c in args.copies.split(",")], cameras, args.data)
        return 0
    if args.one is not None:
        print(json.dumps(run_one(args.one, cameras, args.spacing, args.threads, args.data, args.source,
                                 Path(args.cache), args.tile_rocks)))
        return 0

    load = os.getloadavg()[0]
    rows = []
    for copies in [int(c) for c in args.copies.split(",")]:
        cmd = [sys.executable, __file__, "--one", str(copies), "--cameras", args.cameras, "--spacing",
               str(args.spacing), "--threads", str(args.threads), "--data", args.data, "--source", args.source,
               "--cache", args.cache] + ([] if args.tile_rocks is None else ["--tile-rocks", str(args.tile_rocks)])
        out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
        row = json.loads(out.strip().splitlines()[-1])
        rows.append(row)
        stages = ", ".join(f"{k} {v / 1e3:.2f}" for k, v in row["stages_ms"].items() if k != "total")
        print(f"{row['rocks']:5d} rocks {row['views']:4d} views {row['segments']:5d} segments {row['objects']:4d} objects: "
              f"{row['wall_s']:7.2f} s wall ({row['cpu_s']:.2f} s CPU), peak RSS {row['peak_rss_mb']:7.0f} MB (input {row['input_mb']:.0f} MB, "
              f"before labelling {row['rss_before_mb']:.0f} MB), purity {row['average_purity']:.4f}"
              + (f" (tiles alone {row['tiles_alone_purity']:.4f})" if row["tiles_alone_purity"] is not None else "")
              + f"  [{stages} s]",
              flush=True)

    single = next((r["average_purity"] for r in rows if r["copies"] == 1), None)
    if single is not None:
        worst = min(r["average_purity"] for r in rows)
        print(f"quality: single scene {single:.4f}, lowest tiled {worst:.4f}")
    if len(rows) >= 2:
        x = np.log([r["rocks"] for r in rows])
        slope, intercept = np.polyfit(x, np.log([r["wall_s"] for r in rows]), 1)
        cpu_slope = np.polyfit(x, np.log([r["cpu_s"] for r in rows]), 1)[0]
        print(f"growth exponent (log total time vs log rocks): wall {slope:.3f}, CPU {cpu_slope:.3f}")
        _plot(rows, slope, intercept, Path(args.out) / "scale.png")
    if args.docs is not None:
        path = Path(args.docs) if args.docs else DOCS_TABLES / f"scale-{args.source}.md"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(docs_table(args, rows, load))
        print(f"wrote {path}")
    return 0


def docs_table(args: argparse.Namespace, rows: list[dict], load: float) -> str:
    """The run's rows as Markdown, with the release, the machine, its load and the command."""
    import torch

    from shadowcorr import __version__

    command = " ".join(["python benchmarks/bench_scale.py", "--copies", args.copies, "--threads", str(args.threads)]
                       + ([] if args.source == "sample" else ["--source", args.source])
                       + ([] if args.tile_rocks is None else ["--tile-rocks", str(args.tile_rocks)]) + ["--docs"])
    lines = [f"ShadowCorr {__version__}; {platform.machine()} with {os.cpu_count()} cores, torch {torch.__version__}; "
             f"load average {load:.1f} before the run; one run: `{command}`.", "",
             "| tiles | rocks | views | segments | wall | CPU | peak RSS (of it, decoded input) | average purity |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        alone = f" (alone: {r['tiles_alone_purity']:.3f})" if r["tiles_alone_purity"] is not None else ""
        lines.append(f"| {r['copies']} | {r['rocks']:,} | {r['views']} | {r['segments']:,} | {r['wall_s']:.2f} s | "
                     f"{r['cpu_s']:.2f} s | {r['peak_rss_mb'] / 1024:.2f} GB ({r['input_mb'] / 1024:.1f} GB) | "
                     f"{r['average_purity']:.3f}{alone} |")
    if len(rows) >= 2:
        x = np.log([r["rocks"] for r in rows])
        lines += ["", f"Growth exponent of the wall time against the rocks: "
                      f"{np.polyfit(x, np.log([r['wall_s'] for r in rows]), 1)[0]:.2f}."]
    return "\n".join(lines) + "\n"


def _plot(rows: list[dict], slope: float, intercept: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    rocks = np.array([r["rocks"] for r in rows], dtype=float)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.loglog(rocks, [r["wall_s"] for r in rows], "o-", label="total")
    for stage in ("poses", "segments", "surface_evidence", "shells", "shadows", "segment_embedding", "network", "grouping"):
        ax.loglog(rocks, [max(r["stages_ms"].get(stage, 0.0), 1e-3) / 1e3 for r in rows], ".--", label=stage)
    ax.loglog(rocks, np.exp(intercept) * rocks**slope, ":", color="k", label=f"fit: rocks^{slope:.2f}")
    ax.set_xlabel("rocks (tiled scenes)")
    ax.set_ylabel("seconds")
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"plot: {path}")


if __name__ == "__main__":
    sys.exit(main())
