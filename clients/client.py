"""Synchronous and asynchronous HTTP clients for the ShadowCorr service.

Both keep one ``httpx`` connection pool for their lifetime (use them as context
managers, or call ``close``), send the bearer token when given, apply the retry
policy of :mod:`shadowcorr_client.retry`, and turn every failure into a
:class:`~shadowcorr_client.errors.ShadowCorrError`.  Successful ``/correspond`` answers are
validated into :class:`shadowcorr.result.Result`, the model the library itself returns,
when the library is installed; a client installed alone returns a
:class:`shadowcorr_client.result.ResultView` with the same attributes.

The request/response handling lives in :class:`_Protocol`, shared by both clients, so
the two can only differ in *how* they wait (``time.sleep`` vs ``asyncio.sleep``).
"""

from __future__ import annotations

import asyncio
import logging
import random
import time
from dataclasses import dataclass
from urllib.parse import quote
from typing import TYPE_CHECKING, Any, Callable, Literal, Mapping

import httpx

from .errors import ClientError, ConnectionFailed, InvalidResponse, ResponseError, ServerError
from .retry import NO_RETRY, RetryPolicy, parse_retry_after
from .request_body import BundleSource, BundleUpload, as_upload

if TYPE_CHECKING:  # the Result model is imported when the first result is parsed, not with the client
    from shadowcorr.result import Result

    from .result import ResultView

__all__ = [
    "ShadowCorrClient",
    "AsyncShadowCorrClient",
    "RetryEvent",
    "DEFAULT_SERVER",
    "DEFAULT_TIMEOUT",
    "correspond_params",
]

log = logging.getLogger("shadowcorr.client")

DEFAULT_SERVER = "http://127.0.0.1:8000"
#: Connecting is quick or hopeless; a large scene on a busy CPU server can take minutes to answer.
DEFAULT_TIMEOUT = httpx.Timeout(connect=10.0, read=300.0, write=120.0, pool=None)

Method = Literal["fused", "projection", "shadowcorr", "meanshift"]


def _user_agent() -> str:
    from importlib.metadata import PackageNotFoundError, version

    for distribution in ("shadowcorr-client", "shadowcorr"):  # installed alone, or with the library
        try:
            return f"shadowcorr-client/{version(distribution)}"
        except PackageNotFoundError:
            continue
    return "shadowcorr-client"  # run from a source tree


@dataclass(frozen=True)
class RetryEvent:
    """One retry about to happen: passed to the ``on_retry`` callback of a client."""

    method: str
    path: str
    attempt: int  # the attempt that failed (1-based)
    delay: float  # seconds until the next attempt
    status: int | None  # HTTP status that caused it, or None for a connection failure
    reason: str


def correspond_params(
    *,
    bandwidth: float | None = None,
    split_components: bool | None = None,
    min_blob_pixels: int | None = None,
    min_cluster_size: int | None = None,
    refine_poses: bool | None = None,
    method: Method | None = None,
    metrics: bool | None = None,
) -> dict[str, str]:
    """Query parameters of ``POST /correspond``; options left ``None`` use the server's defaults."""
    raw: dict[str, Any] = {
        "bandwidth": bandwidth,
        "split_components": split_components,
        "min_blob_pixels": min_blob_pixels,
        "min_cluster_size": min_cluster_size,
        "refine_poses": refine_poses,
        "method": method,
        "metrics": metrics,
    }
    # Booleans as "true"/"false": what FastAPI parses, rather than Python's "True".
    return {k: (("true" if v else "false") if isinstance(v, bool) else str(v)) for k, v in raw.items() if v is not None}


def error_from_response(response: httpx.Response, *, attempts: int = 1) -> ResponseError:
    """The exception for an error response, filled from the service's error JSON when present."""
    status = response.status_code
    code, message, problems = f"http_{status}", response.reason_phrase or "error", []
    try:
        body = response.json()
    except ValueError:
        body = None
        text = response.text.strip()
        if text:  # e.g. a reverse proxy's HTML page: show its start, not all of it
            message = f"{message}: {text[:300]}"
    if isinstance(body, dict):
        code = str(body.get("error") or code)
        message = str(body.get("message") or body.get("detail") or body.get("status") or message)
        for p in body.get("problems") or []:
            if isinstance(p, Mapping):
                problems.append({"loc": str(p.get("loc", "")), "msg": str(p.get("msg", ""))})
    cls = ClientError if status < 500 else ServerError
    return cls(status, code, message, problems, retry_after=parse_retry_after(response.headers.get("retry-after")),
               attempts=attempts)


