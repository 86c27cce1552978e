"""Input limits: request body size (main process) and scene size (worker processes).

Bodies are received completely, before a request takes an admission slot, into
memory when small and a temporary file otherwise (``receive_body``), under a size
limit, a byte budget over all bodies in flight, a deadline and a minimum rate.  The
size limit is enforced twice: a declared ``Content-Length`` over the limit is refused
before a byte is read, and the bytes actually received are counted while streaming,
because a chunked body declares no length and a client may lie.

Bundle limits (views, pixels per view, files, decompressed bytes) are applied by the
library's loader through :class:`shadowcorr.io.BundleLimits`.  The cost limits are
checked here: before ``prepare``, cheaply, on the number of instance ids and of
instance pixels with valid depth in the masks (a scene over a limit is refused
without cutting it into blobs); after, exactly, on the segments ``prepare`` found.
"""

from __future__ import annotations

import asyncio
import os
import tempfile
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from starlette.requests import Request

from shadowcorr.bundle import SceneBundle
from shadowcorr.io import BundleLimits

from .errors import ApiError, JobError
from .settings import ServiceSettings

__all__ = ["RequestLimits", "ByteBudget", "Upload", "UploadRules", "receive_body", "check_instances"]

# Masks with ids below this are counted with bincount (fast); larger ids need np.unique.
_BINCOUNT_MAX_ID = 1 << 20


@dataclass(frozen=True)
class RequestLimits:
    """The limits a worker applies to one request (picklable, sent along with the job)."""

    bundle: BundleLimits
    max_segments: int
    max_scene_points: int
    max_mask_runs: int

    @classmethod
    def from_settings(cls, s: ServiceSettings) -> "RequestLimits":
        return cls(
            bundle=BundleLimits(
                max_views=s.max_views,
                max_pixels_per_view=s.max_pixels_per_view,
                max_total_bytes=s.max_uncompressed_bytes,
                max_files=s.max_files,
                max_segments=s.max_segments,
                max_scene_pixels=s.max_scene_pixels,
                max_scene_points=s.max_scene_points,
            ),
            max_segments=s.max_segments,
            max_scene_points=s.max_scene_points,
            max_mask_runs=s.max_mask_runs,
        )


class ByteBudget:
    """Bytes of request bodies held at once (being received, queued or processed).

    Spooling moves bodies out of memory but not off the machine: the budget bounds the
    temporary-file space too, and refuses (503) what would go beyond it.
    """

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.used = 0

    def take(self, n: int) -> bool:
        if self.used + n > self.limit:
            return False
        self.used += n
        return True

    def give(self, n: int) -> None:
        self.used -= n


@dataclass
class Upload:
    """A complete request body: in ``data`` when small, else in the temporary file ``path``.

    Sent to the worker as is (a path, not the bytes, for large bodies), so the main
    process never holds a large body in memory.
    """

    size: int
    data: bytes | None = None
    path: str | None = None

    def read(self) -> bytes:
        if self.data is not None:
            return self.data
        assert self.path is not None
        with open(self.path, "rb") as fh:
            return fh.read()

    def discard(self) -> None:
        """Delete the temporary file (if any); safe to call twice."""
        if self.path is not None:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass
            self.path = None
        self.data = None


@dataclass(frozen=True)
class UploadRules:
    """How a body must arrive (from the settings)."""

    max_bytes: int
    spool_bytes: int
    timeout_s: float
    grace_s: float
    min_bytes_per_s: int
    retry_after_s: int

    @classmethod
    def from_settings(cls, s: ServiceSettings) -> "UploadRules":
        return cls(s.max_body_bytes, s.spool_bytes, s.body_timeout_s, s.body_grace_s, s.min_upload_bytes_per_s,
                   s.retry_after_s)


