"""Input limits: request body size (main process) and scene size (worker processes).

The body limit is enforced twice: a declared ``Content-Length`` over the limit is
refused before a byte is read, and the bytes actually received are counted while
streaming, because a chunked body declares no length and a client may lie.

Bundle limits (views, pixels per view, files, decompressed bytes) are applied by the
library's loader through :class:`shadowcorr.io.BundleLimits`.  The segment limit is
checked here, before and after ``prepare``: before, cheaply, on the number of
instance ids in the masks (a mask with more instances than the limit is refused
without cutting it into blobs); after, exactly, on the segments ``prepare`` found.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from starlette.requests import ClientDisconnect, Request

from shadowcorr.bundle import SceneBundle
from shadowcorr.io import BundleLimits

from .errors import ApiError, JobError
from .settings import ServiceSettings

__all__ = ["RequestLimits", "read_body", "check_instances", "check_segment_count"]

# Masks with ids below this are counted with bincount (fast); larger ids need np.unique.
_BINCOUNT_MAX_ID = 1 << 20


@dataclass(frozen=True)
class RequestLimits:
    """The limits a worker applies to one request (picklable, sent along with the job)."""

    bundle: BundleLimits
    max_segments: int

    @classmethod
    def from_settings(cls, s: ServiceSettings) -> "RequestLimits":
        return cls(
            bundle=BundleLimits(
                max_views=s.max_views,
                max_pixels_per_view=s.max_pixels_per_view,
                max_total_bytes=s.max_uncompressed_bytes,
                max_files=s.max_files,
                max_segments=s.max_segments,
            ),
            max_segments=s.max_segments,
        )


async def read_body(request: Request, max_bytes: int) -> bytes:
    """Read the whole request body, refusing (413) more than ``max_bytes``.

    Only I/O happens here: chunks are appended to a list and joined once at the end.
    """
    declared = request.headers.get("content-length")
    if declared is not None:
        try:
            n = int(declared)
        except ValueError:
            raise ApiError(400, "bad_request", f"invalid Content-Length header {declared!r}",
                           [{"loc": "headers.content-length", "msg": "not an integer"}]) from None
        if n > max_bytes:
            raise _too_large(max_bytes, f"Content-Length is {n} bytes")
    chunks: list[bytes] = []
    total = 0
    try:
        async for chunk in request.stream():
            total += len(chunk)
            if total > max_bytes:
                raise _too_large(max_bytes, f"more than {max_bytes} bytes received")
            chunks.append(chunk)
    except ClientDisconnect:
        raise ApiError(400, "client_disconnected", "the client disconnected before the body was complete") from None
    if total == 0:
        raise ApiError(400, "empty_body", "the request body is empty; upload a bundle",
                       [{"loc": "body", "msg": "empty"}])
    return b"".join(chunks)


def _too_large(limit: int, what: str) -> ApiError:
    return ApiError(
        413,
        "payload_too_large",
        f"request body too large: {what}; the limit is {limit} bytes",
        [{"loc": "body", "msg": f"larger than {limit} bytes"}],
    )


def check_instances(bundle: SceneBundle, max_segments: int, min_blob_pixels: int) -> None:
    """Cheap checks on the decoded masks, before ``prepare`` spends seconds on them.

    * 413 when the masks hold more instances than ``max_segments``: counted per view as
      instance ids with at least ``max(min_blob_pixels, 1)`` pixels.  Each gives at least
      one segment unless splitting leaves only small blobs, so this bound stops absurd
      masks (every pixel its own id) before the real work.
    * 422 when no view has an instance pixel with valid depth: there is nothing to match.

    Point-segment bundles are limited by the loader (``BundleLimits.max_segments``).
    """
    if bundle.point_segments is not None:
        return
    total = 0
    any_foreground = False
    usable = False  # some instance pixel with valid depth (the loader zeroes invalid depth)
    threshold = max(min_blob_pixels, 1)
    for view in bundle.views:
        mask = view.mask
        if mask is None or mask.size == 0:
            continue
        on = mask > 0
        fg = mask[on]  # foreground only: usually a small share of the pixels, so counting is cheap
        if fg.size == 0:
            continue
        any_foreground = True
        if int(fg.max()) < _BINCOUNT_MAX_ID:
            counts = np.bincount(fg)
        else:
            _, counts = np.unique(fg, return_counts=True)
        total += int(np.count_nonzero(counts >= threshold))
        if total > max_segments:
            raise JobError(
                413,
                "too_many_segments",
                f"the masks hold at least {total} instances (counted up to view {view.name!r}); "
                f"the limit is {max_segments} segments per scene",
                [{"loc": f"views[{view.name}].mask", "msg": f"more than {max_segments} instances in the scene"}],
            )
        if not usable and view.depth is not None and view.depth.shape == mask.shape:
            usable = bool((view.depth[on] > 0).any())
    if total == 0 or not usable:
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


def check_segment_count(num_segments: int, max_segments: int) -> None:
    """The exact check after ``prepare``: too many segments (413) or none at all (422)."""
    if num_segments > max_segments:
        raise JobError(
            413,
            "too_many_segments",
            f"the scene has {num_segments} segments; the limit is {max_segments}",
            [{"loc": "views", "msg": f"{num_segments} segments > {max_segments}"}],
        )
    if num_segments == 0:
        raise JobError(
            422,
            "no_segments",
            "the scene has no segments: every mask is empty, or every blob is smaller than min_blob_pixels "
            "or has no valid depth",
            [{"loc": "views", "msg": "no segment with valid depth in any view"}],
        )
