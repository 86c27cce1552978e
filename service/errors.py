"""Error responses: one JSON shape for every failure, and the handlers that produce it.

Every error the service returns is ``{"error": code, "message": str, "problems": [{loc, msg}]}``
so that a client needs a single code path: ``code`` is short and stable (for programs),
``message`` is a sentence (for people), ``problems`` point at the offending input.

Errors raised inside worker processes cross a process boundary by pickling.  Plain
exception pickling re-creates an exception from ``args`` only, which would lose the
structured problems of a ``BundleError``, so workers raise :class:`JobError` whose
``args`` *are* its fields.
"""

from __future__ import annotations

import logging
from http import HTTPStatus
from typing import Any, Callable, Mapping, Sequence

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

__all__ = [
    "ApiError",
    "JobError",
    "ErrorBody",
    "ProblemModel",
    "error_response",
    "install_error_handlers",
    "problems_from_pydantic",
]

log = logging.getLogger("shadowcorr.service")


class ProblemModel(BaseModel):
    loc: str = Field(description="where the problem is: a query parameter, a form part, a manifest field")
    msg: str


class ErrorBody(BaseModel):
    """The body of every error response."""

    error: str = Field(description="short stable code, e.g. 'invalid_bundle', 'payload_too_large'")
    message: str = Field(description="human-readable summary naming the problem")
    problems: list[ProblemModel] = Field(default_factory=list)


class ApiError(Exception):
    """An error that becomes an HTTP response (raised in the main process)."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        problems: Sequence[Mapping[str, str]] | None = None,
        headers: Mapping[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.problems = [dict(p) for p in problems or ()]
        self.headers = dict(headers or {})


class JobError(Exception):
    """An error raised in a worker process, picklable with all its fields."""

    def __init__(self, status: int, code: str, message: str, problems: list[dict[str, str]] | None = None) -> None:
        super().__init__(status, code, message, list(problems or []))

    @property
    def status(self) -> int:
        return int(self.args[0])

    @property
    def code(self) -> str:
        return str(self.args[1])

    @property
    def message(self) -> str:
        return str(self.args[2])

    @property
    def problems(self) -> list[dict[str, str]]:
        return list(self.args[3])

    def __str__(self) -> str:
        return f"{self.code}: {self.message}"

    def to_api(self) -> ApiError:
        return ApiError(self.status, self.code, self.message, self.problems)


def error_response(
    status: int,
    code: str,
    message: str,
    problems: Sequence[Mapping[str, str]] | None = None,
    headers: Mapping[str, str] | None = None,
) -> JSONResponse:
    body = {"error": code, "message": message, "problems": [dict(p) for p in problems or ()]}
    return JSONResponse(body, status_code=status, headers=dict(headers or {}))


def problems_from_pydantic(errors: Sequence[Mapping[str, Any]], prefix: str = "") -> list[dict[str, str]]:
    """pydantic / FastAPI error dicts -> ``[{loc, msg}]`` with dotted locs (``query.bandwidth``)."""
    out = []
    for e in errors:
        parts = [str(p) for p in e.get("loc", ())]
        if prefix:
            parts.insert(0, prefix)
        msg = str(e.get("msg", "invalid value"))
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, ") :]
        if e.get("type") == "extra_forbidden":
            msg = "unknown parameter"
        out.append({"loc": ".".join(parts) or "request", "msg": msg})
    return out


def _summary(problems: Sequence[Mapping[str, str]], what: str) -> str:
    shown = "; ".join(f"{p['loc']}: {p['msg']}" for p in problems[:5])
    more = f" (and {len(problems) - 5} more)" if len(problems) > 5 else ""
    return f"{what}: {shown}{more}" if shown else what


_STATUS_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    413: "payload_too_large",
    415: "unsupported_media_type",
    422: "invalid_request",
    429: "too_many_requests",
    500: "internal_error",
    503: "unavailable",
    504: "timeout",
}


def _allowed_methods(request: Request) -> str:
    """The methods of every route whose path matches the request's (one route per method and path)."""
    methods: set[str] = set()
    for route in request.app.routes:
        regex = getattr(route, "path_regex", None)
        if regex is not None and regex.match(request.url.path) and getattr(route, "methods", None):
            methods |= set(route.methods)
    return ", ".join(sorted(methods))


def install_error_handlers(app: Any, on_error: Callable[[str], None] | None = None) -> None:
    """Route every exception through the one JSON error shape; ``on_error(code)`` counts them."""

    def respond(status: int, code: str, message: str, problems: Any = None, headers: Any = None) -> JSONResponse:
        if on_error is not None:
            on_error(code)
        return error_response(status, code, message, problems, headers)

    async def api_error(_: Request, exc: ApiError) -> JSONResponse:
        return respond(exc.status, exc.code, exc.message, exc.problems, exc.headers)

    async def validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
        problems = problems_from_pydantic(exc.errors())
        # Query parameters are the method's options (bandwidth, ...): the code clients already know for them.
        options = bool(problems) and all(p["loc"].startswith("query.") for p in problems)
        code, what = ("invalid_options", "invalid options") if options else ("invalid_request", "invalid request parameters")
        return respond(422, code, _summary(problems, what), problems)

    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = _STATUS_CODES.get(exc.status_code, "http_error")
        detail = exc.detail if isinstance(exc.detail, str) else HTTPStatus(exc.status_code).phrase
        headers = getattr(exc, "headers", None)
        if exc.status_code == 405:  # every method of the path, not only those of its first route
            headers = {**(headers or {}), "Allow": _allowed_methods(request)}
        return respond(exc.status_code, code, detail, headers=headers)

    async def unexpected(_: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error")
        return respond(500, "internal_error", f"internal error ({type(exc).__name__}); see the server log")

    app.add_exception_handler(ApiError, api_error)
    app.add_exception_handler(RequestValidationError, validation_error)
    app.add_exception_handler(StarletteHTTPException, http_error)
    app.add_exception_handler(Exception, unexpected)
