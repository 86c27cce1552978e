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
import re
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from shadowcorr import __version__
from shadowcorr.config import METHODS, NETWORK_METHODS, REQUEST_OPTIONS, ShadowCorrConfig
from shadowcorr.nn import Model, load_model
from shadowcorr.pipeline import check_compatible, embed, model_info
from shadowcorr.result import ModelInfo
from shadowcorr.stages import VoxelScene

from . import jobs
from .batcher import DynamicBatcher
from .errors import ApiError, JobError
from .limits import ByteBudget, RequestLimits, Upload, UploadRules, receive_body
from .metrics import ServiceMetrics
from .settings import ServiceSettings
from .spool import SpoolDir, remove_stale_spool_dirs
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
        self.base_config = ShadowCorrConfig(max_stage_seconds=settings.max_stage_seconds)
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
            memory_bytes=settings.worker_memory_bytes,
            metrics=self.metrics,
            startup_timeout_s=settings.startup_timeout_s,
            kill_grace_s=settings.cancel_grace_s,
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
        self.budget = ByteBudget(settings.max_upload_bytes_in_flight)
        self.per_client: dict[str, int] = {}  # admitted requests by client address
        self.upload_rules = UploadRules.from_settings(settings)
        self.shutdown_deadline: float | None = None  # time.monotonic() by which requests must be answered
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_event = asyncio.Event()
        self.spool: SpoolDir | None = None  # this server's directory for large bodies, from start()

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
        loop = self._loop = asyncio.get_running_loop()
        # Bodies a crashed (SIGKILLed) server was receiving would otherwise stay on disk for good.
        for path in remove_stale_spool_dirs():
            log.info("removed %s: spooled bodies of a server that is no longer running", path)
        self.spool = SpoolDir()
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
        await self.pool.close()  # no worker reads a spooled body any more
        self._thread.shutdown(wait=True)
        if self.spool is not None:
            self.spool.close()

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
            # Which model runs is said by name, version and checksum; where its file lies on this
            # machine, or lay on the machine that trained it, is no business of a client.
            model = {
                "name": self.model.name,
                "version": self.model.version,
                "sha256": self.model.sha256,
                "packaged": s.model_path is None,
                "card": _without_paths(self.model.card.model_dump(mode="json")),
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
                "max_scene_points": s.max_scene_points,
                "max_requests_per_client": s.max_requests_per_client,
                "max_upload_bytes_in_flight": s.max_upload_bytes_in_flight,
                "queue_size": s.queue_size,
                "request_timeout_s": s.request_timeout_s,
                "max_stage_seconds": s.max_stage_seconds,
            },
            "batching": {"max_batch_size": s.max_batch_size, "max_wait_ms": s.max_wait_ms},
            "request_options": {
                name: {
                    "default": getattr(self.base_config, name),
                    "description": ShadowCorrConfig.model_fields[name].description or "",
                }
                for name in _request_options()
            },
            "methods": list(METHODS),
            "units": self.base_config.units,
            "settings": s.public_dict(),
            **({"error": self.startup_error} if self.startup_error else {}),
        }

    # ------------------------------------------------------------------ requests
    def begin_shutdown(self) -> None:
        """SIGTERM / SIGINT arrived (called from the signal handler, so thread-safe).

        In-flight requests get ``graceful_shutdown_s`` from now to finish; those still
        running then are answered 503 by :meth:`until_shutdown_deadline`.
        """
        if self._loop is not None and self.shutdown_deadline is None:
            deadline = time.monotonic() + self.settings.graceful_shutdown_s
            self._loop.call_soon_threadsafe(self._stopping, deadline)

    def _stopping(self, deadline: float) -> None:
        self.shutdown_deadline = deadline
        self._stop_event.set()

    async def until_shutdown_deadline(self) -> None:
        """Return at the shutdown deadline (never, while the service is not shutting down)."""
        await self._stop_event.wait()
        assert self.shutdown_deadline is not None
        await asyncio.sleep(max(0.0, self.shutdown_deadline - time.monotonic()))

    def check_not_shutting_down(self) -> None:
        """503 ``shutting_down`` (with Retry-After) once SIGTERM has arrived: for every request read from then on."""
        if self.shutdown_deadline is not None:
            raise ApiError(503, "shutting_down", "the service is shutting down; retry later",
                           headers={"Retry-After": str(self.settings.retry_after_s)})

    def check_accepting(self) -> None:
        """503 (with Retry-After) while warming up or shutting down: before reading a byte of the body."""
        self.check_not_shutting_down()
        if not self.ready:
            headers = {"Retry-After": str(self.settings.retry_after_s)}
            why = self.startup_error or "the model is loading and the workers are warming up"
            raise ApiError(503, "not_ready", f"the service is not ready: {why}", headers=headers)

    async def receive(self, request: Any) -> tuple[Upload, int]:
        """The request's whole body (see ``limits.receive_body``), timed as stage ``read_body``."""
        assert self.spool is not None, "receive() before start()"
        t0 = time.perf_counter()
        try:
            return await receive_body(request, self.upload_rules, self.budget, str(self.spool.path))
        finally:
            self.metrics.stage_latency.labels("read_body").observe(time.perf_counter() - t0)
            self.metrics.upload_bytes.set(self.budget.used)

    def admit(self, upload: Upload, reserved: int, started: float, client: str) -> "Ticket":
        """Take an admission slot for a received body, or refuse it and drop the body.

        503 when ``queue_size`` requests are in flight; 429 when this client (by address)
        already holds ``max_requests_per_client`` of them, so that one busy client cannot
        take every slot from the others.  From here the ticket owns the upload and its
        share of the byte budget, until :meth:`release` *and* the end of every worker job
        it started.
        """
        ticket = Ticket(upload, reserved, started, client)
        ticket.read_ms = (time.monotonic() - started) * 1e3
        retry = {"Retry-After": str(self.settings.retry_after_s)}
        try:
            self.check_accepting()
            if self.in_flight >= self.settings.queue_size:
                raise ApiError(
                    503,
                    "overloaded",
                    f"{self.in_flight} requests in flight, the limit is queue_size = {self.settings.queue_size}; "
                    "retry later",
                    headers=retry,
                )
            held = self.per_client.get(client, 0)
            if held >= self.settings.max_requests_per_client:
                raise ApiError(
                    429,
                    "too_many_requests",
                    f"this client already has {held} requests in flight, the limit is max_requests_per_client = "
                    f"{self.settings.max_requests_per_client}; retry when one has finished",
                    headers=retry,
                )
        except ApiError:
            self._drop_upload(ticket)
            raise
        self.in_flight += 1
        self.preparing += 1
        self.per_client[client] = self.per_client.get(client, 0) + 1
        ticket.admitted = True
        self.metrics.queue_depth.set(self.in_flight)
        return ticket

    def left_upstream(self, ticket: "Ticket") -> None:
        """The request will not reach the batcher any more (it has a scene, or failed)."""
        if ticket.upstream:
            ticket.upstream = False
            self.preparing -= 1

    def release(self, ticket: "Ticket") -> None:
        """The request is answered; its slot is freed once no worker runs a job of it any more."""
        self.left_upstream(ticket)
        ticket.ended = True
        self._free_if_idle(ticket)

    def _job_stopped(self, ticket: "Ticket") -> None:
        ticket.jobs -= 1
        self._free_if_idle(ticket)

    def _free_if_idle(self, ticket: "Ticket") -> None:
        if ticket.ended and ticket.jobs == 0 and ticket.admitted:
            ticket.admitted = False
            self.in_flight -= 1
            left = self.per_client.pop(ticket.client) - 1
            if left:
                self.per_client[ticket.client] = left
            self.metrics.queue_depth.set(self.in_flight)
            self._drop_upload(ticket)

    def _drop_upload(self, ticket: "Ticket") -> None:
        ticket.upload.discard()
        self.budget.give(ticket.reserved)
        ticket.reserved = 0
        self.metrics.upload_bytes.set(self.budget.used)

    async def _run_job(self, ticket: "Ticket", fn: Any, *args: Any, priority: int) -> Any:
        ticket.jobs += 1
        return await self.pool.run(fn, *args, priority=priority, on_stopped=lambda: self._job_stopped(ticket))

    async def correspond(self, ticket: "Ticket", content_type: str, config: ShadowCorrConfig, metrics: bool,
                         artefact: "jobs.Artefact | None" = None) -> bytes:
        """Run one scene through the pipeline; returns the Result JSON bytes, or the ``artefact``'s bytes."""
        stage = self.metrics.stage_latency
        t_start = time.perf_counter()
        read_ms = {"read_body": ticket.read_ms}
        try:
            if config.method not in NETWORK_METHODS:
                self.left_upstream(ticket)  # no network: never in the batcher
                out = await self._run_job(ticket, jobs.baseline, ticket.upload, content_type, config, self.limits,
                                          metrics, read_ms, ticket.started, artefact, priority=PRIORITY_START)
                stage.labels("baseline").observe(time.perf_counter() - t_start)
                return out
            try:
                prepared: jobs.Prepared = await self._run_job(
                    ticket, jobs.decode_and_prepare, ticket.upload, content_type, config, self.limits,
                    priority=PRIORITY_START,
                )
            finally:
                self.left_upstream(ticket)
            t_prepared = time.perf_counter()
            stage.labels("queue").observe(max(0.0, t_prepared - t_start - (prepared.decode_ms + prepared.prepare_ms) / 1e3))
            stage.labels("decode").observe(prepared.decode_ms / 1e3)
            stage.labels("prepare").observe(prepared.prepare_ms / 1e3)
            embeddings, batch = await self.batcher.submit(prepared.scene)
            stage.labels("batch_wait").observe(batch.wait_s)
            extra = {**read_ms, "decode": prepared.decode_ms, "batch_wait": batch.wait_s * 1e3,
                     "network": batch.run_s * 1e3}
            t_assign = time.perf_counter()
            out = await self._run_job(
                ticket, jobs.assign_scene, prepared.scene, embeddings, config, self.model_info, metrics, extra,
                ticket.started,
                jobs.ExportJob(artefact, ticket.upload, content_type, self.limits) if artefact else None,
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
    """One admitted request's place in the bookkeeping: its upload, budget share and running jobs."""

    __slots__ = ("upstream", "upload", "reserved", "started", "read_ms", "client", "jobs", "ended", "admitted")

    def __init__(self, upload: Upload, reserved: int, started: float, client: str) -> None:
        self.upstream = True  # may still reach the batcher
        self.upload = upload
        self.reserved = reserved  # bytes of the upload budget held
        self.started = started  # time.monotonic() when the body started to arrive
        self.read_ms = 0.0  # how long the body took to arrive
        self.client = client  # the client's address, for the per-client limit
        self.jobs = 0  # worker jobs started and not yet stopped
        self.ended = False  # the request has been answered (or abandoned)
        self.admitted = False  # holds an admission slot


def _request_options() -> tuple[str, ...]:
    return REQUEST_OPTIONS


#: An absolute file-system path in free text (``/tmp/x``, ``C:\\x``, ``C:/x``): not inside a word,
#: a relative path or a URL (``https://host/x``).
_ABSOLUTE_PATH = re.compile(r"(?<![\w.:/~-])(?:/|[A-Za-z]:[\\/])[^\s'\",;)]+")


def _without_paths(value: Any) -> Any:
    """``value`` (JSON data) with every absolute path in its strings replaced by ``<path>``.

    A model card's training recipe records the paths and commands of the machine that
    built it (``--out /tmp/synth/train``); the recipe stays, the machine's layout does not.
    """
    if isinstance(value, dict):
        return {k: _without_paths(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_without_paths(v) for v in value]
    if isinstance(value, str):
        return _ABSOLUTE_PATH.sub("<path>", value)
    return value
