"""Where the default's wrong segments come from: every wrongly placed segment, by what went wrong.

    python benchmarks/bench_errors.py                                   # the combined-error rows of every rig
    python benchmarks/bench_errors.py --conditions 'syn:4v-low+field,real:04+mild' --scenes 10 --show
    python benchmarks/bench_errors.py --docs                            # docs/benchmarks/tables/errors.md

``fused`` labels the quality benchmark's scenes under its perturbations (the same scene cache,
the same perturbation seeds, the same scoring: ``bench_quality.segment_truth`` and
``wrong_segments``), and every wrongly placed segment is put in one of these classes, read
against its rock's *main object* (the object holding most of the rock's segments) and its
object's *main rock*:

* **piece kept apart** - its object's main rock is its own rock, but its object is not the
  rock's main object: the rock fell apart.
  - *its view in the main object*: the main object holds a segment of the piece's view, so
    the view's cannot-link (two mask ids of one view) stood between them - a piece that a
    split mask cut off and that the seams and the other views did not join back;
  - *other views only*: the main object holds none of its view - a side of the rock whose
    points land on no segment of the rock in the other views and whose shadow meets none.
* **rock joined to another** - it sits in its rock's main object, but that object's main rock
  is another: two rocks became one object.
  - *through a merged mask, found* / *not found*: the object holds a mask that the segmenter
    drew over several rocks (the perturbation's own record of its merges), which the grouping
    did / did not read as merged (``group_by_evidence(...).merged``);
  - *no merged mask*: the two rocks were chained by the evidence itself.
* **joined to another rock's object** - its object's main rock is another, and its own rock's
  main object lies elsewhere: this segment alone went wrong.

Each class is counted in segments and in their points (the points are what the average purity
weighs).  ``--show`` lists every wrong segment with its class.  ``--docs`` writes the table
(default ``docs/benchmarks/tables/errors.md``, which the benchmark page includes) with the
release, the machine and the command.  Ground truth is read for scoring only, after the
labels are made.  Nothing here is timed.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_quality  # noqa: E402  (the conditions, the scene cache, the perturbations and the scoring)

DOCS_TABLE = REPO / "docs" / "benchmarks" / "tables" / "errors.md"
DEFAULT_CONDITIONS = "*+mild,*+field,*+harsh"

#: The classes, in table order: (key, column title).
CLASSES: tuple[tuple[str, str], ...] = (
    ("piece_own_view", "piece kept apart: its view in the main object"),
    ("piece_other_views", "piece kept apart: other views only"),
    ("merged_found", "rock joined through a merged mask, found"),
    ("merged_missed", "rock joined through a merged mask, not found"),
    ("chained", "rock joined, no merged mask"),
    ("joined_wrong", "joined to another rock's object"),
)


def classify(truth: np.ndarray, labels: np.ndarray, view: np.ndarray, wrong: np.ndarray,
             drawn_over_rocks: np.ndarray, read_as_merged: np.ndarray) -> list[str]:
    """The class (a key of :data:`CLASSES`) of every segment flagged in ``wrong``, in index order.

    ``truth``: each segment's rock (-1: none); ``labels``: its object; ``view``: its view;
    ``drawn_over_rocks``: whether its mask was drawn over several rocks (the perturbation's
    record); ``read_as_merged``: whether the grouping read it as a merged mask.
    """
    main_rock, main_object = bench_quality.majorities(truth, labels)
    out = []
    for k in np.flatnonzero(wrong):
        rock, obj = int(truth[k]), int(labels[k])
        if main_rock.get(obj) == rock:  # its object is its rock's, but not the rock's main one
            in_main = (labels == main_object[rock]) & (view == view[k])
            out.append("piece_own_view" if in_main.any() else "piece_other_views")
        elif main_object[rock] == obj:  # its rock's main object belongs to another rock
            drawn = (labels == obj) & drawn_over_rocks  # the object's masks drawn over several rocks
            if not drawn.any():
                out.append("chained")
            else:
                out.append("merged_found" if read_as_merged[drawn].any() else "merged_missed")
        else:
            out.append("joined_wrong")
    return out


def run_task(task: Any) -> Any:
    """Every condition of one quality-benchmark task: its wrong segments with their classes, as
    the task's records (run by ``bench_quality.evaluate``, with the model its workers load)."""
    from shadowcorr import ShadowCorrConfig, assign, prepare
    from shadowcorr.stages import embed, group_by_evidence

    config = ShadowCorrConfig()
    records = task.records
    for name, _, _, clean, bundle, merged in bench_quality.task_bundles(task):
        scene = prepare(bundle, config)
        (embeddings,) = embed(bench_quality._MODEL, [scene])
        read_as_merged = group_by_evidence(scene, embeddings, config).merged
        result = assign(scene, embeddings, config)
        truth = bench_quality.segment_truth(bundle, result, clean, merged, config)
        labels = np.array(result.labels, dtype=np.int64)
        wrong = bench_quality.wrong_segments(truth, labels)
        view_index = {v.name: j for j, v in enumerate(bundle.views)}
        view = np.array([view_index[s.view] for s in result.segments], dtype=np.int64)
        drawn = np.array([s.instance in merged.get(s.view, {}) for s in result.segments], dtype=bool)
        points = np.array([s.num_points for s in result.segments], dtype=np.int64)
        for k, kind in zip(np.flatnonzero(wrong), classify(truth, labels, view, wrong, drawn, read_as_merged)):
            records.append({"condition": name, "scene": task.scene_index, "segment": int(k),
                            "view": result.segments[k].view, "points": int(points[k]), "class": kind,
                            "support": result.segments[k].support})
        records.append({"condition": name, "scene": task.scene_index, "segments": int(labels.size),
                        "scored_points": int(points[truth >= 0].sum())})
    return task


