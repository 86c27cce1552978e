"""One batch run: find the scenes, skip those already done, run the rest on an engine,
append one JSON line per finished scene, and summarise.

The results file is the one ``shadowcorr-client upload-dataset`` writes (same record
shape, same reader and writer from :mod:`shadowcorr_client.records`): each line is written and
flushed as soon as its scene finishes, so an interrupted run keeps every finished scene
and running the same command again does only the rest (a ``failed`` scene is tried
again; its new line supersedes the old one).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Literal, Sequence

from shadowcorr_client.dataset import SceneSource, discover_scenes
from shadowcorr_client.records import RecordWriter, UploadRecord, UploadSummary, read_records, summarize_records
from shadowcorr.config import NETWORK_METHODS, ShadowCorrConfig

from .stages import SceneTask

__all__ = ["BatchOptions", "BatchRun", "plan_batch", "run_batch", "ENGINES"]

ENGINES = ("local", "ray")


@dataclass
class BatchOptions:
    """How to run a batch (the ``shadowcorr batch`` flags)."""

    engine: Literal["local", "ray"] = "local"
    workers: int = 2  # processes (local) or the local Ray instance's CPUs
    ray_address: str | None = None
    ray_plan: Literal["auto", "fused", "staged"] = "auto"  # Ray: whole scenes as tasks, or prepare tasks + actors
    actors: int = 1  # Ray, staged: network actors, each holding the model
    batch_size: int = 8  # Ray, staged: prepared scenes per forward pass
    model_path: str | None = None
    device: str = "cpu"
    config: ShadowCorrConfig = field(default_factory=ShadowCorrConfig)
    metrics: bool = True
    cameras: Sequence[int] | None = None
    limit: int | None = None


@dataclass
class BatchRun:
    """What one run found and did."""

    scenes: list[SceneSource]
    todo: list[SceneSource]
    skipped: int  # already ok in the results file
    unreadable_lines: int  # torn lines skipped in the results file
    records: list[UploadRecord] = field(default_factory=list)
    interrupted: bool = False
    summary: UploadSummary | None = None


def plan_batch(input_path: str | Path, out: str | Path, options: BatchOptions) -> tuple[BatchRun, dict[str, UploadRecord]]:
    """The scenes under ``input_path`` and those still to do given the results file ``out``."""
    scenes = discover_scenes(input_path, options.cameras)
    latest, bad = read_records(out)
    done = {name for name, record in latest.items() if record.ok}
    todo = [s for s in scenes if s.name not in done]
    skipped = len(scenes) - len(todo)
    if options.limit is not None:
        todo = todo[: options.limit]
    return BatchRun(scenes=scenes, todo=todo, skipped=skipped, unreadable_lines=bad), latest


def _engine_records(todo: Sequence[SceneSource], options: BatchOptions) -> Iterator[UploadRecord]:
    tasks = [SceneTask(source=s, config=options.config, metrics=options.metrics) for s in todo]
    needs_model = options.config.method in NETWORK_METHODS
    common = dict(model_path=options.model_path, device=options.device, needs_model=needs_model)
    if options.engine == "ray":
        from .ray_engine import run_ray

        return run_ray(tasks, address=options.ray_address, workers=None if options.ray_address else options.workers,
                       plan=options.ray_plan, actors=options.actors, batch_size=options.batch_size, **common)
    if options.engine == "local":
        from .local import run_local

        return run_local(tasks, workers=options.workers, **common)
    raise ValueError(f"unknown engine {options.engine!r}; choose one of {', '.join(ENGINES)}")


def run_batch(
    input_path: str | Path,
    out: str | Path,
    options: BatchOptions,
    *,
    on_start: Callable[[BatchRun], None] | None = None,
    on_record: Callable[[UploadRecord], None] | None = None,
) -> BatchRun:
    """Run every scene of ``input_path`` not yet ``ok`` in ``out``; returns the run with its summary.

    ``on_start`` sees the plan before any scene runs, ``on_record`` every record right
    after its line is on disk (the CLI draws its progress bar with them).  A
    ``KeyboardInterrupt`` ends the run early with ``interrupted`` set; the lines written
    until then stay.
    """
    run, latest = plan_batch(input_path, out, options)
    if on_start is not None:
        on_start(run)
    start = time.perf_counter()
    if run.todo:
        records = _engine_records(run.todo, options)
        with RecordWriter(out) as writer:
            try:
                for record in records:
                    writer.write(record)  # first, so the line is on disk whatever happens next
                    run.records.append(record)
                    latest[record.scene] = record
                    if on_record is not None:
                        on_record(record)
            except KeyboardInterrupt:
                run.interrupted = True
            finally:
                close = getattr(records, "close", None)
                if close is not None:  # stops the engine: cancels scenes not started, shuts Ray down
                    close()
    run.summary = summarize_records([s.name for s in run.scenes], run.skipped, run.records, latest,
                                    time.perf_counter() - start)
    return run


def describe_plan(run: BatchRun, input_path: str | Path, options: BatchOptions) -> str:
    """One line saying what is about to happen (printed on stderr by the CLI)."""
    where = (f"Ray at {options.ray_address}" if options.engine == "ray" and options.ray_address
             else f"{options.engine} engine, {options.workers} workers")
    if options.engine == "ray":
        from .ray_engine import resolve_plan

        plan = resolve_plan(options.ray_plan, options.device)
        where += (f", {plan} plan" + (f", {options.actors} network actor(s) of batch {options.batch_size}"
                                      if plan == "staged" else ""))
    return (f"{len(run.scenes)} scenes in {input_path}: {run.skipped} already done, "
            f"running {len(run.todo)} on the {where}" + (f" ({options.device})" if options.device != "cpu" else ""))


def print_failures(run: BatchRun) -> None:
    if run.summary is None:
        return
    for scene, message in run.summary.failures:
        print(f"failed {scene}: {message}", file=sys.stderr)
