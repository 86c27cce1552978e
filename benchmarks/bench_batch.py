"""Scenes per second of ``shadowcorr batch`` with the local and the Ray engine, with the per-stage split.

Generates N small synthetic scenes once (cached under ``out/bench_batch/scenes_N``: 7-8
rocks, four 320x180 views, numpy raster renderer), then runs every engine over all of
them into a fresh results file and prints, per engine:

* wall time and scenes/s end to end (Ray: starting the local Ray instance included),
  and in steady state (from the first finished scene to the last);
* the per-stage split: the sum over scenes of each ``timings_ms`` stage, in seconds;
* whether every engine gave every scene the same labels as the first engine;
* the ratio Ray / local of the end-to-end and the steady-state throughput.

``--parent-network`` also measures the local variant where workers prepare and assign
and the parent runs the network batched over the prepared scenes (the design that
``batch.local`` was measured against and does not use).

    python benchmarks/bench_batch.py                      # 50 scenes, 2 workers, local + ray
    python benchmarks/bench_batch.py --scenes 12 --engines local ray --parent-network
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import tempfile
import time
from collections import defaultdict
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Iterator

from batch import BatchOptions, SceneTask, run_batch
from batch.stages import embed_tasks, finish_task, prepare_task, single_thread_numerics
from clients.dataset import discover_scenes
from clients.records import RecordWriter, UploadRecord, read_records

REPO = Path(__file__).resolve().parents[1]
SMALL_SCENE = dict(
    n_rocks=(7, 8), rock_subdivisions=3, field_radius=120.0, terrain_half_size=1000.0, terrain_resolution=128,
    width=320, height=180, focal_px=1615.0 / 6, renderer="raster", background_depth="invalid",
)


def scene_cache(n: int, seed: int, workers: int) -> Path:
    """The N benchmark scenes, generated on first use."""
    from shadowcorr.synth import SynthConfig, generate_dataset

    out = REPO / "out" / "bench_batch" / f"scenes_{n}_seed{seed}"
    generate_dataset(SynthConfig(**SMALL_SCENE), n, out, seed=seed, workers=workers, progress=True, resume=True)
    return out


def _parent_network_records(scenes: Path, workers: int, batch_size: int) -> Iterator[UploadRecord]:
    """Workers prepare and assign; the parent batches the network over prepared scenes."""
    from shadowcorr.config import ShadowCorrConfig
    from shadowcorr.nn import load_model

    single_thread_numerics()
    model = load_model()
    config = ShadowCorrConfig()
    queue = [SceneTask(source=s, config=config) for s in discover_scenes(scenes)]
    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=single_thread_numerics) as pool:
        preparing = {pool.submit(prepare_task, t) for t in queue}
        finishing: set = set()
        ready: list[SceneTask] = []
        while preparing or finishing:
            done, _ = wait(preparing | finishing, return_when=FIRST_COMPLETED)
            for future in done:
                if future in finishing:
                    finishing.discard(future)
                    yield future.result()
                else:
                    preparing.discard(future)
                    ready.append(future.result())
            # A batch as soon as batch_size scenes wait, or whatever waits once nothing else is preparing.
            if ready and (len(ready) >= batch_size or not preparing):
                finishing |= {pool.submit(finish_task, t) for t in embed_tasks(model, ready)}
                ready = []


def _run(name: str, scenes: Path, out: Path, args: argparse.Namespace) -> dict:
    t0 = time.perf_counter()
    stamps: list[float] = []
    if name == "local-parent-network":
        with RecordWriter(out) as writer:
            for record in _parent_network_records(scenes, args.workers, args.batch_size):
                writer.write(record)
                stamps.append(time.perf_counter())
    else:
        options = BatchOptions(engine=name, workers=args.workers, actors=args.actors, batch_size=args.batch_size)
        run_batch(scenes, out, options, on_record=lambda _: stamps.append(time.perf_counter()))
    wall = time.perf_counter() - t0
    latest, _ = read_records(out)
    stages: dict[str, float] = defaultdict(float)
    for record in latest.values():
        for stage, ms in ((record.result or {}).get("timings_ms") or {}).items():
            stages[stage] += ms / 1e3
    steady = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 1 and stamps[-1] > stamps[0] else float("nan")
    return {
        "engine": name, "scenes": len(stamps), "ok": sum(r.ok for r in latest.values()), "wall_s": wall,
        "scenes_per_s": len(stamps) / wall, "steady_scenes_per_s": steady,
        "first_scene_after_s": stamps[0] - t0 if stamps else float("nan"), "stages_s": dict(stages),
        "labels": {n: [s["object"] for s in (r.result or {}).get("segments", [])] for n, r in latest.items()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=4242)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--actors", type=int, default=1)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--engines", nargs="+", default=["local", "ray"], choices=["local", "ray"])
    parser.add_argument("--parent-network", action="store_true", help="also measure the parent-batched local variant")
    parser.add_argument("--json", help="also write the figures here")
    args = parser.parse_args()

    scenes = scene_cache(args.scenes, args.seed, args.workers)
    engines = list(args.engines) + (["local-parent-network"] if args.parent_network else [])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in engines:
            rows.append(_run(name, scenes, Path(tmp) / f"{name}.jsonl", args))

    stage_names = [s for s in rows[0]["stages_s"] if s != "total"]
    print(f"{args.scenes} synthetic scenes (7-8 rocks, 4 views of 320x180), {args.workers} workers, "
          f"Ray: {args.actors} actor(s), batch {args.batch_size}")
    print(f"{'engine':<22}{'ok':>4}{'wall s':>9}{'scenes/s':>10}{'steady/s':>10}{'1st s':>7}  same labels")
    reference = rows[0]["labels"]
    for r in rows:
        same = all(r["labels"].get(n) == labels for n, labels in reference.items())
        print(f"{r['engine']:<22}{r['ok']:>4}{r['wall_s']:>9.1f}{r['scenes_per_s']:>10.3f}"
              f"{r['steady_scenes_per_s']:>10.3f}{r['first_scene_after_s']:>7.1f}  {same}")
    print("per-stage CPU time, summed over scenes (s): " + ", ".join(stage_names))
    for r in rows:
        print(f"  {r['engine']:<20}" + " ".join(f"{r['stages_s'].get(s, 0.0):7.1f}" for s in stage_names)
              + f"   total {r['stages_s'].get('total', 0.0):.1f}")
    by_name = {r["engine"]: r for r in rows}
    if "local" in by_name and "ray" in by_name:
        loc, ray = by_name["local"], by_name["ray"]
        print(f"Ray / local throughput: end to end {ray['scenes_per_s'] / loc['scenes_per_s']:.2f}, "
              f"steady state {ray['steady_scenes_per_s'] / loc['steady_scenes_per_s']:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps([{k: v for k, v in r.items() if k != "labels"} for r in rows], indent=1))


if __name__ == "__main__":
    main()
