"""``--engine ray``: the batch as a Ray Data pipeline, on this machine or a Ray cluster.

Two plans, chosen by ``plan`` (``--ray-plan``; ``auto`` takes ``fused`` on CPU and
``staged`` with ``--device cuda``)::

    fused                                    staged
    from_items(scenes)  one block a scene    from_items(scenes)
      .map_batches(     tasks of 2 scenes:     .map(prepare)              tasks: read, segments,
         run_scenes)    read, prepare, one                                shadows, voxel scene
                        forward pass,          .map_batches(NetworkActor) actor pool: one forward
                        clustering, records                               pass per batch of prepared
      .iter_rows()      stream to the driver                              scenes, then clustering
                                               .iter_rows()

``fused`` is the local engine's design on Ray: whole scenes are tasks (two a task, see
``_SCENES_PER_FUSED_TASK``), and each Ray worker process loads the model once
(:func:`shadowcorr_batch.stages.process_model`) and keeps it, as Ray keeps its task workers warm
across tasks and runs.  On CPU this is the faster plan (``benchmarks/bench_batch.py``):
the network is about a quarter of a scene's CPU time and gains nothing from batching there, a
CPU actor is one more process importing torch in every run (about 5 CPU seconds, as
Ray Data ends its actors with the run), and only each scene's path and configuration
cross the object store.  ``staged`` is the plan for GPUs: prepare tasks spread over
every CPU of the cluster while ``--actors`` actors, one GPU each, batch
``--batch-size`` prepared scenes per forward pass.
Clustering runs in the actor right after the network rather than as a third operator of
tasks: it is about 5 % of a scene's CPU time, and on a small cluster Ray Data reserves a
whole CPU for every task operator (measured here: a separate clustering operator left one
of two CPUs reserved and idle, so the prepare tasks ran one at a time), besides shipping
every prepared scene (about 200 kB) through the object store a second time.

Rows are ``{"task": SceneTask}``: a Python object column.  Ray Data keeps such a column
as an Arrow extension type that serialises the object with Ray's own (cloudpickle)
serialisation inside the cluster; the objects are this program's own scene tasks, never
data read from outside, and a ``SceneTask`` holds only numpy arrays, strings and
pydantic models, so it travels without custom code.  The last operator turns each task
into a JSON line, which is all the driver receives.

Every task and actor runs with one OpenMP / BLAS thread (``runtime_env`` environment
variables, so libraries loaded later start that way too, plus
:func:`shadowcorr_batch.stages.single_thread_numerics` for those loaded already), as the local
engine's workers do: one scene per core.

Ray is an optional dependency (``pip install "shadowcorr[ray]"``); nothing here imports
it before :func:`run_ray` is called.
"""

from __future__ import annotations

import json
import logging
import signal
from typing import TYPE_CHECKING, Any, Iterator, Literal, Sequence

import numpy as np

from .ray_watchdog import start_watchdog, stop_watchdog
from .stages import SceneTask, embed_tasks, finish_task, prepare_task, process_model, run_scenes, single_thread_numerics

if TYPE_CHECKING:
    from shadowcorr_client.records import UploadRecord

__all__ = ["run_ray", "import_ray", "resolve_plan", "RAY_MISSING", "RAY_PLANS"]

RAY_MISSING = 'the Ray engine needs Ray: pip install "shadowcorr[ray]"'
RAY_PLANS = ("auto", "fused", "staged")

# A CPU actor reserves no CPU slot: its forward passes (and clustering) are about a
# quarter of a scene's CPU time, and Ray schedules whole CPUs, so any share of one (even
# 0.2) would leave room for one prepare task fewer on that node (one of two here).
_ACTOR_CPUS_ON_CPU = 0
# Scenes per fused task.  Ray Data notices a finished task only when its scheduling loop
# next polls (every 0.1 s, longer on a busy machine), and only then submits the next one:
# measured here, 0.1-0.2 s idle per task on each core, a quarter of a 0.45 s scene.  Two
# scenes a task halve that; more leave a core idle at the end of a run for longer (50
# scenes on 2 CPUs, warm: 17.0 s with one scene a task, 15.3 s with two, 17.7 s with
# three, median of 3; the local engine 19.6 s at the same time, load average 7-8).
_SCENES_PER_FUSED_TASK = 2
# Set before the worker imports numpy / torch, so every thread pool starts at one thread.
_ONE_THREAD_ENV = {"env_vars": {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}}
_numerics_limited = False


def import_ray() -> Any:
    """``ray`` with Ray Data, or a ``RuntimeError`` saying how to install it."""
    try:
        import ray
        import ray.data  # noqa: F401  (the [data] extra: pyarrow, pandas)
    except ImportError as exc:
        raise RuntimeError(f"{RAY_MISSING} ({exc})") from None
    return ray


def resolve_plan(plan: str, device: str) -> Literal["fused", "staged"]:
    """``fused`` or ``staged`` for ``plan`` (``auto``: staged when the network runs on a GPU)."""
    if plan == "auto":
        return "staged" if device.startswith("cuda") else "fused"
    if plan not in RAY_PLANS:
        raise ValueError(f"unknown Ray plan {plan!r}; choose one of {', '.join(RAY_PLANS)}")
    return plan  # type: ignore[return-value]