class _Spool:
    """Chunks -> memory up to ``spool_bytes``, then a file in ``directory`` (written as they come, never joined)."""

    def __init__(self, spool_bytes: int, directory: str) -> None:
        self.spool_bytes = spool_bytes
        self.directory = directory
        self.buffer = bytearray()
        self.file: Any = None
        self.size = 0

    def write(self, chunk: bytes) -> None:
        self.size += len(chunk)
        if self.file is None and self.size > self.spool_bytes:
            self.file = tempfile.NamedTemporaryFile(prefix="shadowcorr-upload-", dir=self.directory, delete=False)
            self.file.write(self.buffer)
            self.buffer = bytearray()
        if self.file is not None:
            self.file.write(chunk)  # page cache: microseconds per chunk, fine on the event loop
        else:
            self.buffer += chunk

    def finish(self) -> Upload:
        if self.file is None:
            return Upload(self.size, data=bytes(self.buffer))
        self.file.close()
        return Upload(self.size, path=self.file.name)

    def abort(self) -> None:
        if self.file is not None:
            self.file.close()
            os.unlink(self.file.name)


async def receive_body(request: Request, rules: UploadRules, budget: ByteBudget,
                       spool_dir: str) -> tuple[Upload, int]:
    """Receive the whole body before the request takes an admission slot.

    A body over ``rules.spool_bytes`` is written to a file in ``spool_dir``.  Returns the
    upload and the bytes it holds of ``budget`` (the caller gives them back when the
    request is over).  Refuses with

    * 413 over ``max_bytes`` (the declared ``Content-Length`` before a byte is read, or
      the bytes streamed, since a chunked body declares nothing and a client may lie);
    * 503 when the bodies in flight would exceed the byte budget;
    * 408 when the body is not complete within ``timeout_s``, or when, after ``grace_s``,
      it arrives slower than ``min_bytes_per_s`` on average: a stalled upload is cut
      off as soon as its rate says it cannot be a real one;
    * 400 for an empty body or a client that disconnects mid-upload.
    """
    declared = request.headers.get("content-length")
    reserved = 0
    if declared is not None:
        try:
            reserved = int(declared)
        except ValueError:
            raise ApiError(400, "bad_request", f"invalid Content-Length header {declared!r}",
                           [{"loc": "headers.content-length", "msg": "not an integer"}]) from None
        if reserved > rules.max_bytes:
            raise _too_large(rules.max_bytes, f"Content-Length is {reserved} bytes")
    if not budget.take(reserved):
        raise _over_budget(budget, rules)
    spool = _Spool(rules.spool_bytes, spool_dir)
    start = time.monotonic()
    try:
        while True:
            # The next chunk must arrive while the average rate still meets the minimum.
            due = rules.grace_s + (spool.size / rules.min_bytes_per_s if rules.min_bytes_per_s else rules.timeout_s)
            wait = min(due, rules.timeout_s) - (time.monotonic() - start)
            try:
                message = await asyncio.wait_for(request.receive(), max(wait, 0.0))
            except asyncio.TimeoutError:
                raise _too_slow(spool.size, time.monotonic() - start, rules) from None
            if message["type"] == "http.disconnect":
                raise ApiError(400, "client_disconnected", "the client disconnected before the body was complete")
            chunk = message.get("body", b"")
            if spool.size + len(chunk) > rules.max_bytes:
                raise _too_large(rules.max_bytes, f"more than {rules.max_bytes} bytes received")
            if spool.size + len(chunk) > reserved:  # chunked (or lying) body: reserve as it grows
                if not budget.take(spool.size + len(chunk) - reserved):
                    raise _over_budget(budget, rules)
                reserved = spool.size + len(chunk)
            spool.write(chunk)
            if not message.get("more_body", False):
                break
    except BaseException:
        spool.abort()
        budget.give(reserved)
        raise
    upload = spool.finish()
    budget.give(reserved - upload.size)
    if upload.size == 0:
        raise ApiError(400, "empty_body", "the request body is empty; upload a bundle",
                       [{"loc": "body", "msg": "empty"}])
    return upload, upload.size


def _over_budget(budget: ByteBudget, rules: UploadRules) -> ApiError:
    return ApiError(
        503, "overloaded",
        f"uploads in flight already hold {budget.used} of max_upload_bytes_in_flight = {budget.limit} bytes; retry later",
        headers={"Retry-After": str(rules.retry_after_s), "Connection": "close"},
    )


def _too_slow(received: int, elapsed: float, rules: UploadRules) -> ApiError:
    if elapsed >= rules.timeout_s - 1e-3:
        why = f"the body did not arrive within body_timeout_s = {rules.timeout_s:g} s"
    else:
        why = (f"the body arrives too slowly: {received} bytes in {elapsed:.1f} s, below min_upload_bytes_per_s = "
               f"{rules.min_bytes_per_s} after the first {rules.grace_s:g} s")
    return ApiError(408, "body_timeout", why, [{"loc": "body", "msg": why}], headers={"Connection": "close"})


