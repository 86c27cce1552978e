"""Site maps over HTTP: create a map, add scans to it, read it and its history, delete it.

Routes (``add_map_routes``)::

    POST   /maps                       -> 201 {"map": id}
    POST   /maps/{id}/scans            one scan, uploaded as for /correspond -> the update JSON
    GET    /maps/{id}                  the whole map: scans, objects, segments, events
    GET    /maps/{id}/events?since=N   the history after event N -> {"map", "events"}
    DELETE /maps/{id}                  -> 204

Each map is one file, ``<maps_dir>/<id>.map`` (``shadowcorr.SiteMap``); ids are 32 hex digits
chosen by the server, and anything else in the path is an unknown map (404).  Without a
``maps_dir`` setting the server keeps no maps (404 ``maps_disabled``).

A scan runs as ``/correspond`` does, under the same upload limits and with the same errors:
the body is received and admitted first, a worker decodes it and prepares the scan against the
map (``SiteMap.prepare_scan``), the batcher runs the network, and a worker groups the segments
and commits the update in one transaction (``SiteMap.commit_scan``).  One writer per map: the
server holds a map from its scan's first byte to its commit, and a second scan of the same map
(or a delete) meanwhile gets 409 ``map_busy`` with Retry-After; the map file's own write lock
refuses a writer of another process as well.
"""

from __future__ import annotations

import asyncio
import re
import secrets
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
from fastapi import FastAPI, Query, Request
from fastapi.responses import JSONResponse, Response

from shadowcorr.config import ShadowCorrConfig
from shadowcorr.sitemap import MapBusyError, MapConflictError, MapFileError, MapState, MapUpdate, ScanPlan, SiteMap

from . import jobs
from .errors import ApiError, ErrorBody, JobError
from .limits import RequestLimits, Upload, check_instances
from .multipart import BodyError, content_kind
from .workers import PRIORITY_FINISH, PRIORITY_START, WorkerCrashed

if TYPE_CHECKING:
    from .runtime import Runtime

__all__ = ["MAP_ID", "add_map_routes", "commit_scan", "prepare_scan"]

#: What a map id looks like: the server's own ``secrets.token_hex(16)``.
MAP_ID = re.compile(r"[0-9a-f]{32}")
_SUFFIXES = ("", "-wal", "-shm")

_ERRORS: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorBody, "description": "no such map, or the server keeps no maps (map_not_found, maps_disabled)"},
    409: {"model": ErrorBody, "description": "another scan of this map is being added (map_busy), or the map changed "
          "while this scan was prepared (map_changed); see Retry-After",
          "headers": {"Retry-After": {"description": "seconds to wait before retrying", "schema": {"type": "integer"}}}},
}


# --------------------------------------------------------------------------- worker jobs
def _map_config(config: ShadowCorrConfig, limits: RequestLimits) -> ShadowCorrConfig:
    """The run-time settings a worker applies to a map's own configuration (time and size limits)."""
    return ShadowCorrConfig(max_stage_seconds=config.max_stage_seconds,
                            max_segments=min(config.max_segments, limits.max_segments))


def _map_errors(fn, *args):
    """Errors of the map itself as clean job errors (the rest as ``jobs`` reports them)."""
    try:
        return fn(*args)
    except MapBusyError as e:
        raise JobError(409, "map_busy", str(e)) from None
    except MapConflictError as e:
        raise JobError(409, "map_changed", str(e)) from None
    except MapFileError as e:
        raise JobError(500, "map_unreadable", f"the map file cannot be read: {e}") from None
    except FileNotFoundError:
        raise JobError(404, "map_not_found", "the map was deleted while the scan was being added") from None


def _prepare(upload: Upload, content_type: str, path: str, config: ShadowCorrConfig, limits: RequestLimits,
             name: str | None) -> ScanPlan:
    bundle = jobs._load(upload, content_type, limits)
    with SiteMap(path, _map_config(config, limits), create=False) as site:
        check_instances(bundle, limits, site.config.min_blob_pixels)
        return site.prepare_scan(bundle, name)