def _limit_numerics() -> None:
    """:func:`single_thread_numerics`, once per worker process (it takes a few milliseconds)."""
    global _numerics_limited
    if not _numerics_limited:
        single_thread_numerics()
        _numerics_limited = True


def _records_column(records: Sequence["UploadRecord"]) -> np.ndarray:
    return np.array([r.to_json() for r in records], dtype=object)


def _scenes_batch(batch: dict[str, np.ndarray], model_path: str | None, device: str,
                  needs_model: bool) -> dict[str, np.ndarray]:
    _limit_numerics()
    model = process_model(model_path, device) if needs_model else None
    return {"record": _records_column(run_scenes(list(batch["task"]), model))}


def _prepare_row(row: dict[str, Any]) -> dict[str, Any]:
    _limit_numerics()
    return {"task": prepare_task(row["task"])}


class NetworkActor:
    """Holds the model; each call runs one forward pass over a batch of prepared scenes, then clusters each."""

    def __init__(self, model_path: str | None, device: str) -> None:
        from shadowcorr.nn import load_model

        if device == "cpu":
            single_thread_numerics()
        self.model = load_model(model_path, device=device)

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {"record": _records_column([finish_task(t) for t in embed_tasks(self.model, list(batch["task"]))])}


def run_ray(
    tasks: Sequence[SceneTask],
    *,
    address: str | None = None,
    workers: int | None = None,
    plan: str = "auto",
    actors: int = 1,
    batch_size: int = 8,
    model_path: str | None = None,
    device: str = "cpu",
    needs_model: bool = True,
) -> Iterator["UploadRecord"]:
    """Run every task on Ray Data; yield each record as soon as its scene is done.

    Without ``address`` a local Ray instance is started with ``workers`` CPUs (and shut
    down at the end, or by :mod:`shadowcorr_batch.ray_watchdog` if this process dies first); with
    one (``auto``, ``ray://host:10001``, ``host:6379``) the run joins that cluster, whose
    nodes need shadowcorr installed.  ``plan`` picks the pipeline (module docstring).
    With ``staged``, ``actors`` network actors hold the model, each taking up to
    ``batch_size`` prepared scenes per forward pass, with one GPU each when ``device`` is
    ``cuda``; methods without a network always run ``fused``.
    """
    from shadowcorr_client.records import UploadRecord

    if actors < 1:
        raise ValueError(f"actors must be >= 1, got {actors}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    plan = resolve_plan(plan, device) if needs_model else "fused"
    if not tasks:
        return
    ray = import_ray()
    started_here = not ray.is_initialized()
    watchdog = None
    try:
        if started_here:
            sigterm = signal.getsignal(signal.SIGTERM)
            if address:
                ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
            else:
                watchdog = start_watchdog()  # the instance's agents outlive a killed driver (see the module)
                ray.init(num_cpus=workers, include_dashboard=False, logging_level=logging.WARNING, log_to_driver=False)
            # ray.init replaces the program's SIGTERM handler with a bare sys.exit(15): keep the
            # program's own (the CLI's stops the run like Ctrl-C, with its own message and status).
            if sigterm is not None and signal.getsignal(signal.SIGTERM) is not sigterm:
                signal.signal(signal.SIGTERM, sigterm)
        context = ray.data.DataContext.get_current()
        context.enable_progress_bars = False  # the runner draws its own bar, counting finished scenes
        context.print_on_execution_start = False
        # The task column holds Python objects by design (see the module docstring): say so,
        # which also silences Ray's warning about falling back to them.
        context.enable_fallback_to_arrow_object_ext_type = True
        # One block per scene: every scene is its own task, spread over the cluster.
        ds = ray.data.from_items([{"task": t} for t in tasks], override_num_blocks=len(tasks))
        if plan == "fused":
            ds = ds.map_batches(
                _scenes_batch,
                fn_kwargs={"model_path": model_path, "device": device, "needs_model": needs_model},
                batch_size=_SCENES_PER_FUSED_TASK,
                batch_format="numpy",
                num_cpus=1,
                runtime_env=_ONE_THREAD_ENV,
            )
        else:
            gpu = device.startswith("cuda")
            ds = ds.map(_prepare_row, num_cpus=1, runtime_env=_ONE_THREAD_ENV).map_batches(
                NetworkActor,
                fn_constructor_kwargs={"model_path": model_path, "device": device},
                batch_size=batch_size,
                batch_format="numpy",
                compute=ray.data.ActorPoolStrategy(size=actors),
                num_cpus=1 if gpu else _ACTOR_CPUS_ON_CPU,
                num_gpus=1 if gpu else None,
                runtime_env=_ONE_THREAD_ENV,
            )
        for row in ds.iter_rows():
            yield UploadRecord.from_dict(json.loads(row["record"]))
    finally:
        if started_here:
            ray.shutdown()
        if watchdog is not None:
            stop_watchdog(watchdog)