def _too_large(limit: int, what: str) -> ApiError:
    return ApiError(
        413,
        "payload_too_large",
        f"request body too large: {what}; the limit is max_body_bytes = {limit} bytes",
        [{"loc": "body", "msg": f"larger than {limit} bytes"}],
        headers={"Connection": "close"},  # the rest of the body is not read
    )


def _over_limit(code: str, what: str, limit: str, maximum: int, view: str) -> JobError:
    """413 for a scene whose masks, counted up to ``view``, already exceed ``limit``."""
    return JobError(
        413,
        code,
        f"the masks hold at least {what} (counted up to view {view!r}); the limit is {limit} = {maximum}",
        [{"loc": f"views[{view}].mask", "msg": f"more than {maximum} ({limit})"}],
    )


def check_instances(bundle: SceneBundle, limits: RequestLimits, min_blob_pixels: int) -> None:
    """Cheap checks on the decoded masks: the cost estimate that admits ``prepare`` or not.

    ``prepare`` costs grow with the segments it cuts and the points it back-projects;
    both are bounded here from counts that take milliseconds, before it spends seconds:

    * 413 ``too_many_segments`` when the masks hold more instances than ``max_segments``:
      counted per view as instance ids with at least ``max(min_blob_pixels, 1)`` pixels.
      Each gives at least one segment unless splitting leaves only small blobs, so this
      bound stops absurd masks (every pixel its own id) before the real work.
    * 413 ``too_many_points`` when more than ``max_scene_points`` instance pixels have a
      valid depth (each becomes a 3D point).
    * 413 ``too_many_runs`` when the masks hold more than ``max_mask_runs`` runs (stretches
      of one instance id along a row): the blob finder's memory grows with them, and a
      speckled mask of a few kilobytes of PNG holds millions.
    * 422 when no view has an instance pixel with valid depth: there is nothing to match.

    Point-segment bundles are limited by the loader (``BundleLimits.max_segments`` and
    ``max_scene_points``, the latter before their points are decompressed).
    """
    if bundle.point_segments is not None:
        return
    total = points = runs = 0
    any_foreground = False
    threshold = max(min_blob_pixels, 1)
    for view in bundle.views:
        mask = view.mask
        if mask is None or mask.size == 0:
            continue
        on = mask > 0
        fg = mask[on]  # foreground only: usually a small share of the pixels, so counting is cheap
        if fg.size == 0:
            continue
        # A run starts at a foreground pixel whose left neighbour differs, or at a row's start.
        runs += int(np.count_nonzero(on[:, 0])) + int(np.count_nonzero(on[:, 1:] & (mask[:, 1:] != mask[:, :-1])))
        if runs > limits.max_mask_runs:
            raise _over_limit("too_many_runs", f"{runs} runs of instance pixels", "max_mask_runs",
                              limits.max_mask_runs, view.name)
        any_foreground = True
        if int(fg.max()) < _BINCOUNT_MAX_ID:
            counts = np.bincount(fg)
        else:
            _, counts = np.unique(fg, return_counts=True)
        total += int(np.count_nonzero(counts >= threshold))
        if total > limits.max_segments:
            raise _over_limit("too_many_segments", f"{total} instances", "max_segments", limits.max_segments, view.name)
        if view.depth is not None and view.depth.shape == mask.shape:
            points += int(np.count_nonzero(view.depth[on] > 0))  # the loader zeroes invalid depth
        if points > limits.max_scene_points:
            raise _over_limit("too_many_points", f"{points} instance pixels with valid depth", "max_scene_points",
                              limits.max_scene_points, view.name)
    if total == 0 or points == 0:
        if not any_foreground:
            why = "every mask is empty (all background)"
        elif total == 0:
            why = f"every instance has fewer than min_blob_pixels = {min_blob_pixels} pixels"
        else:
            why = "no instance pixel has a valid depth"
        raise JobError(
            422,
            "no_segments",
            f"the scene has no segments: {why}",
            [{"loc": "views", "msg": why}],
        )