def table(records: list[dict[str, Any]], conditions: list[Any]) -> str:
    """Per condition: wrong segments and their share of the scored points, per class."""
    lines = ["| condition | runs | wrong segments (share of points) | "
             + " | ".join(title for _, title in CLASSES) + " |",
             "|---|---|---|" + "---|" * len(CLASSES)]
    for c in conditions:
        rows = [r for r in records if r["condition"] == c.name]
        runs = [r for r in rows if "segments" in r]
        wrong = [r for r in rows if "class" in r]
        total = max(sum(r["scored_points"] for r in runs), 1)
        count, mass = Counter(r["class"] for r in wrong), Counter()
        for r in wrong:
            mass[r["class"]] += r["points"]
        cells = [f"{count[k]} ({100.0 * mass[k] / total:.2f} %)" if count[k] else "–" for k, _ in CLASSES]
        lines.append(f"| `{c.name}` | {len(runs)} | {len(wrong)} ({100.0 * sum(mass.values()) / total:.2f} %) | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--conditions", default=DEFAULT_CONDITIONS,
                   help=f"comma-separated globs over the quality benchmark's rows (default {DEFAULT_CONDITIONS})")
    p.add_argument("--scenes", type=int, default=30, help="synthetic scenes per row (default 30)")
    p.add_argument("--real-repeats", type=int, default=20, help="perturbation seeds of the real scene (default 20)")
    p.add_argument("--workers", type=int, default=2, help="processes")
    p.add_argument("--cache", default=str(REPO / "out" / "bench_quality_cache"), help="the quality benchmark's scenes")
    p.add_argument("--show", action="store_true", help="list every wrong segment with its class")
    p.add_argument("--docs", nargs="?", const=str(DOCS_TABLE), default=None, metavar="PATH",
                   help="also write the table as Markdown (default docs/benchmarks/tables/errors.md)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    every_rig = [*bench_quality.SYNTH_RIGS, *bench_quality.REAL_RIGS]
    conditions = bench_quality.select(bench_quality.all_conditions(False, every_rig), args.conditions)
    if not conditions:
        print("no condition matches --conditions", file=sys.stderr)
        return 2
    scenes = {rig: bench_quality.ensure_scenes(Path(args.cache), rig, bench_quality.synth_config(rig, {}),
                                               args.scenes, bench_quality.SYNTH_SEED, args.workers)
              for rig in dict.fromkeys(c.rig for c in conditions) if rig in bench_quality.SYNTH_RIGS}
    tasks = bench_quality.build_tasks(conditions, ["fused"], scenes, Path(bench_quality.SAMPLE), args.real_repeats,
                                      bench_quality.SYNTH_SEED)
    print(f"{len(conditions)} conditions: {sum(len(t.conditions) for t in tasks)} runs, {args.workers} worker(s)",
          flush=True)
    records: list[dict[str, Any]] = []
    t0 = time.perf_counter()

    def done(task: Any) -> None:
        records.extend(task.records)
        finished = sum(1 for r in records if "segments" in r)
        print(f"  [{finished}] {task.rig} scene {task.scene_index} ({time.perf_counter() - t0:.0f} s)", flush=True)

    bench_quality.evaluate(tasks, args.workers, None, 1, done, run=run_task)
    if args.show:
        for r in sorted((r for r in records if "class" in r), key=lambda r: (r["condition"], r["scene"], r["segment"])):
            print(f"{r['condition']} scene {r['scene']} segment {r['segment']} ({r['view']}, {r['points']} points, "
                  f"support {r['support']:.2f}): {r['class']}")
    text = table(records, conditions)
    print(text)
    if args.docs:
        command = "python benchmarks/bench_errors.py"
        for flag, value, default in (("--conditions", args.conditions, DEFAULT_CONDITIONS),
                                     ("--scenes", args.scenes, 30), ("--real-repeats", args.real_repeats, 20)):
            if value != default:
                command += f" {flag} '{value}'" if flag == "--conditions" else f" {flag} {value}"
        command += " --docs" if Path(args.docs).resolve() == DOCS_TABLE else f" --docs {args.docs}"
        from shadowcorr import __version__

        header = (f"ShadowCorr {__version__}; {platform.machine()} with {os.cpu_count()} cores, "
                  f"{platform.python_implementation()} {platform.python_version()}; method `fused`, "
                  f"{args.scenes} synthetic scenes and {args.real_repeats} seeds of the real scene per row: "
                  f"`{command}`.  \nEach cell: wrongly placed segments, and in brackets their share of the "
                  "row's scored points (what the average purity weighs).\n\n")
        Path(args.docs).parent.mkdir(parents=True, exist_ok=True)
        Path(args.docs).write_text(header + text)
        print(f"wrote {args.docs}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
