"""Send many scenes with bounded concurrency (the engine behind ``upload-dataset``).

``concurrency`` workers pull scenes from one shared iterator, so at most that many
scenes are held in memory (read, converted, in flight) at any time, and a slow scene
never blocks the others.  Reading and converting a scene runs in a thread, keeping
the event loop free to stream the other uploads.  Every outcome -- success or
failure -- is handed to ``on_record`` as soon as it is known, which is what lets the
CLI write the results file line by line and resume after an interruption.
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any, Callable, Iterable, Iterator

from .client import AsyncShadowCorrClient
from .dataset import SceneSource
from .errors import ShadowCorrError
from .records import UploadRecord

__all__ = ["upload_scene", "upload_scenes"]


async def upload_scene(client: AsyncShadowCorrClient, scene: SceneSource, options: dict[str, Any]) -> UploadRecord:
    """Send one scene; never raises for a per-scene problem (it becomes a ``failed`` record).

    ``latency_ms`` is the time of the HTTP exchange, retries included, without the
    local reading/conversion, so it measures the service.
    """
    source = str(scene.path)
    try:
        upload = await asyncio.to_thread(scene.load)
    except Exception as exc:  # noqa: BLE001 - one unreadable or inconvertible scene must not end a long upload
        error = exc.to_dict() if isinstance(exc, ShadowCorrError) else {"type": type(exc).__name__, "message": str(exc)}
        problems = getattr(exc, "problems", None)
        if problems and "problems" not in error:  # the library's BundleError lists what is wrong
            error["problems"] = [p.model_dump() if hasattr(p, "model_dump") else p for p in problems]
        return UploadRecord(scene.name, "failed", error=error, source=source)
    start = time.perf_counter()
    try:
        result = await client.correspond(upload, **options)
    except ShadowCorrError as exc:
        return UploadRecord(scene.name, "failed", latency_ms=(time.perf_counter() - start) * 1e3,
                            error=exc.to_dict(), source=source)
    latency_ms = (time.perf_counter() - start) * 1e3
    # Through JSON text, not model_dump(): the results file must be strict JSON (NaN -> null).
    return UploadRecord(scene.name, "ok", latency_ms=latency_ms, result=json.loads(result.model_dump_json()),
                        source=source)


async def upload_scenes(
    client: AsyncShadowCorrClient,
    scenes: Iterable[SceneSource],
    *,
    concurrency: int = 4,
    options: dict[str, Any] | None = None,
    on_record: Callable[[UploadRecord], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> list[UploadRecord]:
    """Send every scene, at most ``concurrency`` at once; returns the records in completion order.

    ``should_stop`` is asked before each new scene; once it says yes, no further scene
    is started (those in flight finish), e.g. when the server has gone away.
    """
    if concurrency < 1:
        raise ValueError(f"concurrency must be >= 1, got {concurrency}")
    opts = dict(options or {})
    pending: Iterator[SceneSource] = iter(scenes)
    records: list[UploadRecord] = []

    async def worker() -> None:
        # A shared iterator instead of one task per scene: memory stays bounded by the
        # number of workers, not by the size of the dataset.
        for scene in pending:
            if should_stop is not None and should_stop():
                return
            record = await upload_scene(client, scene, opts)
            records.append(record)
            if on_record is not None:
                on_record(record)

    await asyncio.gather(*(worker() for _ in range(concurrency)))
    return records
