"""``--engine ray``: the batch as a Ray Data pipeline, on this machine or a Ray cluster.

::

    from_items(scenes)                     one block per scene
      .map(prepare)                        tasks: read the bundle, segments, shadows, voxel scene
      .map_batches(NetworkActor, ...)      an actor pool; each actor holds the model and runs one
                                           forward pass over a batch of prepared scenes
      .map(finish)                         tasks: clustering, labels, the result record
      .iter_rows()                         records stream back to the driver as scenes finish

Rows are ``{"task": SceneTask}``: a Python object column.  Ray Data keeps such a column
as an Arrow extension type that serialises the object with Ray's own (cloudpickle)
serialisation inside the cluster; the objects are this program's own scene tasks, never
data read from outside, and a ``SceneTask`` holds only numpy arrays, strings and
pydantic models, so it travels without custom code.  The last stage turns each task
into a JSON line, which is all the driver receives.

Ray is an optional dependency (``pip install "shadowcorr[ray]"``); nothing here imports
it before :func:`run_ray` is called.
"""

from __future__ import annotations

import json
import logging
from typing import TYPE_CHECKING, Any, Iterator, Sequence

import numpy as np

from .stages import SceneTask, embed_tasks, finish_task, prepare_task, single_thread_numerics

if TYPE_CHECKING:
    from clients.records import UploadRecord

__all__ = ["run_ray", "import_ray", "RAY_MISSING"]

RAY_MISSING = 'the Ray engine needs Ray: pip install "shadowcorr[ray]"'

# A CPU actor reserves no CPU slot: its forward pass is a small share of a scene's
# work (network ~10 % of a scene's CPU time, see the README), so reserving a whole core
# for it would leave that core idle most of the time and cost a prepare/finish slot.
_ACTOR_CPUS_ON_CPU = 0


def import_ray() -> Any:
    """``ray`` with Ray Data, or a ``RuntimeError`` saying how to install it."""
    try:
        import ray
        import ray.data  # noqa: F401  (the [data] extra: pyarrow, pandas)
    except ImportError as exc:
        raise RuntimeError(f"{RAY_MISSING} ({exc})") from None
    return ray


def _prepare_row(row: dict[str, Any]) -> dict[str, Any]:
    single_thread_numerics()
    return {"task": prepare_task(row["task"])}


def _finish_row(row: dict[str, Any]) -> dict[str, Any]:
    single_thread_numerics()
    return {"record": finish_task(row["task"]).to_json()}


class NetworkActor:
    """Holds the model; each call runs one forward pass over a batch of prepared scenes."""

    def __init__(self, model_path: str | None, device: str) -> None:
        from shadowcorr.nn import load_model

        if device == "cpu":
            single_thread_numerics()
        self.model = load_model(model_path, device=device)

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        tasks = embed_tasks(self.model, list(batch["task"]))
        out = np.empty(len(tasks), dtype=object)  # np.array(tasks) would try to unpack the dataclasses
        out[:] = tasks
        return {"task": out}


def run_ray(
    tasks: Sequence[SceneTask],
    *,
    address: str | None = None,
    workers: int | None = None,
    actors: int = 1,
    batch_size: int = 8,
    model_path: str | None = None,
    device: str = "cpu",
    needs_model: bool = True,
) -> Iterator["UploadRecord"]:
    """Run every task on Ray Data; yield each record as soon as its scene is done.

    Without ``address`` a local Ray instance is started with ``workers`` CPUs (and shut
    down at the end); with one (``auto``, ``ray://host:10001``, ``host:6379``) the run
    joins that cluster, whose nodes need shadowcorr installed.  ``actors`` network
    actors hold the model, each taking up to ``batch_size`` prepared scenes per forward
    pass, with one GPU each when ``device`` is ``cuda``.
    """
    from clients.records import UploadRecord

    if actors < 1:
        raise ValueError(f"actors must be >= 1, got {actors}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if not tasks:
        return
    ray = import_ray()
    started_here = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, logging_level=logging.WARNING, log_to_driver=False)
        started_here = True
    try:
        context = ray.data.DataContext.get_current()
        context.enable_progress_bars = False  # the runner draws its own bar, counting finished scenes
        context.print_on_execution_start = False
        # The task column holds Python objects by design (see the module docstring): say so,
        # which also silences Ray's warning about falling back to them.
        context.enable_fallback_to_arrow_object_ext_type = True
        # One block per scene: every scene is its own prepare task, spread over the cluster.
        ds = ray.data.from_items([{"task": t} for t in tasks], override_num_blocks=len(tasks))
        ds = ds.map(_prepare_row, num_cpus=1)
        if needs_model:
            gpu = device.startswith("cuda")
            ds = ds.map_batches(
                NetworkActor,
                fn_constructor_kwargs={"model_path": model_path, "device": device},
                batch_size=batch_size,
                batch_format="numpy",
                compute=ray.data.ActorPoolStrategy(size=actors),
                num_cpus=1 if gpu else _ACTOR_CPUS_ON_CPU,
                num_gpus=1 if gpu else None,
            )
        ds = ds.map(_finish_row, num_cpus=1)
        for row in ds.iter_rows():
            yield UploadRecord.from_dict(json.loads(row["record"]))
    finally:
        if started_here:
            ray.shutdown()
