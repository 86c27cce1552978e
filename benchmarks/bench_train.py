"""Benchmark: training time per scene (forward + loss + backward + Adam step) of both neighbourhoods.

Runs ``--epochs`` epochs of the real training step (:class:`shadowcorr.train.Trainer`'s
inner loop, one scene per step) over a few scenes with the network in neighbourhood
"reference" (centre-tap convolutions, SPEC §3) and "grid" (true 3^3 / 5^3 voxel
neighbourhoods), and prints per variant the median seconds per scene step, the voxels
per scene and the epoch time.  Validation is not included.

Scenes: prepared bundles from ``--data`` (a directory of bundle directories, e.g. from
``shadowcorr synth``; prepared scenes are cached, see ``--cache``), or, without
``--data``, small analytic sphere fields from ``tests/scenes.py`` (about 1-2 thousand
voxels each, far smaller than the ~4-5 thousand of a synthetic rock field).

Usage::

    python benchmarks/bench_train.py [--data DIR] [--scenes 4] [--epochs 2] [--threads 1] [--device cpu]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a checkout without installing

from shadowcorr.nn import NetConfig, ShadowCorrNet  # noqa: E402
from shadowcorr.train.dataset import TrainScene, find_bundles, prepare_scenes  # noqa: E402
from shadowcorr.train.losses import LossConfig, graph_neighbours, multi_objective_loss  # noqa: E402


def sphere_scenes(n: int, cache: Path) -> list[TrainScene]:
    """``n`` small sphere fields written as bundles and prepared (through the cache)."""
    from shadowcorr.io import write_bundle
    from tests.scenes import sphere_scene

    rng = np.random.default_rng(0)
    root = cache / "sphere_bundles"
    dirs = []
    for i in range(n):
        d = root / f"scene_{i:05d}"
        if not (d / "manifest.json").exists():
            centres = np.c_[rng.uniform(-150, 150, (6, 2)), np.full(6, 40.0)]
            write_bundle(sphere_scene(centres, rng.uniform(25, 45, 6), cameras=4), d, depth_format="npy",
                         mask_format="npy")
        dirs.append(d)
    scenes, _ = prepare_scenes(dirs, cache_dir=cache, progress=False)
    return scenes


def time_variant(neighbourhood: str, scenes: list[TrainScene], epochs: int, device: torch.device) -> list[float]:
    """Seconds of every training step (one scene each) after one warm-up step."""
    torch.manual_seed(0)
    net = ShadowCorrNet(NetConfig(neighbourhood=neighbourhood)).to(device).train()
    opt = torch.optim.Adam(net.parameters(), lr=5e-5)
    cfg = LossConfig()
    data = []
    for ts in scenes:
        f = torch.from_numpy(ts.scene.features).to(device)
        v = torch.from_numpy(ts.scene.voxel_index.astype(np.int64)).to(device)
        b = torch.zeros(len(f), dtype=torch.int64, device=device)
        edges = tuple(e.to(device) for e in graph_neighbours(v.cpu(), b.cpu(), cfg.graph_k))
        data.append((f, v, torch.from_numpy(ts.target).to(device), b, edges))

    def step(f, v, t, b, edges) -> None:
        emb = net(f, v, 8.0, b)
        loss, _ = multi_objective_loss(emb, t, b, v, cfg, edges=edges)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize()

    step(*data[0])  # warm-up (allocator, kernels)
    times = []
    for _ in range(epochs):
        for item in data:
            t0 = time.perf_counter()
            step(*item)
            times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="directory of bundle directories (default: analytic sphere scenes)")
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--epochs", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cache", help="prepared-scene cache (default: a temporary directory)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)

    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(args.cache) if args.cache else Path(tmp)
        if args.data:
            scenes, _ = prepare_scenes(find_bundles(args.data, args.scenes), cache_dir=cache, progress=False)
        else:
            scenes = sphere_scenes(args.scenes, cache)
    voxels = [s.num_voxels for s in scenes]
    print(f"{len(scenes)} scenes, voxels per scene: mean {np.mean(voxels):.0f} (min {min(voxels)}, max {max(voxels)}); "
          f"device {device}, {args.threads} thread(s), {args.epochs} epoch(s)")
    print(f"{'neighbourhood':<14}{'median s/scene':>16}{'mean s/scene':>14}{'s/epoch':>10}")
    for nb in ("reference", "grid"):
        t = time_variant(nb, scenes, args.epochs, device)
        print(f"{nb:<14}{statistics.median(t):>16.3f}{statistics.mean(t):>14.3f}{sum(t) / args.epochs:>10.2f}")


if __name__ == "__main__":
    main()
