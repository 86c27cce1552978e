"""The FastAPI application: routes, lifespan, error handlers.

Routes:

* ``POST /correspond`` -- one scene in (multipart form or bare archive), Result JSON out, or with
  ``?format=bag|ply|rrd`` the same result as a zipped ROS 2 bag, zipped PLY files or a Rerun
  recording (``shadowcorr.export``).
* ``GET /health``      -- liveness + readiness (503 until the model and workers are warm).
* ``GET /info``        -- model card, limits, version, public settings.
* ``GET /metrics``     -- Prometheus text.
* ``/maps``            -- site maps that grow scan by scan (see :mod:`.maps`).

``create_app(settings)`` builds an app with its own runtime, so tests and embedders
can run several side by side.
"""

from __future__ import annotations

import asyncio
import time
from contextlib import asynccontextmanager
from typing import Annotated, Any, AsyncIterator, Literal

from fastapi import FastAPI, Query, Request
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model

from shadowcorr import __version__
from shadowcorr.config import METHODS, REQUEST_OPTIONS, ShadowCorrConfig
from shadowcorr.export import FORMATS, STORAGES, rerun_available
from shadowcorr.result import Result

from .errors import ApiError, ErrorBody, install_error_handlers, problems_from_pydantic
from .maps import add_map_routes
from .jobs import Artefact
from .metrics import CONTENT_TYPE_LATEST, ServiceMetrics
from .middleware import AccessMiddleware
from .multipart import BodyError, content_kind
from .runtime import Runtime
from .settings import ServiceSettings

__all__ = ["create_app", "CorrespondQuery"]


def _query_model() -> type[BaseModel]:
    """Query parameters of /correspond: ``method``, ``metrics`` and the library's REQUEST_OPTIONS.

    Built from ``ShadowCorrConfig``'s own fields, with their defaults and constraints
    (``bandwidth > 0`` becomes ``exclusiveMinimum: 0`` in OpenAPI), so the service never
    drifts from the library: a new request option appears here without service edits.
    Numbers must be finite (``bandwidth=inf`` or ``nan`` is refused before any work);
    unknown names are refused.
    """
    fields: dict[str, Any] = {
        "method": (
            Literal[METHODS],
            Field(ShadowCorrConfig.model_fields["method"].default,
                  description=ShadowCorrConfig.model_fields["method"].description),
        ),
        "metrics": (bool, Field(False, description="add ground-truth metrics to the result when the bundle has ground truth")),
        "format": (Literal["json", *FORMATS], Field(
            "json", description="json: the result; bag: a zip of a ROS 2 bag directory and result.json; ply: a zip of "
            "the PLY files and result.json; rrd: a Rerun recording (501 where the Rerun SDK is not installed)")),
        "frame_id": (str, Field("map", min_length=1, max_length=256, pattern=r"^[A-Za-z0-9_/]+$",
                                description="world frame of the bag's messages (format=bag)")),
        "storage": (Literal[STORAGES], Field("mcap", description="the bag's storage plugin (format=bag)")),
    }
    for name in REQUEST_OPTIONS:
        f = ShadowCorrConfig.model_fields[name]
        finite = {"allow_inf_nan": False} if f.annotation is float else {}
        annotation = Annotated[(f.annotation, *f.metadata)] if f.metadata else f.annotation
        fields[name] = (annotation, Field(f.default, description=f.description or name, **finite))
    return create_model("CorrespondQuery", __config__=ConfigDict(extra="forbid"), **fields)


CorrespondQuery = _query_model()

