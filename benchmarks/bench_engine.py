"""Per-stage timings of the engine on the real sample scene (median of repeated runs).

    python benchmarks/bench_engine.py [--repeats 7] [--cameras 0,2,4,6] [--model PATH] [--device cpu|cuda] [--threads 1]
                                      [--docs [PATH]]
    python benchmarks/bench_engine.py --against REV [--repeats 15]     # this checkout against a git revision

Prints milliseconds per stage (median wall time of ``result.timings_ms``) for two paths:
  in memory: decoded SceneBundle -> labels (pose refinement, segments, evidence, network, grouping)
  on disk:   bundle directory -> labels (load_bundle + the above)
(both without scoring against the ground truth: the purity printed comes from a separate warm-up run)
and the median CPU time of the in-memory path (on a shared machine the steadier figure).
Targets for a 4-view 1080p scene on one core: pose refinement <= 150 ms; everything else
<= 150 ms in memory and <= 250 ms from disk.  ``--threads N`` runs the stages with
``num_threads = N`` and the network on N torch threads (0: every core).  With ``--device cuda`` the network runs on
the GPU (every other stage stays on the CPU).  ``--docs`` also writes the figures as a Markdown table
(default ``docs/benchmarks/tables/engine.md``, which the documentation's benchmark page includes),
with the release, the machine and its load average, so that no figure is typed by hand.

``--against REV`` compares this checkout's default with the library of a git revision (its
``shadowcorr/`` exported from the repository and imported as a second package, with its own
packaged model), both in this one process, one scene from each in turn, ``--repeats`` rounds on
one thread: on a shared machine the same code runs several per cent faster or slower from one
process to the next, which hides a change of a few milliseconds between two separate runs.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from shadowcorr import ShadowCorrConfig, __version__, correspond, load_bundle, load_model
from shadowcorr.convert import convert_ue, load_ue_scene
from shadowcorr.ops import resolve_threads

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "examples" / "ue_sample"  # ships with the repository
DOCS_TABLE = REPO / "docs" / "benchmarks" / "tables" / "engine.md"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--cameras", default="0,2,4,6")
    parser.add_argument("--model", default=None, help="default: the packaged model")
    parser.add_argument("--data", default=str(SAMPLE))
    parser.add_argument("--threads", type=int, default=1, help="num_threads of the configuration and torch's "
                        "threads (0: every core; the service's workers use 1)")
    parser.add_argument("--device", default="cpu", help="torch device of the network: cpu, cuda, cuda:N")
    parser.add_argument("--docs", nargs="?", const=str(DOCS_TABLE), default=None, metavar="PATH",
                        help=f"also write the figures to PATH (default {DOCS_TABLE.relative_to(REPO)})")
    parser.add_argument("--against", metavar="REV", help="compare with the library of this git revision, both "
                        "versions in one process, one scene each in turn (--repeats rounds)")
    args = parser.parse_args()
    if args.against:
        return compare_with(args.against, args.repeats, [int(c) for c in args.cameras.split(",")], args.data)
    load_before = os.getloadavg()[0]
    config = ShadowCorrConfig(num_threads=args.threads)
    torch.set_num_threads(resolve_threads(args.threads))
    cameras = [int(c) for c in args.cameras.split(",")]
    model = load_model(args.model, device=args.device)

    bundle = load_ue_scene(args.data, 2001, cameras)
    # Warm-up (first-call allocations and lazy imports); its metrics are the ones printed.  The timed
    # runs leave scoring against the ground truth out: a user's scene has none.
    scored = correspond(bundle, model, config)
    stages: dict[str, list[float]] = {}
    totals, cpu = [], []
    for _ in range(args.repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        result = correspond(bundle, model, config, metrics=False)
        totals.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
        for k, v in result.timings_ms.items():
            stages.setdefault(k, []).append(v)

    with tempfile.TemporaryDirectory() as tmp:
        path = convert_ue(args.data, 2001, cameras, Path(tmp) / "bundle")
        disk, loads = [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            loaded = load_bundle(path)
            t1 = time.perf_counter()
            correspond(loaded, model, config, metrics=False)
            disk.append((time.perf_counter() - t0) * 1e3)
            loads.append((t1 - t0) * 1e3)

    m = scored.metrics or {}
    print(f"scene Set2001 cameras {args.cameras}: {len(result.segments)} segments, "
          f"{sum(o.num_voxels for o in result.objects)} voxels, model {model.name} on {args.device}, "
          f"num_threads {args.threads}")
    print(f"average purity {m.get('average_purity', float('nan')):.2f}, voxel ARI {m.get('voxel_ari', float('nan')):.4f}")
    print(f"{'stage':<20}{'median ms':>12}")
    for k, v in stages.items():
        if k != "total":
            print(f"{k:<20}{statistics.median(v):>12.1f}")
    poses = statistics.median(stages.get("poses", [0.0]))
    print(f"{'in memory -> labels':<20}{statistics.median(totals):>12.1f}   "
          f"({statistics.median(totals) - poses:.1f} without pose refinement; target <= 150)")
    print(f"{'  CPU time':<20}{statistics.median(cpu):>12.1f}")
    print(f"{'load_bundle':<20}{statistics.median(loads):>12.1f}")
    print(f"{'on disk -> labels':<20}{statistics.median(disk):>12.1f}   "
          f"({statistics.median(disk) - poses:.1f} without pose refinement; target <= 250)")
    if args.docs:
        path = Path(args.docs)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(docs_table(args, stages, totals, cpu, loads, disk, len(result.segments),
                                   (load_before, os.getloadavg()[0])))
        print(f"wrote {path}")
    return 0


def compare_with(rev: str, rounds: int, cameras: list[int], data: str) -> int:
    """Median in-memory time and stage times of this checkout and of revision ``rev``, one process, one thread."""
    import importlib
    import subprocess
    import tarfile

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        archive = Path(tmp) / "library.tar"
        try:
            subprocess.run(["git", "-C", str(REPO), "archive", "--format=tar", "-o", str(archive), rev, "shadowcorr"],
                           check=True, capture_output=True, text=True)
        except (OSError, subprocess.CalledProcessError) as error:
            detail = getattr(error, "stderr", "") or str(error)
            print(f"cannot export shadowcorr/ of {rev!r} from {REPO}: {detail.strip()}", file=sys.stderr)
            return 2
        with tarfile.open(archive) as tar:
            tar.extractall(tmp, filter="data")
        # The revision's library as package "shadowcorr_ref": its modules import each other relatively;
        # the one lookup of its own package data by name is pointed at the copy.
        reference = Path(tmp) / "shadowcorr_ref"
        (Path(tmp) / "shadowcorr").rename(reference)
        for source in reference.rglob("*.py"):
            text = source.read_text()
            if 'resources.files("shadowcorr")' in text:
                source.write_text(text.replace('resources.files("shadowcorr")', 'resources.files("shadowcorr_ref")'))
        sys.path.insert(0, tmp)
        versions = {}
        for name, label in (("shadowcorr", "this checkout"), ("shadowcorr_ref", rev)):
            library = importlib.import_module(name)
            convert = importlib.import_module(name + ".convert")
            config, model = library.ShadowCorrConfig(num_threads=1), library.load_model()
            bundle = convert.load_ue_scene(data, 2001, cameras)
            library.correspond(bundle, model, config, metrics=False)  # warm-up
            versions[label] = (library, bundle, model, config)
        totals: dict[str, list[float]] = {label: [] for label in versions}
        stages: dict[str, dict[str, list[float]]] = {label: {} for label in versions}
        for round_ in range(rounds):
            # alternate which version goes first, so that neither always runs on the other's caches
            for label in list(versions)[:: 1 if round_ % 2 == 0 else -1]:
                library, bundle, model, config = versions[label]
                t0 = time.perf_counter()
                result = library.correspond(bundle, model, config, metrics=False)
                totals[label].append((time.perf_counter() - t0) * 1e3)
                for k, v in result.timings_ms.items():
                    stages[label].setdefault(k, []).append(v)
    med = statistics.median
    this, other = versions
    print(f"scene Set2001 cameras {','.join(map(str, cameras))}, one thread, {rounds} rounds in one process")
    print(f"{'stage':<20}{'this checkout':>15}{rev[:12]:>15}{'difference':>12}")
    names = list(stages[this]) + [k for k in stages[other] if k not in stages[this]]
    for k in names:
        if k == "total":
            continue
        a, b = (med(stages[label][k]) if k in stages[label] else None for label in (this, other))
        shown = [f"{x:>15.1f}" if x is not None else f"{'-':>15}" for x in (a, b)]
        print(f"{k:<20}{shown[0]}{shown[1]}{(a or 0.0) - (b or 0.0):>+12.1f}")
    a, b = med(totals[this]), med(totals[other])
    print(f"{'in memory -> labels':<20}{a:>15.1f}{b:>15.1f}{a - b:>+12.1f}   ({100 * (a / b - 1):+.1f} %)")
    return 0


def docs_table(args: argparse.Namespace, stages: dict[str, list[float]], totals: list[float], cpu: list[float],
               loads: list[float], disk: list[float], segments: int, load: tuple[float, float]) -> str:
    """The run's figures as Markdown: medians per stage and per path, with what was measured where."""
    med = statistics.median
    poses = med(stages.get("poses", [0.0]))
    threads = args.threads if args.threads else "every"
    lines = [
        f"ShadowCorr {__version__}; {platform.machine()} with {os.cpu_count()} cores, {platform.python_implementation()} "
        f"{platform.python_version()}, torch {torch.__version__}, network on {args.device}; "
        f"{threads} thread(s); load average {load[0]:.1f} before and {load[1]:.1f} after the run.  ",
        f"The real sample scene, cameras {args.cameras} ({segments} segments); medians of {args.repeats} runs "
        f"after a warm-up: `python benchmarks/bench_engine.py --repeats {args.repeats} --threads {args.threads} --docs`.",
        "",
        "| stage | median ms |",
        "|---|---|",
    ]
    lines += [f"| {k} | {med(v):.1f} |" for k, v in stages.items() if k != "total"]
    lines += [
        "",
        "| path | median ms |",
        "|---|---|",
        f"| in memory → labels | {med(totals):.1f} ({med(totals) - poses:.1f} without pose refinement) |",
        f"| in memory → labels, CPU time | {med(cpu):.1f} |",
        f"| `load_bundle` | {med(loads):.1f} |",
        f"| on disk → labels | {med(disk):.1f} ({med(disk) - poses:.1f} without pose refinement) |",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
