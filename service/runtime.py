"""The running service: model, worker pool, batcher, admission control and the request flow.

Request flow of ``POST /correspond`` (method ``shadowcorr``)::

    event loop:  admit (bounded) -> read body (counted) -------------------------------> respond
    workers:                         decode + prepare ---------------> assign (JSON)
    inference thread:                                  embed (batched)

The event loop only does I/O and bookkeeping; JSON for the result is produced by the
worker that ran ``assign``.  Method ``meanshift`` has no network and runs as a single
worker job.

Start-up happens in the background so that ``/health`` answers (503, ``ready: false``)
while the model loads and the workers warm up; ready means: model loaded, one warm-up
forward pass done, and every worker started and warmed up (one ``prepare`` + one
``assign`` in its initializer).
"""

from __future__ import annotations

import asyncio
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from shadowcorr import __version__
from shadowcorr.config import REQUEST_OPTIONS, ShadowCorrConfig
from shadowcorr.nn import Model, load_model
from shadowcorr.pipeline import check_compatible, embed, model_info
from shadowcorr.result import ModelInfo
from shadowcorr.voxel_scene import VoxelScene

from . import jobs
from .batcher import DynamicBatcher
from .errors import ApiError, JobError
from .limits import RequestLimits
from .metrics import ServiceMetrics
from .settings import ServiceSettings
from .workers import PRIORITY_FINISH, PRIORITY_START, WorkerCrashed, WorkerPool

__all__ = ["Runtime"]

log = logging.getLogger("shadowcorr.service")

#: /health status -> the message sent with ``error: not_ready`` (a failed start sends its own error).
_NOT_READY = {
    "failed": "the server failed to start",
    "starting": "the server is starting: loading the model and warming up the workers",
    "unavailable": "every worker is being replaced",
}


