"""Scenes per second of ``shadowcorr batch`` with the local and the Ray engine, with the per-stage split.

Generates N small synthetic scenes once (cached under ``out/bench_batch/``: 7-8 rocks,
four 320x180 views, numpy raster renderer), starts a local Ray instance with
``--workers`` CPUs (timed: the Ray start-up), then runs the engines in turn,
``--repeats`` rounds, each run over all N scenes into a fresh results file.  Engines:
``local`` (the process pool), ``ray-fused`` (Ray, each scene one task: the default on
CPU) and ``ray-staged`` (Ray, prepare tasks then ``--actors`` network actors batching
``--batch-size`` scenes: the default with a GPU).

The first round is cold: the local pool's forkserver and Ray's worker processes start
and import torch (the Ray instance itself is already up; its start-up is printed
apart and added to the cold end-to-end ratio).  Later rounds are warm: the local pool
re-forks from its preloaded server, Ray keeps its task workers (a staged run still
starts its actors afresh: Ray Data ends them with the run).  Per engine it prints:

* wall time and scenes/s, cold and warm (median over the warm rounds), and when the
  first record arrived;
* the CPU time of the whole engine per run (this process and every process under it:
  the pool's workers, or Ray's raylet, GCS and workers; sampled every 0.2 s), beside
  the wall time, so that the machine's other load can be told apart;
* the per-stage split: the sum over scenes of each ``timings_ms`` stage, in seconds (each
  runs on one thread, so this is CPU time when the machine is not oversubscribed;
  ``network`` is each scene's share of its batch's forward pass);
* whether every engine gave every scene the same labels as the first one;
* the ratio of each Ray plan's throughput to the local engine's: warm, and cold end to
  end with Ray's start-up added.

``--parent-network`` also measures (once, cold) the local variant where workers prepare
and assign and the parent runs the network batched over the prepared scenes (the design
``shadowcorr_batch.local`` was measured against and does not use).

    python benchmarks/bench_batch.py                      # 50 scenes, 2 workers, 2 rounds, all engines
    python benchmarks/bench_batch.py --scenes 16 --repeats 3 --engines local ray-fused
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import tempfile
import threading
import time
from collections import defaultdict
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Iterator

from shadowcorr_batch import BatchOptions, SceneTask, run_batch
from shadowcorr_batch.stages import embed_tasks, finish_task, prepare_task, single_thread_numerics
from shadowcorr_client.dataset import discover_scenes
from shadowcorr_client.records import RecordWriter, UploadRecord, read_records

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
    context = mp.get_context("forkserver")  # as shadowcorr_batch.local does
    context.set_forkserver_preload(["shadowcorr_batch.stages"])
    with ProcessPoolExecutor(workers, mp_context=context, initializer=single_thread_numerics) as pool:
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


class TreeCpu:
    """CPU seconds (user + system) used by this process and every process under it, while running.

    Sampled every ``interval`` s, keeping each process's last reading, because the
    workers of a pool or of Ray are not this process's own children once they exit.
    """

    def __init__(self, interval: float = 0.2) -> None:
        import psutil

        self._root = psutil.Process()
        self._interval = interval
        self._last: dict[tuple[int, float], float] = {}
        self._start = self._snapshot()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def _snapshot(self) -> dict[tuple[int, float], float]:
        import psutil

        readings = {}
        for proc in [self._root, *self._root.children(recursive=True)]:
            try:
                times = proc.cpu_times()
                readings[(proc.pid, proc.create_time())] = times.user + times.system
            except psutil.Error:  # it ended between listing and reading
                continue
        return readings

    def _sample(self) -> None:
        while not self._stop.wait(self._interval):
            self._last.update(self._snapshot())

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        self._last.update(self._snapshot())
        return sum(cpu - self._start.get(key, 0.0) for key, cpu in self._last.items())


def _run(name: str, scenes: Path, out: Path, args: argparse.Namespace) -> dict:
    cpu = TreeCpu()
    t0 = time.perf_counter()
    stamps: list[float] = []
    if name == "local-parent-network":
        with RecordWriter(out) as writer:
            for record in _parent_network_records(scenes, args.workers, args.batch_size):
                writer.write(record)
                stamps.append(time.perf_counter())
    else:
        engine, _, plan = name.partition("-")
        options = BatchOptions(engine=engine, workers=args.workers, ray_plan=plan or "auto", actors=args.actors,
                               batch_size=args.batch_size)
        run_batch(scenes, out, options, on_record=lambda _: stamps.append(time.perf_counter()))
    wall = time.perf_counter() - t0
    cpu_s = cpu.stop()
    latest, _ = read_records(out)
    stages: dict[str, float] = defaultdict(float)
    for record in latest.values():
        for stage, ms in ((record.result or {}).get("timings_ms") or {}).items():
            stages[stage] += ms / 1e3
    return {
        "engine": name, "scenes": len(stamps), "ok": sum(r.ok for r in latest.values()), "wall_s": wall,
        "cpu_s": cpu_s, "scenes_per_s": len(stamps) / wall,
        "first_scene_after_s": stamps[0] - t0 if stamps else float("nan"), "stages_s": dict(stages),
        "labels": {n: [s["object"] for s in (r.result or {}).get("segments", [])] for n, r in latest.items()},
    }


def _median(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


ENGINES = ("local", "ray-fused", "ray-staged")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=4242)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--actors", type=int, default=1, help="ray-staged: network actors")
    parser.add_argument("--batch-size", type=int, default=8, help="ray-staged: scenes per forward pass")
    parser.add_argument("--repeats", type=int, default=2, help="rounds over the engines; the first is cold")
    parser.add_argument("--engines", nargs="+", default=list(ENGINES), choices=ENGINES)
    parser.add_argument("--parent-network", action="store_true", help="also measure the parent-batched local variant")
    parser.add_argument("--json", help="also write the figures here")
    args = parser.parse_args()

    scenes = scene_cache(args.scenes, args.seed, args.workers)
    load_before = os.getloadavg()
    ray_start_s = 0.0
    if any(e.startswith("ray") for e in args.engines):
        from shadowcorr_batch.ray_engine import import_ray

        ray = import_ray()
        t0 = time.perf_counter()
        ray.init(num_cpus=args.workers, include_dashboard=False, log_to_driver=False)
        ray_start_s = time.perf_counter() - t0
    runs: dict[str, list[dict]] = defaultdict(list)
    with tempfile.TemporaryDirectory() as tmp:
        for rnd in range(args.repeats):
            for name in args.engines:
                runs[name].append(_run(name, scenes, Path(tmp) / f"{name}_{rnd}.jsonl", args))
        if args.parent_network:
            runs["local-parent-network"].append(_run("local-parent-network", scenes, Path(tmp) / "pn.jsonl", args))

    print(f"{args.scenes} synthetic scenes (7-8 rocks, 4 views of 320x180), {args.workers} workers; ray-staged: "
          f"{args.actors} actor(s), batch {args.batch_size}; load average before {load_before[0]:.1f}, "
          f"after {os.getloadavg()[0]:.1f}")
    print(f"Ray start-up (ray.init, {args.workers} CPUs): {ray_start_s:.1f} s")
    print(f"{'engine':<22}{'ok':>4}{'cold s':>8}{'cpu s':>7}{'cold/s':>8}{'1st s':>7}"
          f"{'warm s':>8}{'cpu s':>7}{'warm/s':>8}{'1st s':>7}  same labels")
    names = list(runs)
    reference = runs[names[0]][0]["labels"]
    summary = {}
    for name in names:
        cold, warm = runs[name][0], runs[name][1:]
        same = all(r["labels"].get(n) == labels for r in runs[name] for n, labels in reference.items())
        warm_s = _median([r["wall_s"] for r in warm])
        summary[name] = {"cold_wall_s": cold["wall_s"], "warm_wall_s": warm_s}
        print(f"{name:<22}{cold['ok']:>4}{cold['wall_s']:>8.1f}{cold['cpu_s']:>7.1f}{cold['scenes_per_s']:>8.3f}"
              f"{cold['first_scene_after_s']:>7.1f}{warm_s:>8.1f}{_median([r['cpu_s'] for r in warm]):>7.1f}"
              f"{args.scenes / warm_s:>8.3f}{_median([r['first_scene_after_s'] for r in warm]):>7.1f}  {same}")
    stage_names = [s for s in runs[names[0]][0]["stages_s"] if s != "total"]
    print("per-stage time, summed over scenes (s), last run of each engine:")
    print(f"  {'':<20}" + " ".join(f"{s[:8]:>8}" for s in stage_names) + "    total")
    for name in names:
        stages = runs[name][-1]["stages_s"]
        print(f"  {name:<20}" + " ".join(f"{stages.get(s, 0.0):8.1f}" for s in stage_names)
              + f"  {stages.get('total', 0.0):7.1f}")
    if "local" in summary:
        loc = summary["local"]
        for name in (n for n in names if n.startswith("ray")):
            ray_ = summary[name]
            print(f"{name} / local throughput: warm {loc['warm_wall_s'] / ray_['warm_wall_s']:.2f}, cold end to end "
                  f"{loc['cold_wall_s'] / (ray_['cold_wall_s'] + ray_start_s):.2f} (Ray start-up included)")
    if args.json:
        Path(args.json).write_text(json.dumps({"ray_start_s": ray_start_s, "load_before": load_before, "runs": {
            n: [{k: v for k, v in r.items() if k != "labels"} for r in rs] for n, rs in runs.items()}}, indent=1))


if __name__ == "__main__":
    main()
