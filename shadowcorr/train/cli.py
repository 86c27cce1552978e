"""``shadowcorr train``: train a ShadowCorr network on bundle directories with ground truth.

The main CLI calls :func:`add_train_parser` with its subparsers; the parsed arguments go
to :func:`run_train`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

__all__ = ["add_train_parser", "run_train", "config_from_args"]


def add_train_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``train`` on the main CLI's subparsers."""
    p = subparsers.add_parser(
        "train",
        help="train a network on synthetic (or other ground-truth) bundles",
        description="Adam on the paper's multi-objective loss, one scene per step; validation voxel ARI through the "
        "real assign() path selects the best epoch, which is exported as RUN_DIR/model.safetensors with its model card.",
    )
    p.add_argument("--data", required=True, help="directory of training bundle directories")
    p.add_argument("--val", help="directory of validation bundles (model selection); without it the lowest "
                                 "training loss selects")
    p.add_argument("--test", help="held-out bundles: the best model is evaluated on them at the end (card metrics)")
    p.add_argument("--out", required=True, help="run directory (run.json, checkpoints/, model.safetensors)")
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--lr", type=float, default=5e-5)
    p.add_argument("--batch-scenes", type=int, default=1, help="scenes per optimizer step (default 1, as the paper)")
    p.add_argument("--grad-clip", type=float, help="clip the gradient norm (default: off)")
    p.add_argument("--neighbourhood", choices=["grid", "reference"], default="grid",
                   help="'grid': true voxel-grid convolution neighbourhoods; 'reference': centre taps only (SPEC §3)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--init", help="start from this model file (e.g. the reference checkpoint or a .safetensors)")
    p.add_argument("--device", default="auto", help="auto (cuda when present), cpu, cuda, cuda:N")
    p.add_argument("--workers", type=int, default=2, help="processes preparing scenes (default 2)")
    p.add_argument("--cache", help="cache directory of prepared scenes (default ~/.cache/shadowcorr/voxel_scenes)")
    p.add_argument("--max-train-scenes", type=int, help="use only the first N training bundles (name order)")
    p.add_argument("--max-val-scenes", type=int)
    p.add_argument("--max-test-scenes", type=int)
    p.add_argument("--name", default="shadowcorr-trained", help="model name in the card")
    p.add_argument("--model-version", default="1.0", help="model version in the card")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's choice; 1 is fastest on a busy machine)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run_train)
    return p


def config_from_args(args: argparse.Namespace):
    """The :class:`TrainConfig` the arguments describe."""
    from .trainer import TrainConfig

    return TrainConfig(
        data=args.data, val=args.val, test=args.test, out=args.out, epochs=args.epochs, lr=args.lr,
        batch_scenes=args.batch_scenes, grad_clip=args.grad_clip, neighbourhood=args.neighbourhood, seed=args.seed,
        init=args.init, device=args.device, workers=args.workers, cache_dir=args.cache,
        max_train_scenes=args.max_train_scenes, max_val_scenes=args.max_val_scenes,
        max_test_scenes=args.max_test_scenes, name=args.name, version=args.model_version,
    )  # fmt: skip


def run_train(args: argparse.Namespace) -> int:
    import torch

    from .trainer import train

    if args.threads:
        torch.set_num_threads(args.threads)
    record = train(config_from_args(args), resume=args.resume, progress=not args.quiet)
    model = record["model"]
    print(f"best epoch {record.get('best_epoch')}; model written to {model['path']}")
    print(json.dumps(model["metrics"], indent=1))
    print(f"run log: {Path(args.out) / 'run.json'}")
    return 0
