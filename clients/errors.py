"""Exceptions raised by the ShadowCorr HTTP client.

One base class, :class:`ShadowCorrError`, so a caller that only wants "did it work"
needs a single ``except``.  Below it the split follows what a caller can *do*:

* :class:`ConnectionFailed` -- the server could not be reached or dropped the
  connection (after the configured retries): check the address, try later.
* :class:`ClientError` (4xx) -- the request itself is wrong (bad bundle, bad option,
  bad token, too large): fix the input; retrying cannot help, so it never happens.
* :class:`ServerError` (5xx) -- the server failed or was overloaded (503) even after
  the retries: try later, or look at the server log.
* :class:`InvalidResponse` -- a 2xx answer that is not the JSON the contract promises
  (a proxy page, a version mismatch).
* :class:`BundleInputError` -- the local input could not be packed for upload
  (missing manifest, a file it names is absent); raised before anything is sent.
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "ShadowCorrError",
    "ConnectionFailed",
    "ResponseError",
    "ClientError",
    "ServerError",
    "InvalidResponse",
    "BundleInputError",
]


class ShadowCorrError(Exception):
    """Base class of every error raised by :mod:`clients`."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (used for the ``error`` field of upload records)."""
        return {"type": type(self).__name__, "message": str(self)}


class ConnectionFailed(ShadowCorrError):
    """No HTTP answer: connect refused, connection dropped, DNS failure or timeout."""

    def __init__(self, message: str, *, url: str = "", attempts: int = 1) -> None:
        super().__init__(message)
        self.url = url
        self.attempts = attempts

    def to_dict(self) -> dict[str, Any]:
        return {**super().to_dict(), "url": self.url, "attempts": self.attempts}


class ResponseError(ShadowCorrError):
    """The server answered with an error status; fields mirror the service's error JSON.

    Attributes
    ----------
    status : int
        HTTP status code.
    error : str
        Short, stable error code from the body (``invalid_bundle``, ``unavailable``, ...);
        ``http_<status>`` when the body is not the service's error JSON.
    message : str
        Human-readable sentence from the server.
    problems : list of dict
        ``[{"loc": ..., "msg": ...}]`` pointing at the offending input.
    retry_after : float or None
        Seconds from the ``Retry-After`` header, when the server sent one.
    attempts : int
        Requests made before giving up (1 when not retried).
    """

    def __init__(
        self,
        status: int,
        error: str,
        message: str,
        problems: list[dict[str, str]] | None = None,
        *,
        retry_after: float | None = None,
        attempts: int = 1,
    ) -> None:
        self.status = status
        self.error = error
        self.message = message
        self.problems = list(problems or [])
        self.retry_after = retry_after
        self.attempts = attempts
        super().__init__(self._render())

    def _render(self) -> str:
        text = f"HTTP {self.status} {self.error}: {self.message}"
        # The message usually summarises the problems already; list the ones it does not name.
        extra = [p for p in self.problems if f"{p.get('loc')}: {p.get('msg')}" not in self.message]
        if extra:
            text += " [" + "; ".join(f"{p.get('loc')}: {p.get('msg')}" for p in extra[:5]) + "]"
        if self.attempts > 1:
            text += f" (after {self.attempts} attempts)"
        return text

    def __str__(self) -> str:
        return self._render()

    def to_dict(self) -> dict[str, Any]:
        return {
            "type": type(self).__name__,
            "status": self.status,
            "error": self.error,
            "message": self.message,
            "problems": self.problems,
            "attempts": self.attempts,
        }


class ClientError(ResponseError):
    """A 4xx answer: the request is wrong.  Never retried."""


class ServerError(ResponseError):
    """A 5xx answer that outlived the retries (or was not retryable, like a 500)."""


class InvalidResponse(ShadowCorrError):
    """A success status whose body is not what the HTTP contract describes."""

    def __init__(self, message: str, *, status: int = 200) -> None:
        super().__init__(message)
        self.status = status


class BundleInputError(ShadowCorrError, ValueError):
    """The local bundle could not be packed for upload (nothing was sent)."""
