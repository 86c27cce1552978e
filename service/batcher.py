"""Dynamic batching of network inference across concurrent requests.

Prepared scenes from concurrent requests are queued; one loop takes up to
``max_batch_size`` of them, waiting at most ``max_wait_s`` after the oldest arrived
for company, and runs a single ``embed(model, scenes)`` forward pass over the ragged
batch in one dedicated thread.  It does not wait when nothing else is on its way
(``upstream()`` says how many scenes are still being prepared): a lone request on an
idle service pays no batching delay.  One forward pass over *k* scenes costs less than *k*
passes (fixed per-call overhead, larger matrix products), and the single thread keeps
the network from competing with itself for cores.

The event loop only moves references around; all tensor work is in the thread.  If
a batch fails, each of its scenes is retried alone, so one bad scene cannot fail the
requests it happened to be batched with.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Generic, Sequence, TypeVar

from .metrics import ServiceMetrics

__all__ = ["DynamicBatcher", "BatchInfo"]

log = logging.getLogger("shadowcorr.service")

T = TypeVar("T")
R = TypeVar("R")


@dataclass(frozen=True)
class BatchInfo:
    """How an item was run: batch size, its wait for the batch, the forward pass time."""

    size: int
    wait_s: float
    run_s: float


@dataclass
class _Item(Generic[T]):
    value: T
    future: asyncio.Future
    enqueued: float


class DynamicBatcher(Generic[T, R]):
    """Collects items into batches for ``run_batch`` (a blocking function run in one thread)."""

    def __init__(
        self,
        run_batch: Callable[[Sequence[T]], Sequence[R]],
        *,
        max_batch_size: int = 8,
        max_wait_s: float = 0.01,
        metrics: ServiceMetrics | None = None,
        thread: ThreadPoolExecutor | None = None,
        upstream: Callable[[], int] | None = None,
    ) -> None:
        if max_batch_size < 1:
            raise ValueError("max_batch_size must be >= 1")
        self.run_batch = run_batch
        self.max_batch_size = max_batch_size
        self.max_wait_s = max(0.0, max_wait_s)
        self.metrics = metrics
        self.upstream = upstream
        self._thread = thread or ThreadPoolExecutor(max_workers=1, thread_name_prefix="shadowcorr-inference")
        self._owns_thread = thread is None
        self._items: deque[_Item[T]] = deque()
        self._wakeup = asyncio.Event()
        self._task: asyncio.Task | None = None
        self.batches = 0
        self.items_done = 0

    @property
    def pending(self) -> int:
        return len(self._items)

    def start(self) -> None:
        self._task = asyncio.create_task(self._loop(), name="dynamic-batcher")

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        while self._items:
            item = self._items.popleft()
            if not item.future.done():
                item.future.set_exception(RuntimeError("the service is shutting down"))
        if self._owns_thread:
            self._thread.shutdown(wait=True)

    async def submit(self, value: T) -> tuple[R, BatchInfo]:
        """Queue ``value``; returns its result and how it was batched."""
        if self._task is None or self._task.done():
            raise RuntimeError("the batcher is not running")
        loop = asyncio.get_running_loop()
        item = _Item(value, loop.create_future(), loop.time())
        self._items.append(item)
        self._gauge()
        self._wakeup.set()
        return await item.future

    def _gauge(self) -> None:
        if self.metrics is not None:
            self.metrics.batcher_pending.set(len(self._items))

    async def _loop(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            while not self._items:
                self._wakeup.clear()
                await self._wakeup.wait()
            # Wait for company until the oldest item has waited max_wait_s (or the batch is full).
            deadline = self._items[0].enqueued + self.max_wait_s
            while len(self._items) < self.max_batch_size:
                if self.upstream is not None and self.upstream() <= 0:
                    break  # nobody else is coming: waiting would only add latency
                remaining = deadline - loop.time()
                if remaining <= 0:
                    break
                self._wakeup.clear()
                try:
                    # Items live in the deque, not in this awaitable: a wake-up lost to the
                    # timeout loses nothing.
                    await asyncio.wait_for(self._wakeup.wait(), remaining)
                except asyncio.TimeoutError:
                    break
            batch: list[_Item[T]] = []
            while self._items and len(batch) < self.max_batch_size:
                item = self._items.popleft()
                if not item.future.done():  # its request gave up while waiting
                    batch.append(item)
            self._gauge()
            if batch:
                await self._run(batch)

    async def _run(self, batch: list[_Item[T]]) -> None:
        loop = asyncio.get_running_loop()
        start = loop.time()
        values = [it.value for it in batch]
        t0 = time.perf_counter()
        try:
            results = await loop.run_in_executor(self._thread, self.run_batch, values)
            if len(results) != len(batch):
                raise RuntimeError(f"run_batch returned {len(results)} results for {len(batch)} items")
        except Exception as exc:
            if len(batch) == 1:
                _settle(batch[0].future, exc=exc)
                return
            log.warning("batch of %d failed (%s); running its items one by one", len(batch), exc)
            for it in batch:
                await self._run([it])
            return
        run_s = time.perf_counter() - t0
        self.batches += 1
        self.items_done += len(batch)
        if self.metrics is not None:
            self.metrics.batch_size.observe(len(batch))
            self.metrics.stage_latency.labels("network").observe(run_s)
        for it, res in zip(batch, results):
            _settle(it.future, result=(res, BatchInfo(len(batch), start - it.enqueued, run_s)))


def _settle(fut: asyncio.Future, *, result: Any = None, exc: BaseException | None = None) -> None:
    if fut.done():
        return
    if exc is not None:
        fut.set_exception(exc)
    else:
        fut.set_result(result)