def _parse_result(response: httpx.Response) -> "Result | ResultView":
    try:
        from shadowcorr.result import Result
    except ModuleNotFoundError:  # the client installed alone: no library, no pydantic
        from .result import parse_result_json

        try:
            return parse_result_json(response.content)
        except ValueError as exc:
            raise InvalidResponse(f"the server's answer is not a ShadowCorr result: {exc}",
                                  status=response.status_code) from None
    from pydantic import ValidationError

    try:
        return Result.model_validate_json(response.content)
    except ValidationError as exc:
        raise InvalidResponse(f"the server's answer is not a ShadowCorr result: {exc}", status=response.status_code) from None


def _map_path(map_id: str) -> str:
    """The URL path of a map, its id quoted (an id is never a path of its own)."""
    return f"/maps/{quote(str(map_id), safe='')}"


def _json(response: httpx.Response) -> Any:
    try:
        return response.json()
    except ValueError:
        raise InvalidResponse(f"expected JSON from {response.request.url.path}, got {response.text[:200]!r}",
                              status=response.status_code) from None


class _Protocol:
    """What both clients share: configuration, request construction, retry decisions."""

    def __init__(
        self,
        server: str,
        token: str | None,
        timeout: float | httpx.Timeout | None,
        retry: RetryPolicy | None,
        on_retry: Callable[[RetryEvent], None] | None,
        seed: int | None,
    ) -> None:
        if not server.startswith(("http://", "https://")):
            raise ValueError(f"server must be an http:// or https:// URL, got {server!r}")
        self.server = server.rstrip("/")
        self.retry = retry or RetryPolicy()
        self.timeout = DEFAULT_TIMEOUT if timeout is None else (
            timeout if isinstance(timeout, httpx.Timeout) else httpx.Timeout(timeout))
        self.headers = {"User-Agent": _user_agent(), "Accept": "application/json"}
        if token:
            self.headers["Authorization"] = f"Bearer {token}"
        self.on_retry = on_retry
        self.rng = random.Random(seed)  # seeded in tests for reproducible jitter; system entropy otherwise

    def decide_response(self, policy: RetryPolicy, method: str, path: str, response: httpx.Response,
                        attempt: int) -> float | None:
        """Delay before retrying this response, or ``None`` to stop (success or final error)."""
        status = response.status_code
        if status < 400 or not policy.should_retry_status(status, attempt):
            return None
        retry_after = parse_retry_after(response.headers.get("retry-after"))
        delay = policy.delay(attempt, retry_after, self.rng)
        self._notify(RetryEvent(method, path, attempt, delay, status, f"HTTP {status}"))
        return delay

    def decide_exception(self, policy: RetryPolicy, method: str, path: str, exc: httpx.TransportError,
                         attempt: int) -> float:
        """Delay before retrying after a transport failure; raises ``ConnectionFailed`` when done."""
        if not policy.should_retry_exception(exc, attempt):
            kind = "timed out" if isinstance(exc, httpx.TimeoutException) else "failed"
            raise ConnectionFailed(
                f"{method} {self.server}{path} {kind}: {type(exc).__name__}: {exc or 'no details'}"
                + (f" (after {attempt} attempts)" if attempt > 1 else ""),
                url=f"{self.server}{path}",
                attempts=attempt,
            ) from exc
        delay = policy.delay(attempt, None, self.rng)
        self._notify(RetryEvent(method, path, attempt, delay, None, type(exc).__name__))
        return delay

    def finish(self, response: httpx.Response, attempt: int) -> httpx.Response:
        """Return a successful response or raise the matching error."""
        status = response.status_code
        if 200 <= status < 300:
            return response
        if 300 <= status < 400:
            raise InvalidResponse(
                f"unexpected redirect ({status}) to {response.headers.get('location')!r}: check the server URL",
                status=status)
        raise error_from_response(response, attempts=attempt)

    def _notify(self, event: RetryEvent) -> None:
        log.info("retrying %s %s in %.2fs after attempt %d: %s", event.method, event.path, event.delay,
                 event.attempt, event.reason)
        if self.on_retry is not None:
            self.on_retry(event)