def _commit(path: str, plan: ScanPlan, embeddings: np.ndarray, config: ShadowCorrConfig, limits: RequestLimits,
            model_sha256: str | None, extra_timings: dict[str, float], started: float) -> bytes:
    with SiteMap(path, _map_config(config, limits), create=False) as site:
        update = site.commit_scan(plan, embeddings, model_sha256=model_sha256)
    update.timings_ms.update({k: round(v, 3) for k, v in extra_timings.items()})
    update.timings_ms["total"] = round((time.monotonic() - started) * 1e3, 3)
    return update.model_dump_json().encode()


def prepare_scan(upload: Upload, content_type: str, path: str, config: ShadowCorrConfig, limits: RequestLimits,
                 name: str | None) -> ScanPlan:
    """Worker job: decode the upload and prepare the scan against the map."""
    return jobs._guarded("preparing the scan", _map_errors, _prepare, upload, content_type, path, config, limits, name)


def commit_scan(path: str, plan: ScanPlan, embeddings: np.ndarray, config: ShadowCorrConfig, limits: RequestLimits,
                model_sha256: str | None, extra_timings: dict[str, float], started: float) -> bytes:
    """Worker job: group the scan's segments, revise the map and commit; returns the update JSON bytes."""
    return jobs._guarded("committing the scan", _map_errors, _commit, path, plan, embeddings, config, limits,
                         model_sha256, extra_timings, started)


# --------------------------------------------------------------------------- routes
class _Maps:
    """The maps directory and which maps have a scan in progress."""

    def __init__(self, directory: Path | None, retry_after_s: int) -> None:
        self.directory = directory
        self.retry_after_s = retry_after_s
        self.writing: set[str] = set()

    def path(self, map_id: str, *, exists: bool = True) -> Path:
        if self.directory is None:
            raise ApiError(404, "maps_disabled", "this server keeps no maps: start it with maps_dir "
                           "(SHADOWCORR_MAPS_DIR) to use /maps")
        path = self.directory / f"{map_id}.map"
        if not MAP_ID.fullmatch(map_id) or (exists and not path.is_file()):
            raise ApiError(404, "map_not_found", f"no map {map_id[:64]!r} on this server")
        return path

    def busy(self, map_id: str) -> ApiError:
        return ApiError(409, "map_busy", f"a scan of map {map_id} is being added; retry when it has finished",
                        headers={"Retry-After": str(max(self.retry_after_s, 1))})