_ERRORS: dict[int | str, dict[str, Any]] = {
    200: {"description": "the result JSON; with format=bag or ply a zip archive (the bag directory or the PLY files, "
          "and result.json), with format=rrd a Rerun recording",
          "content": {"application/zip": {"schema": {"type": "string", "format": "binary"}},
                      "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}},
    400: {"model": ErrorBody, "description": "malformed body: bad multipart form, empty body, client gone mid-upload "
          "(bad_multipart, empty_body, client_disconnected, bad_request)"},
    401: {"model": ErrorBody, "description": "bearer token missing or wrong, when the service has one (unauthorized)"},
    408: {"model": ErrorBody, "description": "headers or body too slow: header_timeout_s, body_timeout_s, "
          "min_upload_bytes_per_s (header_timeout, body_timeout)"},
    413: {"model": ErrorBody, "description": "over a size or cost limit: max_body_bytes, max_scene_pixels, "
          "max_mask_runs, max_segments, max_scene_points, max_stage_seconds, worker_memory_bytes (payload_too_large, "
          "too_many_pixels, too_many_runs, too_many_segments, too_many_points, too_many_voxels, stage_too_slow, "
          "too_large)"},
    415: {"model": ErrorBody, "description": "unsupported Content-Type (unsupported_media_type)"},
    429: {"model": ErrorBody, "description": "this client already has max_requests_per_client requests in flight "
          "(too_many_requests); see Retry-After",
          "headers": {"Retry-After": {"description": "seconds to wait before retrying", "schema": {"type": "integer"}}}},
    422: {"model": ErrorBody, "description": "invalid bundle, query or scene; 'problems' name each one (invalid_bundle, "
          "invalid_options, invalid_request, no_segments, no_valid_depth, unprocessable_scene)"},
    431: {"model": ErrorBody, "description": "request line and headers over max_header_bytes (headers_too_large)"},
    500: {"model": ErrorBody, "description": "internal error, or the worker process died (worker_crashed: retry is safe)"},
    501: {"model": ErrorBody, "description": "format=rrd on a server without the Rerun SDK (format_unavailable)"},
    503: {"model": ErrorBody, "description": "not ready, shutting down, too many requests / upload bytes / connections "
          "in flight (not_ready, shutting_down, overloaded, too_many_connections); see Retry-After",
          "headers": {"Retry-After": {"description": "seconds to wait before retrying", "schema": {"type": "integer"}}}},
    504: {"model": ErrorBody, "description": "the request took longer than request_timeout_s (timeout)"},
}

_BINARY = {"type": "string", "format": "binary"}
_BODY_SCHEMA = {
    "required": True,
    "content": {
        "multipart/form-data": {
            "schema": {
                "description": "either a 'bundle' archive part, or a 'manifest' part plus one file part per file the "
                "manifest names (the part's filename is the path in the manifest); never both",
                "oneOf": [
                    {
                        "type": "object",
                        "title": "archive",
                        "required": ["bundle"],
                        "properties": {"bundle": {**_BINARY, "minLength": 1, "description": "a bundle as .zip or .tar(.gz)"}},
                        "additionalProperties": False,
                    },
                    {
                        "type": "object",
                        "title": "parts",
                        "required": ["manifest"],
                        "properties": {
                            "manifest": {"type": "string", "minLength": 1, "description": "manifest.json text"},
                            "files": {"type": "array", "items": _BINARY},
                        },
                        "additionalProperties": False,
                    },
                ],
            }
        },
        **{t: {"schema": _BINARY} for t in ("application/zip", "application/x-tar")},
    },
}


async def _unless(work: Any, watcher: Any) -> Any:
    """Await ``work``; if ``watcher`` ends first, cancel ``work`` and raise what ``watcher`` raised.

    Watchers wait for something that makes the answer pointless or impossible (the
    client left, the shutdown deadline passed) and then raise the :class:`ApiError` to
    answer with.
    """
    task = asyncio.ensure_future(work)
    guard = asyncio.ensure_future(watcher)
    try:
        done, _ = await asyncio.wait({task, guard}, return_when=asyncio.FIRST_COMPLETED)
    except asyncio.CancelledError:  # uvicorn gave up on the request: stop both
        task.cancel()
        guard.cancel()
        await asyncio.gather(task, guard, return_exceptions=True)
        raise
    if task in done:
        guard.cancel()
        await asyncio.gather(guard, return_exceptions=True)
        return task.result()
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    guard.result()  # raises the watcher's error
    raise RuntimeError("a watcher returned without an error")  # pragma: no cover - watchers always raise


async def _disconnected(request: Request) -> None:
    """Raise once the client disconnects (after the body, the next ASGI message can only be that)."""
    while (await request.receive())["type"] != "http.disconnect":
        pass
    raise ApiError(400, "client_disconnected", "the client disconnected before the answer was ready")


async def _shutdown_deadline(runtime: Runtime) -> None:
    """Raise 503 at the shutdown deadline: an answer the client can act on, instead of a dropped request."""
    await runtime.until_shutdown_deadline()
    grace = runtime.settings.graceful_shutdown_s
    raise ApiError(
        503,
        "shutting_down",
        f"the service is shutting down and this request did not finish within graceful_shutdown_s = {grace:g} s; "
        "retry it (another instance may take it)",
        headers={"Retry-After": str(runtime.settings.retry_after_s)},
    )


#: Media type of each artefact (``?format=``): bags and PLY files are directories, sent as zip archives.
_ARTEFACT_TYPES = {"bag": "application/zip", "ply": "application/zip", "rrd": "application/octet-stream"}


#: The file name each artefact is offered under (Content-Disposition).
_ARTEFACT_FILES = {"bag": "shadowcorr_bag.zip", "ply": "shadowcorr_ply.zip", "rrd": "shadowcorr.rrd"}


def create_app(settings: ServiceSettings | None = None) -> FastAPI:
    """A new service app (its runtime starts with the ASGI lifespan)."""
    settings = settings or ServiceSettings()
    metrics = ServiceMetrics()
    runtime = Runtime(settings, metrics)
    base_config = runtime.base_config

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        await runtime.start()
        try:
            yield
        finally:  # uvicorn has drained in-flight requests (timeout_graceful_shutdown) by now
            await runtime.stop()

    app = FastAPI(
        title="ShadowCorr",
        version=__version__,
        description="Which 3D segments seen from different camera views are the same physical rock.",
        lifespan=lifespan,
    )
    app.state.runtime = runtime
    app.state.settings = settings
    install_error_handlers(app, on_error=lambda code: metrics.errors.labels(code).inc())
    token = settings.auth_token.get_secret_value() if settings.auth_token is not None else None
    app.add_middleware(AccessMiddleware, metrics=metrics, runtime=runtime, token=token,
                       max_header_bytes=settings.max_header_bytes)

    @app.post(
        "/correspond",
        response_model=Result,
        responses=_ERRORS,
        openapi_extra={"requestBody": _BODY_SCHEMA},
        summary="Label every segment of one scene with its physical object",
    )
    async def correspond(
        request: Request, query: Annotated[CorrespondQuery, Query()]  # type: ignore[valid-type]
    ) -> Response:
        params = query.model_dump()  # type: ignore[attr-defined]
        options = {k: params[k] for k in REQUEST_OPTIONS}
        try:
            config = base_config.with_options(**options, method=params["method"])
        except ValidationError as e:
            problems = problems_from_pydantic(e.errors(include_url=False), prefix="query")
            summary = "; ".join(f"{p['loc']}: {p['msg']}" for p in problems)
            raise ApiError(422, "invalid_options", f"invalid options: {summary}", problems) from None
        content_type = request.headers.get("content-type", "")
        try:
            content_kind(content_type)  # wrong media type: refuse before reading a byte
        except BodyError as e:
            code = "unsupported_media_type" if e.status == 415 else "bad_multipart"
            raise ApiError(e.status, code, str(e), [{"loc": e.loc, "msg": str(e)}]) from None
        artefact = None
        if params["format"] != "json":
            if params["format"] == "rrd" and not rerun_available():
                raise ApiError(501, "format_unavailable", "format=rrd needs the Rerun SDK on the server "
                               "(pip install 'shadowcorr[viz]'); format=bag and format=ply work without it")
            artefact = Artefact(params["format"], params["frame_id"], params["storage"])
        runtime.check_accepting()

        async def run() -> bytes:
            started = time.monotonic()
            # The whole body first: a slow or stalled upload holds no admission slot.
            upload, reserved = await runtime.receive(request)
            client = request.client.host if request.client else "unknown"
            ticket = runtime.admit(upload, reserved, started, client)
            try:
                work = _unless(runtime.correspond(ticket, content_type, config, bool(params["metrics"]), artefact),
                               _disconnected(request))
                # wait_for, not asyncio.timeout: the project supports Python 3.10.
                return await asyncio.wait_for(work, settings.request_timeout_s)
            except asyncio.TimeoutError:
                raise ApiError(
                    504, "timeout", f"the request did not finish within request_timeout_s = {settings.request_timeout_s:g} s"
                ) from None
            finally:
                runtime.release(ticket)  # the slot stays taken until its worker job has really stopped

        out = await _unless(run(), _shutdown_deadline(runtime))
        if artefact is None:
            return Response(out, media_type="application/json")
        return Response(out, media_type=_ARTEFACT_TYPES[artefact.format],
                        headers={"Content-Disposition": f'attachment; filename="{_ARTEFACT_FILES[artefact.format]}"'})

    add_map_routes(app, runtime, _ERRORS, _BODY_SCHEMA)

    @app.get("/health", summary="Liveness and readiness (no auth)")
    async def health() -> JSONResponse:
        body = runtime.health()
        return JSONResponse(body, status_code=200 if body["ready"] else 503)

    @app.get("/info", summary="Model card, limits, version and public settings")
    async def info() -> dict[str, Any]:
        return runtime.info()

    @app.get("/metrics", summary="Prometheus metrics", response_class=Response)
    async def prometheus() -> Response:
        return Response(metrics.render(), media_type=CONTENT_TYPE_LATEST)

    return app