class ShadowCorrClient:
    """Blocking client of the ShadowCorr HTTP service.

    Parameters
    ----------
    server : str
        Base URL, e.g. ``http://127.0.0.1:8000``.
    token : str, optional
        Bearer token, when the server requires one.
    timeout : float or httpx.Timeout, optional
        Per-request timeouts (a float applies to connect, read, write and pool alike);
        default: 10 s to connect, 300 s to read.
    retry : RetryPolicy, optional
        Retries on connection failures, 502 and 503 (see :mod:`shadowcorr_client.retry`).
    on_retry : callable, optional
        Called with a :class:`RetryEvent` before each retry (progress displays, counters).
    transport : httpx.BaseTransport, optional
        Replaces the network transport (tests, custom TLS).
    seed : int, optional
        Seed of the backoff jitter.

    Examples
    --------
    >>> with ShadowCorrClient("http://127.0.0.1:8000") as client:  # doctest: +SKIP
    ...     result = client.correspond("scene_bundle/", metrics=True)
    ...     print(result.labels)
    """

    def __init__(
        self,
        server: str = DEFAULT_SERVER,
        *,
        token: str | None = None,
        timeout: float | httpx.Timeout | None = None,
        retry: RetryPolicy | None = None,
        on_retry: Callable[[RetryEvent], None] | None = None,
        transport: httpx.BaseTransport | None = None,
        seed: int | None = None,
    ) -> None:
        self._p = _Protocol(server, token, timeout, retry, on_retry, seed)
        self._http = httpx.Client(base_url=self._p.server, headers=self._p.headers, timeout=self._p.timeout,
                                  transport=transport, follow_redirects=False)

    @property
    def server(self) -> str:
        return self._p.server

    @property
    def retry(self) -> RetryPolicy:
        return self._p.retry

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> "ShadowCorrClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _request(self, method: str, path: str, *, retry: RetryPolicy | None = None,
                 timeout: float | httpx.Timeout | None = None, **kwargs: Any) -> httpx.Response:
        policy = retry or self._p.retry
        extra = {} if timeout is None else {"timeout": timeout}
        attempt = 0
        while True:
            attempt += 1
            try:
                response = self._http.request(method, path, **kwargs, **extra)
            except httpx.TransportError as exc:
                time.sleep(self._p.decide_exception(policy, method, path, exc, attempt))
                continue
            delay = self._p.decide_response(policy, method, path, response, attempt)
            if delay is None:
                return self._p.finish(response, attempt)
            response.close()
            time.sleep(delay)

    def health(self, *, retry: RetryPolicy | None = NO_RETRY) -> dict[str, Any]:
        """``GET /health``; raises :class:`ServerError` (503) while the server is starting.

        Not retried by default: a readiness probe wants the current answer, not a late one.
        """
        return _json(self._request("GET", "/health", retry=retry))

    def wait_until_ready(self, timeout: float = 60.0, interval: float = 0.5) -> dict[str, Any]:
        """Poll ``/health`` until it answers 200 or ``timeout`` seconds pass (then the last error is raised)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                return self.health()
            except (ConnectionFailed, ServerError):
                if time.monotonic() + interval > deadline:
                    raise
            time.sleep(interval)

    def info(self) -> dict[str, Any]:
        """``GET /info``: model, version, limits and settings of the server."""
        return _json(self._request("GET", "/info"))

    def metrics_text(self) -> str:
        """``GET /metrics``: the server's Prometheus metrics, as text."""
        return self._request("GET", "/metrics", headers={"Accept": "text/plain"}).text

    def correspond(
        self,
        bundle: BundleSource,
        *,
        bandwidth: float | None = None,
        split_components: bool | None = None,
        min_blob_pixels: int | None = None,
        min_cluster_size: int | None = None,
        refine_poses: bool | None = None,
        method: Method | None = None,
        metrics: bool | None = None,
        timeout: float | httpx.Timeout | None = None,
    ) -> "Result | ResultView":
        """Label every segment of one scene (``POST /correspond``).

        ``bundle`` is a bundle directory or archive path, archive bytes, a
        ``SceneBundle`` or a :class:`BundleUpload`.  Options left ``None`` use the
        server's defaults.  Returns the validated :class:`shadowcorr.result.Result`.
        """
        upload = as_upload(bundle)
        params = correspond_params(bandwidth=bandwidth, split_components=split_components,
                                   min_blob_pixels=min_blob_pixels, min_cluster_size=min_cluster_size,
                                   refine_poses=refine_poses, method=method, metrics=metrics)
        response = self._request("POST", "/correspond", params=params, files=list(upload.parts), timeout=timeout)
        return _parse_result(response)

    # ------------------------------------------------------------------ site maps
    def create_map(self) -> str:
        """``POST /maps``: a new, empty site map on the server; returns its id."""
        return str(_json(self._request("POST", "/maps", retry=NO_RETRY))["map"])

    def add_scan(self, map_id: str, bundle: BundleSource, *, name: str | None = None,
                 timeout: float | httpx.Timeout | None = None) -> dict[str, Any]:
        """``POST /maps/{id}/scans``: add one scan (a bundle, as for :meth:`correspond`) to a map.

        Returns the update JSON: the scan's segments with their object ids and the events it
        caused.  Not retried: a scan whose answer was lost may have been added, so read the map's
        events before sending it again.  A 409 (``map_busy``) means another scan of the map is
        being added: send it again after the Retry-After.
        """
        upload = as_upload(bundle)
        params = {"name": name} if name is not None else {}
        response = self._request("POST", f"{_map_path(map_id)}/scans", params=params, files=list(upload.parts),
                                 timeout=timeout, retry=NO_RETRY)
        return _json(response)

    def get_map(self, map_id: str) -> dict[str, Any]:
        """``GET /maps/{id}``: scans, objects, every segment with its object, and the events."""
        return _json(self._request("GET", _map_path(map_id)))

    def map_events(self, map_id: str, since: int = 0) -> list[dict[str, Any]]:
        """``GET /maps/{id}/events``: the map's history after event ``since`` (0: all of it)."""
        return list(_json(self._request("GET", f"{_map_path(map_id)}/events", params={"since": str(since)}))["events"])

    def delete_map(self, map_id: str) -> None:
        """``DELETE /maps/{id}``."""
        self._request("DELETE", _map_path(map_id))


