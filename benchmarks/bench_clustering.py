"""Benchmark: shadowcorr.stages.mean_shift vs sklearn.cluster.MeanShift.

Data: L2-normalised 32-D embeddings in 20 well-separated blobs (Gaussian spread 0.06
per axis around random unit directions) plus 5 % uniform noise directions - the
shape of voxel embeddings the clustering step sees - with bandwidth 0.7 (SPEC §2
step 11).  Prints the median wall time of each implementation, the speed-up, and the
agreement of the labels (ARI, and whether they are identical).

Usage::

    python benchmarks/bench_clustering.py [--sizes 1000 2500 10000] [--threads 2]
                                          [--repeats 5] [--sklearn-max 5000]

scikit-learn is skipped for sizes above ``--sklearn-max`` (it needs tens of seconds
at 10,000 points).  Ours runs with ``--threads`` torch threads.  scikit-learn runs
with ``--sklearn-threads`` (default 1) OpenMP/BLAS threads via threadpoolctl: with
``n_jobs=None`` its seeds are processed one after another and each one-point radius
query opens its own OpenMP region, so more threads only add synchronisation - on a
busy machine 2 threads made it 5-20x *slower* than 1.  One thread is its best case.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from sklearn.cluster import MeanShift
from sklearn.metrics import adjusted_rand_score
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing
from shadowcorr.stages import mean_shift  # noqa: E402


def make_embeddings(n: int, dim: int = 32, blobs: int = 20, noise: float = 0.05, seed: int = 0) -> np.ndarray:
    """Unit-norm embeddings in ``blobs`` tight clusters plus a share of random directions."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(blobs, dim))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    n_noise = int(n * noise)
    pts = centres[rng.integers(0, blobs, n - n_noise)] + rng.normal(scale=0.06, size=(n - n_noise, dim))
    pts = np.vstack([pts, rng.normal(size=(n_noise, dim))])
    return (pts / np.linalg.norm(pts, axis=1, keepdims=True)).astype(np.float32)


def _median_ms(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times), out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 2500, 10000])
    ap.add_argument("--dim", type=int, default=32)
    ap.add_argument("--bandwidth", type=float, default=0.7)
    ap.add_argument("--threads", type=int, default=2, help="torch threads for ours")
    ap.add_argument("--sklearn-threads", type=int, default=1, help="OpenMP/BLAS threads for scikit-learn")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--sklearn-repeats", type=int, default=3)
    ap.add_argument("--sklearn-max", type=int, default=5000, help="skip scikit-learn above this many points")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)

    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, torch threads {torch.get_num_threads()}, sklearn threads "
          f"{args.sklearn_threads}, device {args.device}, dim {args.dim}, bandwidth {args.bandwidth}")
    print(f"{'N':>7} {'ours ms':>9} {'sklearn ms':>11} {'speed-up':>9} {'clusters':>9} {'ARI':>7} identical")
    mean_shift(make_embeddings(200, args.dim), args.bandwidth, device=args.device)  # warm-up
    for n in args.sizes:
        x = make_embeddings(n, args.dim)
        ours_ms, (labels, centers) = _median_ms(lambda x=x: mean_shift(x, args.bandwidth, device=args.device),
                                                args.repeats)
        if n <= args.sklearn_max:
            with threadpool_limits(args.sklearn_threads):
                ref_ms, ref = _median_ms(lambda x=x: MeanShift(bandwidth=args.bandwidth).fit(x), args.sklearn_repeats)
            ari = adjusted_rand_score(ref.labels_, labels)
            same = labels.shape == ref.labels_.shape and bool(np.all(labels == ref.labels_))
            print(f"{n:>7} {ours_ms:>9.1f} {ref_ms:>11.1f} {ref_ms / ours_ms:>8.1f}x {len(centers):>9} "
                  f"{ari:>7.4f} {same}")
        else:
            print(f"{n:>7} {ours_ms:>9.1f} {'skipped':>11} {'':>9} {len(centers):>9} {'':>7}")


if __name__ == "__main__":
    main()