def add_map_routes(app: FastAPI, runtime: "Runtime", upload_errors: dict[int | str, dict[str, Any]],
                   upload_body: dict[str, Any]) -> None:
    """The /maps routes on ``app`` (see the module docstring); a scan's upload is documented as
    ``/correspond``'s (``upload_errors``, ``upload_body``)."""
    settings = runtime.settings
    maps = _Maps(settings.maps_dir, settings.retry_after_s)
    if maps.directory is not None:
        maps.directory.mkdir(parents=True, exist_ok=True)

    async def in_thread(fn, *args):
        return await asyncio.get_running_loop().run_in_executor(None, fn, *args)

    def open_map(path: Path) -> SiteMap:
        try:
            return SiteMap(path, create=False)
        except FileNotFoundError:
            raise ApiError(404, "map_not_found", f"no map {path.stem!r} on this server") from None

    @app.post("/maps", status_code=201, responses=_ERRORS, summary="Create an empty site map")
    async def create_map() -> JSONResponse:
        runtime.check_not_shutting_down()
        map_id = secrets.token_hex(16)
        path = maps.path(map_id, exists=False)
        await in_thread(lambda: SiteMap(path, runtime.base_config).close())
        return JSONResponse({"map": map_id}, status_code=201)

    @app.post("/maps/{map_id}/scans", response_model=MapUpdate, responses={**{k: v for k, v in upload_errors.items() if int(k) >= 400}, **_ERRORS},
              openapi_extra={"requestBody": upload_body},
              summary="Add one scan to a map: its segments get the map's object ids, revisions become events")
    async def add_scan(request: Request, map_id: str,
                       name: Annotated[str | None, Query(max_length=256, description="the scan's name (default: the "
                                                         "bundle's)")] = None) -> Response:
        path = maps.path(map_id)
        content_type = request.headers.get("content-type", "")
        try:
            content_kind(content_type)
        except BodyError as e:
            code = "unsupported_media_type" if e.status == 415 else "bad_multipart"
            raise ApiError(e.status, code, str(e), [{"loc": e.loc, "msg": str(e)}]) from None
        runtime.check_accepting()
        if map_id in maps.writing:
            raise maps.busy(map_id)
        maps.writing.add(map_id)
        try:
            return Response(await _add_scan(runtime, request, str(path), content_type, name), media_type="application/json")
        finally:
            maps.writing.discard(map_id)

    @app.get("/maps/{map_id}", response_model=MapState, responses=_ERRORS,
             summary="The whole map: scans, objects, every segment with its object, the events")
    async def get_map(map_id: str) -> Response:
        path = maps.path(map_id)

        def read() -> bytes:
            with open_map(path) as site:
                return site.state().model_dump_json().encode()

        return Response(await in_thread(read), media_type="application/json")

    @app.get("/maps/{map_id}/events", responses=_ERRORS, summary="The map's history after event `since`")
    async def get_events(map_id: str, since: Annotated[int, Query(ge=0, description="the last event already "
                                                                  "known (0: all)")] = 0) -> JSONResponse:
        path = maps.path(map_id)

        def read() -> list[dict[str, Any]]:
            with open_map(path) as site:
                return [e.model_dump(mode="json") for e in site.events(since)]

        return JSONResponse({"map": map_id, "events": await in_thread(read)})

    @app.delete("/maps/{map_id}", status_code=204, responses=_ERRORS, summary="Delete a map")
    async def delete_map(map_id: str) -> Response:
        path = maps.path(map_id)
        if map_id in maps.writing:
            raise maps.busy(map_id)
        for suffix in _SUFFIXES:
            Path(f"{path}{suffix}").unlink(missing_ok=True)
        return Response(status_code=204)


async def _add_scan(runtime: "Runtime", request: Request, path: str, content_type: str, name: str | None) -> bytes:
    """One scan through receive, admission, prepare (worker), network (batcher) and commit (worker)."""
    settings = runtime.settings
    started = time.monotonic()
    upload, reserved = await runtime.receive(request)
    client = request.client.host if request.client else "unknown"
    ticket = runtime.admit(upload, reserved, started, client)
    try:
        async def run() -> bytes:
            try:
                plan = await runtime._run_job(ticket, prepare_scan, ticket.upload, content_type, path,
                                              runtime.base_config, runtime.limits, name, priority=PRIORITY_START)
            finally:
                runtime.left_upstream(ticket)
            embeddings, batch = await runtime.batcher.submit(plan.scene)
            extra = {"read_body": ticket.read_ms, "batch_wait": batch.wait_s * 1e3, "network": batch.run_s * 1e3}
            sha = runtime.model_info.sha256 if runtime.model_info else None
            return await runtime._run_job(ticket, commit_scan, path, plan, embeddings, runtime.base_config,
                                          runtime.limits, sha, extra, started, priority=PRIORITY_FINISH)

        return await asyncio.wait_for(run(), settings.request_timeout_s)
    except asyncio.TimeoutError:
        raise ApiError(504, "timeout", f"the scan did not finish within request_timeout_s = "
                       f"{settings.request_timeout_s:g} s; the map is as it was") from None
    except JobError as e:
        if e.status == 409:
            raise ApiError(409, e.code, e.message, e.problems,
                           headers={"Retry-After": str(max(settings.retry_after_s, 1))}) from None
        raise e.to_api() from None
    except WorkerCrashed as e:
        raise ApiError(500, "worker_crashed", f"{e}; it has been replaced, and the map is as it was: retrying the "
                       "scan is safe") from None
    finally:
        runtime.release(ticket)