class Runtime:
    """Owns every long-lived resource of one service instance."""

    def __init__(self, settings: ServiceSettings, metrics: ServiceMetrics | None = None) -> None:
        self.settings = settings
        self.metrics = metrics or ServiceMetrics()
        self.limits = RequestLimits.from_settings(settings)
        self.base_config = ShadowCorrConfig()
        self.started_at = time.monotonic()
        self.model: Model | None = None
        self.model_info: ModelInfo | None = None
        self.warmed_up = False
        self.startup_error: str | None = None
        self.in_flight = 0
        self.preparing = 0  # admitted requests that may still reach the batcher (it waits for them)
        self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="shadowcorr-inference")
        self.pool = WorkerPool(
            settings.workers,
            torch_threads=settings.torch_threads,
            metrics=self.metrics,
            startup_timeout_s=settings.startup_timeout_s,
            kill_grace_s=settings.request_timeout_s,
        )
        self.batcher: DynamicBatcher[VoxelScene, np.ndarray] = DynamicBatcher(
            self._embed,
            max_batch_size=settings.max_batch_size,
            max_wait_s=settings.max_wait_ms / 1000.0,
            metrics=self.metrics,
            thread=self._thread,
            upstream=lambda: self.preparing,
        )
        self._startup_task: asyncio.Task | None = None

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Load the model, then start workers and batcher; warm-up continues in the background.

        A model that cannot be loaded, or that does not fit the configuration, fails
        the start (the process exits with an error): a container should crash loudly
        on a bad model file rather than serve 503s forever.  Loading takes well under a
        second; the slow part, starting and warming up the workers, runs in the
        background while ``/health`` answers 503.
        """
        self.started_at = time.monotonic()
        loop = asyncio.get_running_loop()
        # torch work (threads setting, file read, state-dict checks) stays off the event loop.
        self.model = await loop.run_in_executor(self._thread, self._load_model)
        self.model_info = model_info(self.model)
        check_compatible(self.model, self.base_config)
        self.pool.start()
        self.batcher.start()
        self._startup_task = asyncio.create_task(self._start_up(), name="startup")

    async def _start_up(self) -> None:
        loop = asyncio.get_running_loop()
        assert self.model is not None
        try:
            scene = await self.pool.run(jobs.warmup_scene, priority=PRIORITY_FINISH)
            await loop.run_in_executor(self._thread, embed, self.model, [scene])  # warm-up forward pass
            await self.pool.wait_started()
            self.warmed_up = True
            self._update_ready()
            log.info("ready: model %s %s (sha256 %s…), %d workers", self.model.name, self.model.version,
                     self.model.sha256[:12], self.pool.ready_count)
        except asyncio.CancelledError:
            raise
        except Exception as e:  # warm-up failed: stay up and say why on /health and /info
            self.startup_error = f"{type(e).__name__}: {e}"
            log.exception("start-up failed")

    def _load_model(self) -> Model:
        import torch

        torch.set_num_threads(self.settings.inference_threads)
        return load_model(self.settings.model_path, device=self.settings.device)

    async def stop(self) -> None:
        if self._startup_task is not None:
            self._startup_task.cancel()
            await asyncio.gather(self._startup_task, return_exceptions=True)
        await self.batcher.close()
        await self.pool.close()
        self._thread.shutdown(wait=True)

    # ------------------------------------------------------------------ state
    @property
    def ready(self) -> bool:
        return self.warmed_up and self.pool.ready_count > 0

    def _update_ready(self) -> None:
        self.metrics.ready.set(1 if self.ready else 0)

    def health(self) -> dict[str, Any]:
        """The ``/health`` body; ``ready`` decides 200 or 503."""
        ready = self.ready
        self._update_ready()
        if self.startup_error:
            status = "failed"
        elif not self.warmed_up:
            status = "starting"
        elif not ready:
            status = "unavailable"  # every worker is being replaced
        elif self.pool.ready_count < self.pool.size:
            status = "degraded"  # some worker is being replaced; still serving
        else:
            status = "ok"
        return {
            "status": status,
            "ready": ready,
            "model": self.model_info.model_dump() if self.model_info else None,
            "uptime_s": round(time.monotonic() - self.started_at, 3),
            "queue_depth": self.in_flight,
            "workers": {"configured": self.pool.size, "ready": self.pool.ready_count, "restarts": self.pool.restarts},
            "batcher": {"pending": self.batcher.pending, "batches": self.batcher.batches},
            # While not ready, the same error shape as every other 503: clients show the code, not "http_503".
            **({} if ready else {"error": "not_ready", "message": self.startup_error or _NOT_READY[status]}),
        }

    def info(self) -> dict[str, Any]:
        s = self.settings
        model = None
        if self.model is not None:
            model = {
                "name": self.model.name,
                "version": self.model.version,
                "sha256": self.model.sha256,
                "path": str(self.model.path) if s.model_path is not None else "(packaged default)",
                "card": self.model.card.model_dump(mode="json"),
            }
        return {
            "service": "shadowcorr",
            "version": __version__,
            "ready": self.ready,
            "model": model,
            "limits": {
                "max_body_bytes": s.max_body_bytes,
                "max_uncompressed_bytes": s.max_uncompressed_bytes,
                "max_files": s.max_files,
                "max_views": s.max_views,
                "max_pixels_per_view": s.max_pixels_per_view,
                "max_segments": s.max_segments,
                "queue_size": s.queue_size,
                "request_timeout_s": s.request_timeout_s,
            },
            "batching": {"max_batch_size": s.max_batch_size, "max_wait_ms": s.max_wait_ms},
            "request_options": {
                name: {
                    "default": getattr(self.base_config, name),
                    "description": ShadowCorrConfig.model_fields[name].description or "",
                }
                for name in _request_options()
            },
            "methods": ["shadowcorr", "meanshift"],
            "units": self.base_config.units,
            "settings": s.public_dict(),
            **({"error": self.startup_error} if self.startup_error else {}),
        }

    # ------------------------------------------------------------------ requests
    def admit(self) -> "Ticket":
        """Count a request in, or refuse it (503) when not ready or when the queue is full."""
        headers = {"Retry-After": str(self.settings.retry_after_s)}
        if not self.ready:
            why = self.startup_error or "the model is loading and the workers are warming up"
            raise ApiError(503, "not_ready", f"the service is not ready: {why}", headers=headers)
        if self.in_flight >= self.settings.queue_size:
            raise ApiError(
                503,
                "overloaded",
                f"{self.in_flight} requests in flight, the limit is {self.settings.queue_size}; retry later",
                headers=headers,
            )
        self.in_flight += 1
        self.preparing += 1
        self.metrics.queue_depth.set(self.in_flight)
        return Ticket()

    def left_upstream(self, ticket: "Ticket") -> None:
        """The request will not reach the batcher any more (it has a scene, or failed)."""
        if ticket.upstream:
            ticket.upstream = False
            self.preparing -= 1

    def release(self, ticket: "Ticket") -> None:
        self.left_upstream(ticket)
        self.in_flight -= 1
        self.metrics.queue_depth.set(self.in_flight)

    async def correspond(
        self, ticket: "Ticket", body: bytes, content_type: str, config: ShadowCorrConfig, metrics: bool
    ) -> bytes:
        """Run one scene through the pipeline; returns the Result JSON bytes."""
        stage = self.metrics.stage_latency
        t_start = time.perf_counter()
        try:
            if config.method == "meanshift":
                self.left_upstream(ticket)  # no network: never in the batcher
                out = await self.pool.run(jobs.baseline, body, content_type, config, self.limits, metrics)
                stage.labels("baseline").observe(time.perf_counter() - t_start)
                return out
            try:
                prepared: jobs.Prepared = await self.pool.run(
                    jobs.decode_and_prepare, body, content_type, config, self.limits, priority=PRIORITY_START
                )
            finally:
                self.left_upstream(ticket)
            del body  # the upload is no longer needed; let it go before the long waits
            t_prepared = time.perf_counter()
            stage.labels("queue").observe(max(0.0, t_prepared - t_start - (prepared.decode_ms + prepared.prepare_ms) / 1e3))
            stage.labels("decode").observe(prepared.decode_ms / 1e3)
            stage.labels("prepare").observe(prepared.prepare_ms / 1e3)
            embeddings, batch = await self.batcher.submit(prepared.scene)
            stage.labels("batch_wait").observe(batch.wait_s)
            extra = {"decode": prepared.decode_ms, "batch_wait": batch.wait_s * 1e3, "network": batch.run_s * 1e3}
            t_assign = time.perf_counter()
            out = await self.pool.run(
                jobs.assign_scene, prepared.scene, embeddings, config, self.model_info, metrics, extra,
                priority=PRIORITY_FINISH,
            )
            stage.labels("assign").observe(time.perf_counter() - t_assign)
            return out
        except JobError as e:
            raise e.to_api() from None
        except WorkerCrashed as e:
            raise ApiError(500, "worker_crashed", f"{e}; it has been replaced, retrying the request is safe") from None
        finally:
            stage.labels("total").observe(time.perf_counter() - t_start)

    def _embed(self, scenes: list[VoxelScene]) -> list[np.ndarray]:
        """Runs in the inference thread."""
        assert self.model is not None
        return embed(self.model, scenes)


class Ticket:
    """One admitted request's place in the bookkeeping."""

    __slots__ = ("upstream",)

    def __init__(self) -> None:
        self.upstream = True


def _request_options() -> tuple[str, ...]:
    return REQUEST_OPTIONS
