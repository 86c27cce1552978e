"""The three stages of one scene, shared by both engines: prepare, embed (batched), finish.

A :class:`SceneTask` carries one scene through them.  It holds only plain values, numpy
arrays and pydantic models, so it crosses process boundaries (the local process pool)
and Ray's object store as it is.  Every stage catches a scene's own failure and keeps
it on the task as an error, so one bad scene becomes one ``failed`` line in the results
file instead of ending a run over thousands.

Labels equal ``shadowcorr correspond`` on the same scene: the stages are the library's
``prepare`` / ``embed`` / ``assign`` with the same configuration, and ``embed`` over a
batch of scenes gives each scene the embeddings it gets alone (scenes never interact in
the network; ``tests/test_batch.py`` checks the labels).
"""

from __future__ import annotations

import functools
import json
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from shadowcorr.config import ShadowCorrConfig
from shadowcorr.config import NETWORK_METHODS
from shadowcorr.pipeline import assign, baseline_embeddings, embed, model_info, prepare
from shadowcorr.result import ModelInfo
from shadowcorr.stages import VoxelScene

if TYPE_CHECKING:
    from shadowcorr_client.dataset import SceneSource
    from shadowcorr_client.records import UploadRecord
    from shadowcorr.nn import Model

__all__ = ["SceneTask", "prepare_task", "embed_tasks", "finish_task", "run_scenes", "process_model", "error_dict",
           "single_thread_numerics"]

@dataclass
class SceneTask:
    """One scene on its way through the stages.

    ``busy_ms`` adds up the scene's own processing time (reading, preparing, its share of
    the batched forward pass, clustering): the ``latency_ms`` of its record.  Time spent
    waiting in queues between stages is not in it.
    """

    source: "SceneSource"
    config: ShadowCorrConfig
    metrics: bool = True
    scene: VoxelScene | None = None
    embeddings: np.ndarray | None = None
    model: ModelInfo | None = None
    error: dict[str, Any] | None = None
    busy_ms: float = 0.0
    extra_timings_ms: dict[str, float] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.source.name


def error_dict(exc: BaseException) -> dict[str, Any]:
    """A failure as the results file records it: ``{"type", "message"[, "problems"]}``.

    The same shape ``upload-dataset`` writes for a scene it could not read; the library's
    ``BundleError`` adds its list of ``{loc, msg}`` problems.
    """
    error: dict[str, Any] = {"type": type(exc).__name__, "message": str(exc)}
    problems = getattr(exc, "problems", None)
    if problems:
        error["problems"] = [p.model_dump() if hasattr(p, "model_dump") else p for p in problems]
    return error


def prepare_task(task: SceneTask) -> SceneTask:
    """Read the scene and run the library's ``prepare`` (segments, shadows, voxel scene)."""
    t0 = time.perf_counter()
    try:
        bundle = task.source.load_bundle()
        load_ms = (time.perf_counter() - t0) * 1e3
        scene = prepare(bundle, task.config)
    except Exception as exc:  # noqa: BLE001 - one unreadable scene must not end a long run
        task.error = error_dict(exc)
    else:
        task.extra_timings_ms["load"] = load_ms
        task.scene = scene
    task.busy_ms += (time.perf_counter() - t0) * 1e3
    return task


def embed_tasks(model: "Model | None", tasks: Sequence[SceneTask]) -> list[SceneTask]:
    """One forward pass over every prepared scene of ``tasks``.

    Each scene's ``network`` timing is its share of the pass, in proportion to its voxels,
    so that summing ``network`` over scenes gives the time the network really ran.  The
    methods without a network (``projection``, ``meanshift``) pass through untouched.
    """
    ready = [t for t in tasks if t.scene is not None and t.error is None and t.config.method in NETWORK_METHODS]
    if not ready:
        return list(tasks)
    if model is None:
        raise ValueError(f"method {ready[0].config.method!r} needs a model")
    t0 = time.perf_counter()
    try:
        outputs = embed(model, [t.scene for t in ready])
    except Exception as exc:  # noqa: BLE001 - e.g. a model that does not fit the scenes' configuration
        for t in ready:
            t.error = error_dict(exc)
        return list(tasks)
    pass_ms = (time.perf_counter() - t0) * 1e3
    info = model_info(model)
    total_voxels = max(sum(t.scene.num_voxels for t in ready), 1)
    for t, out in zip(ready, outputs):
        share = pass_ms * t.scene.num_voxels / total_voxels
        t.embeddings = out
        t.model = info
        t.extra_timings_ms["network"] = share
        t.busy_ms += share
    return list(tasks)


def finish_task(task: SceneTask) -> "UploadRecord":
    """Cluster and label (the library's ``assign``) and turn the outcome into a record."""
    from shadowcorr_client.records import UploadRecord

    source = str(task.source.path)
    if task.error is None:
        t0 = time.perf_counter()
        try:
            scene = task.scene
            assert scene is not None, "finish_task needs a prepared scene"
            scene.timings_ms.update(task.extra_timings_ms)
            if task.config.method not in NETWORK_METHODS:
                result = assign(scene, baseline_embeddings(scene), task.config, metrics=task.metrics)
            else:
                result = assign(scene, task.embeddings, task.config, model=task.model, metrics=task.metrics)
        except Exception as exc:  # noqa: BLE001 - recorded as this scene's failure
            task.error = error_dict(exc)
        task.busy_ms += (time.perf_counter() - t0) * 1e3
    if task.error is not None:
        return UploadRecord(task.name, "failed", latency_ms=task.busy_ms, error=task.error, source=source)
    # Through JSON text, not model_dump(): the results file must be strict JSON (NaN -> null).
    return UploadRecord(task.name, "ok", latency_ms=task.busy_ms, result=json.loads(result.model_dump_json()),
                        source=source)


def run_scenes(tasks: Sequence[SceneTask], model: "Model | None") -> list["UploadRecord"]:
    """Whole scenes in this process: read and prepare each, one forward pass over them all, cluster each."""
    prepared = [prepare_task(t) for t in tasks]
    return [finish_task(t) for t in embed_tasks(model, prepared)]


@functools.lru_cache(maxsize=2)
def process_model(model_path: str | None, device: str) -> "Model":
    """The model, loaded once per process and kept for every later scene it runs.

    A worker process (the local pool's, or a Ray task worker, which Ray keeps and reuses
    across tasks and runs) pays for loading once; loading is tens of milliseconds once
    torch is imported, so a process that runs whole scenes needs no actor to hold it.
    """
    from shadowcorr.nn import load_model

    return load_model(model_path, device=device)


def single_thread_numerics() -> None:
    """One BLAS / OpenMP / torch thread in this process: the engines run one scene per core.

    Several multi-threaded processes on the same cores slow each other down many times
    over (measured here: clustering 3.3 s with 2 threads vs 1.2 s with 1 on a loaded
    2-core machine).  Environment variables come too late in a process that has already
    imported numpy, scipy, pykdtree and torch, so the limits are set on the loaded
    libraries themselves.
    """
    import torch
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)  # OpenBLAS (numpy/scipy) and OpenMP (pykdtree)
    torch.set_num_threads(1)