class AsyncShadowCorrClient:
    """``asyncio`` twin of :class:`ShadowCorrClient` (same arguments, awaitable methods).

    ``max_connections`` bounds the pool; set it at least as high as the number of
    requests you run concurrently.
    """

    def __init__(
        self,
        server: str = DEFAULT_SERVER,
        *,
        token: str | None = None,
        timeout: float | httpx.Timeout | None = None,
        retry: RetryPolicy | None = None,
        on_retry: Callable[[RetryEvent], None] | None = None,
        transport: httpx.AsyncBaseTransport | None = None,
        max_connections: int = 16,
        seed: int | None = None,
    ) -> None:
        self._p = _Protocol(server, token, timeout, retry, on_retry, seed)
        self._http = httpx.AsyncClient(
            base_url=self._p.server, headers=self._p.headers, timeout=self._p.timeout, transport=transport,
            limits=httpx.Limits(max_connections=max_connections, max_keepalive_connections=max_connections),
            follow_redirects=False,
        )

    @property
    def server(self) -> str:
        return self._p.server

    @property
    def retry(self) -> RetryPolicy:
        return self._p.retry

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> "AsyncShadowCorrClient":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def _request(self, method: str, path: str, *, retry: RetryPolicy | None = None,
                       timeout: float | httpx.Timeout | None = None, **kwargs: Any) -> httpx.Response:
        policy = retry or self._p.retry
        extra = {} if timeout is None else {"timeout": timeout}
        attempt = 0
        while True:
            attempt += 1
            try:
                response = await self._http.request(method, path, **kwargs, **extra)
            except httpx.TransportError as exc:
                await asyncio.sleep(self._p.decide_exception(policy, method, path, exc, attempt))
                continue
            delay = self._p.decide_response(policy, method, path, response, attempt)
            if delay is None:
                return self._p.finish(response, attempt)
            await response.aclose()
            await asyncio.sleep(delay)

    async def health(self, *, retry: RetryPolicy | None = NO_RETRY) -> dict[str, Any]:
        """``GET /health``; raises :class:`ServerError` (503) while the server is starting."""
        return _json(await self._request("GET", "/health", retry=retry))

    async def wait_until_ready(self, timeout: float = 60.0, interval: float = 0.5) -> dict[str, Any]:
        """Poll ``/health`` until it answers 200 or ``timeout`` seconds pass (then the last error is raised)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                return await self.health()
            except (ConnectionFailed, ServerError):
                if time.monotonic() + interval > deadline:
                    raise
            await asyncio.sleep(interval)

    async def info(self) -> dict[str, Any]:
        """``GET /info``: model, version, limits and settings of the server."""
        return _json(await self._request("GET", "/info"))

    async def metrics_text(self) -> str:
        """``GET /metrics``: the server's Prometheus metrics, as text."""
        return (await self._request("GET", "/metrics", headers={"Accept": "text/plain"})).text

    async def correspond(
        self,
        bundle: BundleSource,
        *,
        bandwidth: float | None = None,
        split_components: bool | None = None,
        min_blob_pixels: int | None = None,
        min_cluster_size: int | None = None,
        refine_poses: bool | None = None,
        method: Method | None = None,
        metrics: bool | None = None,
        timeout: float | httpx.Timeout | None = None,
    ) -> "Result | ResultView":
        """Label every segment of one scene (``POST /correspond``); see :meth:`ShadowCorrClient.correspond`.

        Packing a ``SceneBundle`` or reading a bundle from disk runs in a thread, so the
        event loop keeps serving other uploads meanwhile.
        """
        upload = bundle if isinstance(bundle, BundleUpload) else await asyncio.to_thread(as_upload, bundle)
        params = correspond_params(bandwidth=bandwidth, split_components=split_components,
                                   min_blob_pixels=min_blob_pixels, min_cluster_size=min_cluster_size,
                                   refine_poses=refine_poses, method=method, metrics=metrics)
        response = await self._request("POST", "/correspond", params=params, files=list(upload.parts),
                                       timeout=timeout)
        return await asyncio.to_thread(_parse_result, response)  # a large result takes a while to validate

    # ------------------------------------------------------------------ site maps
    async def create_map(self) -> str:
        """``POST /maps``; see :meth:`ShadowCorrClient.create_map`."""
        return str(_json(await self._request("POST", "/maps", retry=NO_RETRY))["map"])

    async def add_scan(self, map_id: str, bundle: BundleSource, *, name: str | None = None,
                       timeout: float | httpx.Timeout | None = None) -> dict[str, Any]:
        """``POST /maps/{id}/scans``; see :meth:`ShadowCorrClient.add_scan`."""
        upload = bundle if isinstance(bundle, BundleUpload) else await asyncio.to_thread(as_upload, bundle)
        params = {"name": name} if name is not None else {}
        response = await self._request("POST", f"{_map_path(map_id)}/scans", params=params, files=list(upload.parts),
                                       timeout=timeout, retry=NO_RETRY)
        return _json(response)

    async def get_map(self, map_id: str) -> dict[str, Any]:
        """``GET /maps/{id}``; see :meth:`ShadowCorrClient.get_map`."""
        return _json(await self._request("GET", _map_path(map_id)))

    async def map_events(self, map_id: str, since: int = 0) -> list[dict[str, Any]]:
        """``GET /maps/{id}/events``; see :meth:`ShadowCorrClient.map_events`."""
        response = await self._request("GET", f"{_map_path(map_id)}/events", params={"since": str(since)})
        return list(_json(response)["events"])

    async def delete_map(self, map_id: str) -> None:
        """``DELETE /maps/{id}``."""
        await self._request("DELETE", _map_path(map_id))
