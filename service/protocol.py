"""uvicorn's h11 HTTP protocol with connection guards and JSON error bodies.

uvicorn answers some requests itself, before the application sees them, and has no
time limit on receiving a request's headers.  This subclass of its h11 protocol adds:

* a **header timeout**: a connection that has not sent a complete request line and
  headers within ``header_timeout_s`` (counted from the connection's start, or from
  the end of its previous response) gets 408 and is closed, so a client dripping one
  header byte a second ("slow loris") cannot hold a connection;
* a **connection limit**: beyond ``max_connections`` open connections, a new
  connection's request is answered 503 (with ``Retry-After``) and the connection closed;
* a **draining shutdown**: uvicorn closes idle keep-alive connections as soon as it
  starts shutting down, so a request a client sends on one just then gets no answer at
  all.  Here they stay open for ``graceful_shutdown_s``, where the application answers
  every request JSON 503 ``shutting_down`` with ``Connection: close`` (see
  ``middleware.py``); those still idle at its end are closed then;
* **JSON error bodies** for what uvicorn / h11 refuse themselves (malformed request
  line or headers, a non-numeric ``Content-Length``, headers or a query string over
  ``max_header_bytes``: 400 / 431), in the service's one error shape
  ``{"error", "message", "problems"}``.

The body-read deadline and the minimum upload rate are enforced by the application
(``limits.receive_body``), where the request's size and route are known.
"""

from __future__ import annotations

import asyncio
import json
import logging
import sys
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

__all__ = ["guarded_protocol", "error_bytes"]

log = logging.getLogger("shadowcorr.service")

_REASONS = {400: b"Bad Request", 408: b"Request Timeout", 431: b"Request Header Fields Too Large",
            503: b"Service Unavailable"}


def error_bytes(status: int, code: str, message: str, loc: str, headers: dict[str, str] | None = None) -> bytes:
    """A complete HTTP/1.1 error response (JSON body, ``Connection: close``) as raw bytes."""
    body = json.dumps({"error": code, "message": message, "problems": [{"loc": loc, "msg": message}]}).encode()
    head = [b"HTTP/1.1 %d %s" % (status, _REASONS.get(status, b"Error")),
            b"content-type: application/json", b"content-length: %d" % len(body), b"connection: close"]
    head += [f"{k.lower()}: {v}".encode("latin-1") for k, v in (headers or {}).items()]
    return b"\r\n".join(head) + b"\r\n\r\n" + body


class _GuardedH11Protocol(H11Protocol):
    """See the module docstring.  Limits come from class attributes set by :func:`guarded_protocol`."""

    header_timeout_s: float = 5.0
    max_connections: int = 256
    max_header_bytes: int = 64 * 1024
    retry_after_s: int = 2
    graceful_shutdown_s: float = 30.0

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._header_timer: asyncio.TimerHandle | None = None
        self._drain_timer: asyncio.TimerHandle | None = None

    # ---------------------------------------------------------------- header timeout
    def _arm_header_timer(self) -> None:
        self._disarm_header_timer()
        self._header_timer = self.loop.call_later(self.header_timeout_s, self._header_timed_out)

    def _disarm_header_timer(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _header_timed_out(self) -> None:
        self._header_timer = None
        if self.transport.is_closing():
            return
        msg = f"the request line and headers did not arrive within {self.header_timeout_s:g} s"
        self._close_with(408, "header_timeout", msg, "headers")

    def _close_with(self, status: int, code: str, message: str, loc: str, headers: dict[str, str] | None = None) -> None:
        """Answer with a JSON error and close; h11's state no longer matters on this connection."""
        try:
            self.transport.write(error_bytes(status, code, message, loc, headers))
        finally:
            self.transport.close()

    # ---------------------------------------------------------------- uvicorn hooks
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        if len(self.connections) > self.max_connections:
            # Answered once its request line has arrived (clients read a response best then).
            self.app = self._over_limit  # type: ignore[assignment]
        self._arm_header_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm_header_timer()
        if self._drain_timer is not None:
            self._drain_timer.cancel()
        super().connection_lost(exc)

    def handle_events(self) -> None:
        cycle = self.cycle
        super().handle_events()
        if self.cycle is not cycle:  # a complete request line + headers arrived
            self._disarm_header_timer()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():  # keep-alive: the next request's headers are timed too
            self._arm_header_timer()

    def shutdown(self) -> None:
        # Called by uvicorn's shutdown for every open connection.  A busy one is closed after
        # its response (uvicorn's way); an idle one stays open until the grace period ends.
        if self.cycle is None or self.cycle.response_complete:
            self._drain_timer = self.loop.call_later(self.graceful_shutdown_s, super().shutdown)
        else:
            super().shutdown()

    def send_400_response(self, msg: str) -> None:
        # Called by uvicorn inside its ``except h11.RemoteProtocolError`` block.
        exc = sys.exc_info()[1]
        status = getattr(exc, "error_status_hint", 400) if isinstance(exc, h11.RemoteProtocolError) else 400
        detail = str(exc) if exc is not None else msg
        self._disarm_header_timer()
        if status == 431:
            self._close_with(431, "headers_too_large",
                             f"the request line and headers are larger than max_header_bytes = {self.max_header_bytes} "
                             "bytes (a query string counts too)", "headers")
        else:
            self._close_with(400, "bad_request", f"invalid HTTP request: {detail}", "headers")

    async def _over_limit(self, scope: Any, receive: Any, send: Any) -> None:
        body = json.dumps({
            "error": "too_many_connections",
            "message": f"more than {self.max_connections} open connections; retry later",
            "problems": [],
        }).encode()
        await send({"type": "http.response.start", "status": 503, "headers": [
            (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
            (b"retry-after", str(self.retry_after_s).encode()), (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})


def guarded_protocol(*, header_timeout_s: float, max_connections: int, max_header_bytes: int,
                     retry_after_s: int, graceful_shutdown_s: float) -> type[H11Protocol]:
    """The protocol class to pass as ``uvicorn.Config(http=...)``, with these limits."""
    return type("GuardedH11Protocol", (_GuardedH11Protocol,), {
        "header_timeout_s": header_timeout_s,
        "max_connections": max_connections,
        "max_header_bytes": max_header_bytes,
        "retry_after_s": retry_after_s,
        "graceful_shutdown_s": graceful_shutdown_s,
    })
