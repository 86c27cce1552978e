"""Pure-ASGI middleware: bearer-token check, request-head size limit, shutdown answers and per-request metrics.

The head limit (request line + headers, ``max_header_bytes``) is mostly enforced by h11
while the head arrives in pieces (see ``protocol.py``); a head that arrives complete
in one read is measured here.

Pure ASGI (not ``BaseHTTPMiddleware``) so request bodies stream through untouched and
no extra task is spawned per request.

From SIGTERM on, every request is answered JSON 503 ``shutting_down`` and every response
(those of requests still running too) carries ``Connection: close``: a client learns
that the connection ends with its answer instead of finding it closed under a request
it has just sent.
"""

from __future__ import annotations

import hmac
import time
from typing import TYPE_CHECKING, Any, Awaitable, Callable

from .errors import ApiError, error_response
from .metrics import ServiceMetrics, route_label

if TYPE_CHECKING:
    from .runtime import Runtime

__all__ = ["AccessMiddleware"]

Scope = dict[str, Any]
Receive = Callable[[], Awaitable[dict[str, Any]]]
Send = Callable[[dict[str, Any]], Awaitable[None]]

#: Routes reachable without a token: orchestrators probe health without secrets.
PUBLIC_PATHS = frozenset({"/health"})

_CLOSE = (b"connection", b"close")


class AccessMiddleware:
    """Counts and times requests, enforces the bearer token, answers 503 while shutting down."""

    def __init__(
        self,
        app: Callable[..., Awaitable[None]],
        metrics: ServiceMetrics,
        runtime: "Runtime",
        token: str | None,
        max_header_bytes: int,
    ) -> None:
        self.app = app
        self.metrics = metrics
        self.runtime = runtime
        self._expected = f"Bearer {token}".encode() if token else None
        self.max_header_bytes = max_header_bytes

    @staticmethod
    def _head_bytes(scope: Scope) -> int:
        line = len(scope.get("raw_path", b"")) + len(scope.get("query_string", b"")) + 32
        return line + sum(len(k) + len(v) + 4 for k, v in scope.get("headers", ()))

    def _authorized(self, scope: Scope) -> bool:
        if self._expected is None or scope["path"] in PUBLIC_PATHS:
            return True
        for name, value in scope.get("headers", ()):
            if name == b"authorization":
                # The scheme is case-insensitive (RFC 7235); the token is compared in constant time.
                scheme, _, token = value.partition(b" ")
                return hmac.compare_digest(b"Bearer " + token.strip(), self._expected) and scheme.lower() == b"bearer"
        return False

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        route = route_label(scope["path"])
        start = time.perf_counter()
        status = 500  # if the app dies before answering, that is what the client sees

        async def send_wrapper(message: dict[str, Any]) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                self.metrics.request_latency.labels(route).observe(time.perf_counter() - start)
                headers = list(message.get("headers", ()))
                if self.runtime.shutdown_deadline is not None and _CLOSE not in headers:
                    message = {**message, "headers": [*headers, _CLOSE]}
            await send(message)

        try:
            if self._head_bytes(scope) > self.max_header_bytes:
                response = error_response(
                    431,
                    "headers_too_large",
                    f"the request line and headers are larger than max_header_bytes = {self.max_header_bytes} bytes "
                    "(a query string counts too)",
                    [{"loc": "headers", "msg": f"larger than {self.max_header_bytes} bytes"}],
                    headers={"Connection": "close"},
                )
                self.metrics.errors.labels("headers_too_large").inc()
                await response(scope, receive, send_wrapper)
                return
            try:
                self.runtime.check_not_shutting_down()
            except ApiError as e:  # before the token check: it reveals nothing, and health probes need it too
                self.metrics.errors.labels(e.code).inc()
                await error_response(e.status, e.code, e.message, e.problems, e.headers)(scope, receive, send_wrapper)
                return
            if not self._authorized(scope):
                response = error_response(
                    401,
                    "unauthorized",
                    "missing or wrong bearer token: send 'Authorization: Bearer <token>'",
                    [{"loc": "headers.authorization", "msg": "missing or invalid"}],
                    headers={"WWW-Authenticate": 'Bearer realm="shadowcorr"'},
                )
                self.metrics.errors.labels("unauthorized").inc()
                await response(scope, receive, send_wrapper)
                return
            await self.app(scope, receive, send_wrapper)
        finally:
            self.metrics.requests.labels(route, str(status)).inc()
