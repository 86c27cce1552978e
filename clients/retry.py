"""When and how long to wait before re-sending a request.

Pure functions and a frozen policy object, shared by the sync and the async client
so both behave identically and the logic is testable without a network.

What is retried, and why:

* connection-level failures (refused, reset, dropped before an answer): the request
  never produced a result, and ``POST /correspond`` is a pure computation, so
  sending it again is safe;
* ``503`` (queue full / not ready) and ``502`` (a proxy lost the upstream): transient
  by definition.  A ``Retry-After`` header is honoured -- never retry sooner than the
  server asked -- but capped, so a misconfigured server cannot stall a client for hours;
* never a 4xx (the request is wrong and will stay wrong), never a ``500`` (a bug
  repeats), and by default never a *read* timeout: the server may still be working on
  the scene, and re-sending would double its load exactly when it is slowest.

Backoff is exponential with "equal jitter" (half fixed, half random): the fixed half
guarantees the wait grows, the random half keeps many clients that failed together
from coming back together.
"""

from __future__ import annotations

import email.utils
import math
import random
import time
from dataclasses import dataclass, field

import httpx

__all__ = ["RetryPolicy", "NO_RETRY", "parse_retry_after", "is_retryable_exception"]


@dataclass(frozen=True)
class RetryPolicy:
    """How many times to try a request and how long to wait in between.

    Parameters
    ----------
    max_attempts : int
        Requests in total, the first included (1 = no retry).
    backoff_base : float
        Seconds before the first retry (before jitter); doubles (``backoff_factor``) each time.
    backoff_factor : float
        Growth of the wait per attempt.
    backoff_max : float
        Upper bound of the exponential wait, in seconds.
    retry_after_max : float
        Upper bound of an honoured ``Retry-After``, in seconds.
    retry_statuses : frozenset of int
        HTTP statuses that are retried (never 4xx: they are rejected here).
    retry_timeouts : bool
        Also retry read/write timeouts (off by default, see the module docstring).
    """

    max_attempts: int = 5
    backoff_base: float = 0.5
    backoff_factor: float = 2.0
    backoff_max: float = 30.0
    retry_after_max: float = 60.0
    retry_statuses: frozenset[int] = field(default_factory=lambda: frozenset({502, 503}))
    retry_timeouts: bool = False

    def __post_init__(self) -> None:
        if self.max_attempts < 1:
            raise ValueError(f"max_attempts must be >= 1, got {self.max_attempts}")
        if self.backoff_base < 0 or self.backoff_max < 0 or self.retry_after_max < 0:
            raise ValueError("backoff_base, backoff_max and retry_after_max must be >= 0")
        if self.backoff_factor < 1:
            raise ValueError(f"backoff_factor must be >= 1, got {self.backoff_factor}")
        bad = sorted(s for s in self.retry_statuses if s < 500)
        if bad:
            # A 4xx means the request is wrong; repeating it cannot succeed and only adds load.
            raise ValueError(f"only 5xx statuses may be retried, got {bad}")

    def backoff(self, attempt: int, rng: random.Random | None = None) -> float:
        """Seconds to wait after failed attempt number ``attempt`` (1-based), jitter included."""
        rng = rng or random
        ceiling = min(self.backoff_max, self.backoff_base * self.backoff_factor ** max(attempt - 1, 0))
        return ceiling / 2 + rng.uniform(0, ceiling / 2)

    def delay(self, attempt: int, retry_after: float | None = None, rng: random.Random | None = None) -> float:
        """Seconds to wait before the next attempt.

        With a positive ``retry_after`` the wait is at least that (capped at
        ``retry_after_max``), plus up to 10 % jitter so clients told the same
        instant do not return in lockstep; otherwise it is :meth:`backoff`.
        """
        if retry_after is not None and retry_after > 0:
            rng = rng or random
            base = min(retry_after, self.retry_after_max)
            return base + rng.uniform(0, 0.1 * base)
        return self.backoff(attempt, rng)

    def should_retry_status(self, status: int, attempt: int) -> bool:
        """Whether a response with ``status`` after attempt ``attempt`` warrants another try."""
        return status in self.retry_statuses and attempt < self.max_attempts

    def should_retry_exception(self, exc: BaseException, attempt: int) -> bool:
        """Whether a transport exception after attempt ``attempt`` warrants another try."""
        return attempt < self.max_attempts and is_retryable_exception(exc, retry_timeouts=self.retry_timeouts)


#: A policy that sends every request once.
NO_RETRY = RetryPolicy(max_attempts=1)


def is_retryable_exception(exc: BaseException, *, retry_timeouts: bool = False) -> bool:
    """Transport failures where the server produced no result, so re-sending is safe."""
    if isinstance(exc, (httpx.ReadTimeout, httpx.WriteTimeout)):
        return retry_timeouts
    # ConnectError / ConnectTimeout: nothing reached the server.  RemoteProtocolError,
    # ReadError, WriteError: the connection died mid-exchange (server restart, a stale
    # keep-alive connection the server had already closed).  PoolTimeout is local.
    return isinstance(exc, (httpx.ConnectError, httpx.ConnectTimeout, httpx.RemoteProtocolError,
                            httpx.ReadError, httpx.WriteError, httpx.PoolTimeout))


def parse_retry_after(value: str | None, *, now: float | None = None) -> float | None:
    """Seconds to wait from a ``Retry-After`` header (delta-seconds or an HTTP date).

    Returns ``None`` for a missing or unparsable header, and never a negative number
    (a date in the past means "now").
    """
    if value is None:
        return None
    text = value.strip()
    if not text:
        return None
    try:
        seconds = float(text)
    except ValueError:
        try:
            when = email.utils.parsedate_to_datetime(text)
        except (TypeError, ValueError, IndexError):
            return None
        if when is None:
            return None
        seconds = when.timestamp() - (time.time() if now is None else now)
    if not math.isfinite(seconds):
        return None
    return max(0.0, seconds)
