"""A pool of worker processes for the CPU-bound stages (decode + prepare, assign).

Design: ``size`` *slots*, each owning a one-process ``ProcessPoolExecutor`` (``spawn``
context), all fed from one asyncio priority queue.

Why one executor per process rather than one executor with ``size`` processes: when a
process of a ``ProcessPoolExecutor`` dies, the executor is *broken* and every job in
it fails, including the jobs of the healthy processes.  With one process per
executor only the job that was running in the dead process fails (HTTP 500); the slot
then replaces its executor, and the other slots never notice.

Why ``spawn``: the main process holds threads (inference, executor managers) and a
torch runtime; forking that is unsafe.  Spawned workers import the library afresh
and warm up in their initializer, so a slot reports ready only when its worker can
serve at full speed.

Jobs have priorities (lower first): finishing requests (assign) go before starting new
ones (decode + prepare), so under load each request completes as early as possible
instead of all of them completing late together.

Cancellation: a job whose request gave up (timeout, client gone) is skipped if still
queued.  If it is running it may finish within ``kill_grace_s`` (a couple of seconds:
cheaper than starting and warming up a new worker); if it is still running then, its
worker is killed and replaced, since a process cannot be interrupted otherwise and the
slot must not stay blocked on work nobody waits for.  ``on_stopped`` tells the caller
when the job really let go of its worker (the service holds the request's admission
slot until then, so a cancelled request cannot make room for more work than the
workers can take).
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import multiprocessing
import os
import signal
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Any, Callable

from . import jobs
from .errors import JobError
from .metrics import ServiceMetrics

__all__ = ["WorkerPool", "WorkerCrashed", "PRIORITY_FINISH", "PRIORITY_START"]

log = logging.getLogger("shadowcorr.service")

PRIORITY_FINISH = 0  # assign: the request is nearly done
PRIORITY_START = 1  # decode + prepare: a new request

_LIVENESS_PERIOD_S = 0.5  # how often idle slots check that their process is alive
_RESPAWN_BACKOFF_S = (0.5, 1.0, 2.0, 5.0, 10.0, 30.0)
_EXIT_WAIT_S = 5.0  # how long a closing pool waits for a worker to exit before killing it


class WorkerCrashed(Exception):
    """The worker process running a job died (killed, out of memory, crashed in native code)."""


@dataclass
class _Job:
    fn: Callable[..., Any]
    args: tuple[Any, ...]
    future: asyncio.Future
    slot: "_Slot | None" = None
    on_stopped: Callable[[], None] | None = None  # called once, when the job can no longer use a worker

    def stopped(self) -> None:
        callback, self.on_stopped = self.on_stopped, None
        if callback is not None:
            callback()


@dataclass
class _Slot:
    index: int
    executor: ProcessPoolExecutor | None = None
    pid: int | None = None
    ready: bool = False
    restarts: int = 0
    job: _Job | None = None
    task: asyncio.Task | None = field(default=None, repr=False)

    def kill(self) -> None:
        """SIGKILL the worker (the executor then reports the job broken and the slot respawns)."""
        if self.pid is not None:
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass

    def alive(self) -> bool:
        if self.pid is None:
            return False
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:  # exists, owned by someone else (cannot happen for our child)
            return True
        return True


class WorkerPool:
    """``size`` single-process executors behind one priority queue."""

    def __init__(
        self,
        size: int,
        *,
        torch_threads: int = 1,
        memory_bytes: int = 0,
        metrics: ServiceMetrics | None = None,
        startup_timeout_s: float = 600.0,
        kill_grace_s: float = 60.0,
        warm_up: bool = True,
    ) -> None:
        self.size = size
        self.kill_grace_s = kill_grace_s
        self.torch_threads = torch_threads
        self.memory_bytes = memory_bytes
        self.metrics = metrics
        self.startup_timeout_s = startup_timeout_s
        self.warm_up = warm_up
        self._ctx = multiprocessing.get_context("spawn")
        self._slots = [_Slot(i) for i in range(size)]
        self._queue: asyncio.PriorityQueue[tuple[int, int, _Job]] = asyncio.PriorityQueue()
        self._seq = itertools.count()
        self._closing = False
        self._all_started = asyncio.Event()
        self._started_once: set[int] = set()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Start every slot (spawn + warm-up happen in the background)."""
        for slot in self._slots:
            slot.task = asyncio.create_task(self._run_slot(slot), name=f"worker-slot-{slot.index}")

    async def wait_started(self) -> None:
        """Return once every slot has had a warmed-up worker at least once."""
        await self._all_started.wait()

    async def close(self) -> None:
        """Stop the slots and their processes (queued jobs fail; call after draining).

        A job still running now belongs to a request that the graceful-shutdown timeout
        has already abandoned: its worker is killed rather than waited for.
        """
        self._closing = True
        for slot in self._slots:
            if slot.job is not None:
                slot.kill()
            if slot.task is not None:
                slot.task.cancel()
        await asyncio.gather(*(s.task for s in self._slots if s.task is not None), return_exceptions=True)
        await asyncio.gather(*(asyncio.to_thread(self._shutdown_executor, s) for s in self._slots))
        while not self._queue.empty():
            _, _, job = self._queue.get_nowait()
            if not job.future.done():
                job.future.set_exception(RuntimeError("the service is shutting down"))
            job.stopped()

    # ------------------------------------------------------------------ state
    @property
    def ready_count(self) -> int:
        return sum(1 for s in self._slots if s.ready)

    @property
    def restarts(self) -> int:
        return sum(s.restarts for s in self._slots)

    @property
    def pending(self) -> int:
        return self._queue.qsize()

    # ------------------------------------------------------------------ jobs
    async def run(
        self,
        fn: Callable[..., Any],
        *args: Any,
        priority: int = PRIORITY_START,
        on_stopped: Callable[[], None] | None = None,
    ) -> Any:
        """Run ``fn(*args)`` in a worker process and return its result.

        Raises whatever ``fn`` raised (a :class:`JobError` for input problems), or
        :class:`WorkerCrashed` when the worker died while running it.  ``on_stopped`` is
        called once the job holds no worker any more: when it ends, when it is dropped
        from the queue, or, if the caller is cancelled mid-job, only when the worker has
        really finished it or been killed.
        """
        if self._closing:
            raise RuntimeError("the service is shutting down")
        loop = asyncio.get_running_loop()
        job = _Job(fn, args, loop.create_future(), on_stopped=on_stopped)
        self._queue.put_nowait((priority, next(self._seq), job))
        self._gauge()
        try:
            return await job.future
        except asyncio.CancelledError:
            # The request gave up.  A queued job is skipped by the slot (its future is
            # done); a running one gets kill_grace_s to finish before its worker is killed.
            if job.slot is not None:
                loop.call_later(self.kill_grace_s, self._kill_if_still_running, job)
            raise
        finally:
            if job.slot is None:
                job.stopped()

    def _kill_if_still_running(self, job: _Job) -> None:
        slot = job.slot
        if slot is not None and slot.job is job:
            log.warning(
                "killing worker %s (pid %s): still running a cancelled job %.0f s later",
                slot.index, slot.pid, self.kill_grace_s,
            )
            slot.kill()

    def _gauge(self) -> None:
        if self.metrics is not None:
            self.metrics.pool_pending.set(self._queue.qsize())
            self.metrics.workers_ready.set(self.ready_count)

    async def _run_slot(self, slot: _Slot) -> None:
        try:
            while not self._closing:
                if slot.executor is None:
                    await self._spawn(slot)
                    continue
                item = await self._next_job(slot)
                if item is None:  # the worker died while idle
                    await self._retire(slot, "died while idle")
                    continue
                await self._execute(slot, *item)
        except asyncio.CancelledError:
            pass

    async def _next_job(self, slot: _Slot) -> tuple[int, int, _Job] | None:
        """The next live job, or None as soon as the slot's process is found dead.

        One ``queue.get()`` task is awaited across liveness checks and only cancelled when
        the worker is dead; ``asyncio.wait_for(queue.get(), ...)`` is avoided on purpose:
        before Python 3.12 it can drop an item that arrives just as the timeout fires.
        """
        getter: asyncio.Future = asyncio.ensure_future(self._queue.get())
        try:
            while True:
                done, _ = await asyncio.wait({getter}, timeout=_LIVENESS_PERIOD_S)
                if getter in done:
                    priority, seq, job = getter.result()
                    self._gauge()
                    if job.future.done():  # cancelled while queued
                        getter = asyncio.ensure_future(self._queue.get())
                        continue
                    return priority, seq, job
                if not slot.alive():
                    return None
        finally:
            # Cancelling a pending Queue.get() leaves its item in the queue.
            if not getter.done():
                getter.cancel()

    async def _execute(self, slot: _Slot, priority: int, seq: int, job: _Job) -> None:
        assert slot.executor is not None
        try:
            cf = slot.executor.submit(job.fn, *job.args)
        except (BrokenProcessPool, RuntimeError):
            # Died while idle, between liveness checks: the job never started, so it is
            # innocent; put it back in its place and replace the worker.
            self._queue.put_nowait((priority, seq, job))
            await self._retire(slot, "died while idle")
            return
        slot.job, job.slot = job, slot
        try:
            result = await asyncio.wrap_future(cf)
        except BrokenProcessPool:
            _settle(job, exc=WorkerCrashed(f"worker process {slot.pid} died while running this request"))
            await self._retire(slot, "died while running a job")
        except JobError as e:
            _settle(job, exc=e)
        except Exception as e:  # pickling errors and the like: a bug, not the client's fault
            log.exception("job %s failed in the pool", getattr(job.fn, "__name__", job.fn))
            _settle(job, exc=e)
        else:
            _settle(job, result=result)
        finally:
            slot.job, job.slot = None, None
            job.stopped()
            if self._closing:  # the slot was stopped mid-job: nobody may wait forever
                _settle(job, exc=RuntimeError("the service is shutting down"))

    async def _spawn(self, slot: _Slot) -> None:
        """Create the slot's executor and wait for its warmed-up worker (with backoff on failure)."""
        attempt = 0
        while not self._closing:
            executor = ProcessPoolExecutor(
                max_workers=1,
                mp_context=self._ctx,
                initializer=jobs.init_worker,
                initargs=(self.torch_threads, os.getpid(), self.warm_up, self.memory_bytes),
            )
            try:
                pid = await asyncio.wait_for(asyncio.wrap_future(executor.submit(jobs.hello)), self.startup_timeout_s)
            except asyncio.CancelledError:  # shutdown during start-up: do not leave the process behind
                await asyncio.to_thread(_kill_executor, executor)
                raise
            except (BrokenProcessPool, asyncio.TimeoutError, OSError) as e:
                delay = _RESPAWN_BACKOFF_S[min(attempt, len(_RESPAWN_BACKOFF_S) - 1)]
                log.error("worker %s failed to start (%s); retrying in %.1f s", slot.index, type(e).__name__, delay)
                await asyncio.to_thread(_kill_executor, executor)
                attempt += 1
                await asyncio.sleep(delay)
                continue
            slot.executor, slot.pid, slot.ready = executor, pid, True
            log.info("worker %s ready (pid %s)", slot.index, pid)
            self._started_once.add(slot.index)
            if len(self._started_once) == self.size:
                self._all_started.set()
            self._gauge()
            return

    async def _retire(self, slot: _Slot, why: str) -> None:
        """Drop a dead (or killed) worker; the slot loop spawns a new one."""
        log.warning("worker %s (pid %s) %s; replacing it", slot.index, slot.pid, why)
        slot.ready = False
        executor, slot.executor, slot.pid = slot.executor, None, None
        slot.restarts += 1
        if self.metrics is not None:
            self.metrics.worker_restarts.inc()
        self._gauge()
        if executor is not None:
            await asyncio.to_thread(_kill_executor, executor)

    def _shutdown_executor(self, slot: _Slot) -> None:
        """Let the slot's idle worker exit; one that is still busy (a job the shutdown has abandoned
        while its slot was between jobs) is killed after ``_EXIT_WAIT_S``: a plain
        ``shutdown(wait=True)`` would wait for that job however long it runs, and the server with it."""
        executor, slot.executor = slot.executor, None
        slot.ready = False
        if executor is None:
            return
        processes = list((getattr(executor, "_processes", None) or {}).values())  # no public API for this
        executor.shutdown(wait=False, cancel_futures=True)
        for p in processes:
            p.join(_EXIT_WAIT_S)
        if any(p.is_alive() for p in processes):
            log.warning("worker %s still busy %.0f s into the shutdown; killing it", slot.index, _EXIT_WAIT_S)
            for p in processes:
                p.kill()
                p.join(_EXIT_WAIT_S)


def _settle(job: _Job, *, result: Any = None, exc: BaseException | None = None) -> None:
    if job.future.done():  # the request already gave up
        return
    if exc is not None:
        job.future.set_exception(exc)
    else:
        job.future.set_result(result)


def _kill_executor(executor: ProcessPoolExecutor) -> None:
    """Tear down a broken or hung executor without waiting on its (possibly stuck) worker."""
    processes = list(getattr(executor, "_processes", {}).values())  # no public API for this
    for p in processes:
        try:
            p.kill()
        except Exception:
            pass
    executor.shutdown(wait=True, cancel_futures=True)
