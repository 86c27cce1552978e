"""``shadowcorr batch``: label every scene of a dataset, on this machine or a Ray cluster.

Registered in the ``shadowcorr.commands`` entry-point group (pyproject.toml), like
``serve``, so the library's CLI never imports this package by name.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the runner imports the pipeline (torch): only when the command runs
    from .runner import BatchOptions, BatchRun

__all__ = ["add_batch_parser", "run_batch_command", "options_from_args"]


def add_batch_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``batch`` sub-command to an argparse ``subparsers`` object; returns its parser."""
    from shadowcorr.cli import add_method_options, parse_cameras, positive_int

    p = subparsers.add_parser(
        "batch",
        help="label every scene of a dataset (local process pool or Ray), resumable",
        description="Label every scene under INPUT (bundle folders, archives, Unreal-layout sets) and append "
                    "one JSON line per scene to --out. Run the same command again to resume: scenes already "
                    "'ok' in the results file are skipped.",
    )
    p.add_argument("input", metavar="INPUT", help="dataset directory, bundle or archive")
    p.add_argument("--out", required=True, metavar="RESULTS.jsonl", help="results file (appended to)")
    p.add_argument("--engine", choices=("local", "ray"), default="local",  # runner.ENGINES, without importing it
                   help="local: a process pool on this machine; ray: Ray Data (pip install \"shadowcorr[ray]\")")
    p.add_argument("--workers", type=positive_int, default=os.cpu_count() or 1,
                   help="worker processes (local) or CPUs of the local Ray instance (default: all cores)")
    p.add_argument("--ray-address", metavar="ADDR",
                   help="join this Ray cluster (auto, HOST:6379 or ray://HOST:10001) instead of starting one")
    p.add_argument("--ray-plan", choices=("auto", "fused", "staged"), default="auto",  # ray_engine.RAY_PLANS
                   help="Ray: fused (each scene one task; auto on CPU) or staged (prepare tasks, then network "
                        "actors batching scenes; auto with --device cuda)")
    p.add_argument("--actors", type=positive_int, default=1,
                   help="Ray, staged: network actors, each holding the model")
    p.add_argument("--batch-size", type=positive_int, default=8, help="Ray, staged: prepared scenes per forward pass")
    p.add_argument("--cameras", type=parse_cameras, help="cameras to use from Unreal-layout sets (default: all)")
    p.add_argument("--limit", type=positive_int, help="run at most this many scenes in this run")
    p.add_argument("--no-metrics", action="store_true", help="skip ground-truth metrics")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_method_options(p, threads_default=1)  # the workers already fill the cores, one scene each
    p.set_defaults(func=run_batch_command)
    return p


def options_from_args(args: argparse.Namespace) -> "BatchOptions":
    from shadowcorr.cli import config_from_args

    from .runner import BatchOptions

    return BatchOptions(
        engine=args.engine, workers=args.workers, ray_address=args.ray_address, ray_plan=args.ray_plan,
        actors=args.actors, batch_size=args.batch_size, model_path=args.model, device=args.device,
        config=config_from_args(args), metrics=not args.no_metrics, cameras=args.cameras, limit=args.limit,
    )


def run_batch_command(args: argparse.Namespace) -> int:
    """Entry point of ``shadowcorr batch``; returns the exit status (1 if a scene failed, 130 if interrupted by
    Ctrl-C, 143 if stopped by SIGTERM)."""
    from shadowcorr_client.records import format_summary
    from tqdm import tqdm

    from .runner import describe_plan, print_failures, run_batch

    options = options_from_args(args)
    if options.engine == "ray":
        from .ray_engine import import_ray

        try:
            import_ray()
        except RuntimeError as exc:
            print(f"shadowcorr batch: {exc}", file=sys.stderr)
            return 2
    bar = None

    def on_start(run: BatchRun) -> None:
        nonlocal bar
        if run.unreadable_lines:
            print(f"note: skipped {run.unreadable_lines} unreadable line(s) in {args.out} (an interrupted write)",
                  file=sys.stderr)
        print(describe_plan(run, args.input, options), file=sys.stderr)
        bar = tqdm(total=len(run.todo), unit="scene", desc="batch", dynamic_ncols=True, disable=args.no_progress,
                   file=sys.stderr)

    def on_record(record) -> None:
        assert bar is not None
        if not record.ok:
            bar.write(f"failed {record.scene}: {(record.error or {}).get('message')}", file=sys.stderr)
        bar.update(1)

    terminated = False

    def on_sigterm(signum: int, frame: object) -> None:
        # SIGTERM (kill, systemd, a scheduler) stops the run as Ctrl-C does: the engine
        # shuts down and ends its workers, the lines written stay.  Python's default ends
        # the process at once, with no summary and no shutdown of the engine.
        nonlocal terminated
        terminated = True
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second one must not cut that shutdown short
        raise KeyboardInterrupt

    previous_sigterm = signal.signal(signal.SIGTERM, on_sigterm)
    resume = f"finished scenes are in {args.out}; run the same command again to resume"
    try:
        run = run_batch(args.input, args.out, options, on_start=on_start, on_record=on_record)
    except KeyboardInterrupt:
        if not terminated:
            raise
        # SIGTERM outside the run's own interrupt handling (while finding the scenes): no engine to stop.
        print(f"terminated (SIGTERM): {resume}", file=sys.stderr)
        return 128 + signal.SIGTERM
    finally:
        signal.signal(signal.SIGTERM, previous_sigterm)
        if bar is not None:
            bar.close()
    assert run.summary is not None
    print(format_summary(run.summary))
    print_failures(run)
    if run.interrupted:
        print(f"{'terminated (SIGTERM)' if terminated else 'interrupted'}: {resume}", file=sys.stderr)
        return 128 + signal.SIGTERM if terminated else 130
    return 1 if run.summary.failed else 0
