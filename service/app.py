"""The FastAPI application: routes, lifespan, error handlers.

Routes:

* ``POST /correspond`` -- one scene in (multipart form or bare archive), Result JSON out.
* ``GET /health``      -- liveness + readiness (503 until the model and workers are warm).
* ``GET /info``        -- model card, limits, version, public settings.
* ``GET /metrics``     -- Prometheus text.

``create_app(settings)`` builds an app with its own runtime, so tests and embedders
can run several side by side.
"""

from __future__ import annotations

import asyncio
import time
from contextlib import asynccontextmanager
from typing import Annotated, Any, AsyncIterator, Literal, Optional

from fastapi import FastAPI, Query, Request
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model

from shadowcorr import __version__
from shadowcorr.config import METHODS, REQUEST_OPTIONS, ShadowCorrConfig
from shadowcorr.result import Result

from .errors import ApiError, ErrorBody, install_error_handlers, problems_from_pydantic
from .limits import read_body
from .metrics import CONTENT_TYPE_LATEST, ServiceMetrics
from .middleware import AccessMiddleware
from .multipart import BodyError, content_kind
from .runtime import Runtime
from .settings import ServiceSettings

__all__ = ["create_app", "CorrespondQuery"]


def _query_model() -> type[BaseModel]:
    """Query parameters of /correspond: ``method``, ``metrics`` and the library's REQUEST_OPTIONS.

    Built from ``ShadowCorrConfig``'s own fields so the service never drifts from the
    library: a new request option appears here (and in OpenAPI) without service edits.
    Values are checked by ``ShadowCorrConfig.with_options``; unknown names are refused.
    """
    fields: dict[str, Any] = {
        "method": (
            Literal[METHODS],
            Field(ShadowCorrConfig.model_fields["method"].default,
                  description=ShadowCorrConfig.model_fields["method"].description),
        ),
        "metrics": (bool, Field(False, description="add ground-truth metrics to the result when the bundle has ground truth")),
    }
    for name in REQUEST_OPTIONS:
        f = ShadowCorrConfig.model_fields[name]
        desc = f"{f.description or name} (default {f.default!r})"
        fields[name] = (Optional[f.annotation], Field(None, description=desc))  # type: ignore[name-defined]
    return create_model("CorrespondQuery", __config__=ConfigDict(extra="forbid"), **fields)


CorrespondQuery = _query_model()

_ERRORS: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorBody, "description": "malformed multipart body"},
    401: {"model": ErrorBody, "description": "bearer token missing or wrong (when the service has one)"},
    413: {"model": ErrorBody, "description": "body, scene or segment count over a limit"},
    415: {"model": ErrorBody, "description": "unsupported Content-Type"},
    422: {"model": ErrorBody, "description": "invalid bundle or options; 'problems' name each one"},
    500: {"model": ErrorBody, "description": "internal error, or the worker process died (retry is safe)"},
    503: {"model": ErrorBody, "description": "not ready yet, or too many requests in flight (see Retry-After)"},
    504: {"model": ErrorBody, "description": "the request took longer than the request timeout"},
}

_BODY_SCHEMA = {
    "required": True,
    "content": {
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "description": "either 'bundle', or 'manifest' plus one file part per file the manifest names "
                "(the part's filename is the path in the manifest)",
                "properties": {
                    "bundle": {"type": "string", "format": "binary", "description": "a bundle as .zip or .tar(.gz)"},
                    "manifest": {"type": "string", "description": "manifest.json text"},
                    "files": {"type": "array", "items": {"type": "string", "format": "binary"}},
                },
            }
        },
        **{t: {"schema": {"type": "string", "format": "binary"}} for t in ("application/zip", "application/x-tar")},
    },
}


async def _unless_disconnected(request: Request, work: Any) -> Any:
    """Await ``work``, but cancel it if the client disconnects first (nobody would read the answer).

    Once the body has been read, the next ASGI message can only be ``http.disconnect``.
    """

    async def disconnected() -> None:
        while (await request.receive())["type"] != "http.disconnect":
            pass

    task = asyncio.ensure_future(work)
    watcher = asyncio.ensure_future(disconnected())
    try:
        done, _ = await asyncio.wait({task, watcher}, return_when=asyncio.FIRST_COMPLETED)
    except asyncio.CancelledError:  # timeout or shutdown: stop both
        task.cancel()
        watcher.cancel()
        await asyncio.gather(task, watcher, return_exceptions=True)
        raise
    if task in done:
        watcher.cancel()
        await asyncio.gather(watcher, return_exceptions=True)
        return task.result()
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    raise ApiError(400, "client_disconnected", "the client disconnected before the answer was ready")


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
    app.add_middleware(AccessMiddleware, metrics=metrics, token=token)

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
        options = {k: params[k] for k in REQUEST_OPTIONS if params.get(k) is not None}
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

        async def run() -> bytes:
            t0 = time.perf_counter()
            body = await read_body(request, settings.max_body_bytes)
            metrics.stage_latency.labels("read_body").observe(time.perf_counter() - t0)
            work = runtime.correspond(ticket, body, content_type, config, bool(params["metrics"]))
            del body  # the pipeline owns the upload now and drops it once it is decoded
            return await _unless_disconnected(request, work)

        ticket = runtime.admit()
        try:
            # wait_for, not asyncio.timeout: the project supports Python 3.10.
            out = await asyncio.wait_for(run(), settings.request_timeout_s)
        except asyncio.TimeoutError:
            raise ApiError(
                504, "timeout", f"the request did not finish within {settings.request_timeout_s:g} s"
            ) from None
        finally:
            runtime.release(ticket)
        return Response(out, media_type="application/json")

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

