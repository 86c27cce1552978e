"""Throughput of ``shadowcorr synth`` at default settings (18-20 rocks, 4 views, 1920x1080).

Usage: python benchmarks/bench_synth.py [--scenes 8] [--workers 2] [--renderer auto|gl|raster]

Prints scenes/minute for a whole ``generate_dataset`` run (worker start-up and bundle
writing included) and the mean per-stage seconds recorded in each scene's truth file.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from shadowcorr.synth import SynthConfig, generate_dataset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--renderer", default="auto", choices=["auto", "gl", "raster"])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    config = SynthConfig(renderer=args.renderer)
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        paths = generate_dataset(config, args.scenes, Path(tmp), seed=args.seed, workers=args.workers)
        wall = time.perf_counter() - t
        truths = [json.loads((p / "synth_truth.json").read_text()) for p in paths]
    stages = {k: statistics.mean(tr["timings_s"][k] for tr in truths) for k in truths[0]["timings_s"]}
    contacts = [len(tr["contacts"]) for tr in truths]
    stacked = [sum(not r["on_ground"] for r in tr["rocks"]) for tr in truths]
    print(f"renderer: {sorted({tr['renderer'] for tr in truths})}  workers: {args.workers}  scenes: {args.scenes}")
    print("per scene (s, in a worker): " + "  ".join(f"{k} {v:.2f}" for k, v in stages.items()))
    print(f"rock-rock contacts per scene: mean {statistics.mean(contacts):.1f} (min {min(contacts)}, max {max(contacts)}); "
          f"rocks resting only on rocks: mean {statistics.mean(stacked):.1f}")
    print(f"throughput: {args.scenes / wall * 60:.1f} scenes/minute ({wall:.1f} s wall)")


if __name__ == "__main__":
    main()
