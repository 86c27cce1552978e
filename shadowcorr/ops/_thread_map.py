"""Independent pieces of one stage run on several threads.

numpy releases the GIL inside its sorts and element-wise loops, SciPy's image labelling
and torch inside their kernels, so chunks of whole segments (or whole views) processed on
a small thread pool share the cores of one machine without copying the scene between
processes.  small_gicp holds the GIL while it works, so its calls are given ``num_threads``
as their own thread count instead of running inside the pool.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

Item = TypeVar("Item")
Value = TypeVar("Value")


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the platform reports one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # macOS, Windows
        return max(1, os.cpu_count() or 1)


def resolve_threads(num_threads: int) -> int:
    """``num_threads`` as a count: 0 means every available core."""
    return available_cores() if num_threads == 0 else max(1, num_threads)


def thread_map(function: Callable[[Item], Value], items: Iterable[Item], num_threads: int) -> list[Value]:
    """``[function(item) for item in items]``, on up to ``num_threads`` threads (0: every core).

    Results keep the items' order; with one thread (or one item) no pool is made.  The
    first exception raised by ``function`` propagates.
    """
    items = list(items)
    workers = min(resolve_threads(num_threads), len(items))
    if workers <= 1:
        return [function(item) for item in items]
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="shadowcorr") as pool:
        return list(pool.map(function, items))
