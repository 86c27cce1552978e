"""Ends the local Ray instance of a ``--engine ray`` run when its driver process dies, even by SIGKILL.

``ray.init()`` starts the instance's head processes (gcs_server, raylet, monitors) with
PR_SET_PDEATHSIG on Linux, so the kernel ends them with the driver, and the Ray workers
exit when their raylet is gone; but the raylet's agents (``ray::DashboardAgent``,
``ray::RuntimeEnvAgent``, about 90 MB each) log that the raylet is dead and then take
about a minute to exit (60-62 s in three runs here, apparently waiting on the GCS, dead
too), adopted by PID 1 meanwhile.  On a normal end (or SIGTERM, which the CLI turns into
one) ``ray.shutdown()`` stops them all; this watchdog covers a driver that dies.

:func:`start_watchdog` runs this module as a process of its own session (so a Ctrl-C or
a signal to the driver's process group does not reach it), before ``ray.init()``.  The
watchdog records the driver's Ray processes as they appear, every ``_POLL_S``, and waits
for end-of-file on its stdin, a pipe whose write end only the driver holds: that comes
the moment the driver's process is gone, however it ended.  It then kills the recorded
processes still running.  :func:`stop_watchdog` stands it down after ``ray.shutdown()``.

Standard library and psutil only (found through the driver's ``sys.path``, where Ray
puts the copy it vendors): it must start fast, next to a driver that is importing torch.
"""

from __future__ import annotations

import importlib.util
import os
import select
import subprocess
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported by the watchdog only: shadowcorr_batch.ray_engine, which imports this module, must import without Ray
    import psutil

__all__ = ["start_watchdog", "stop_watchdog"]

# Seconds between two looks at the driver's processes.  A process started less than this
# before the driver dies may be missed; Ray starts its agents with the instance, seconds
# before any scene runs.
_POLL_S = 0.5


def start_watchdog() -> subprocess.Popen[bytes]:
    """Start the watchdog of the Ray instance this process is about to start (call it before ``ray.init()``)."""
    # The driver's import path: this package, and psutil wherever the driver finds it (Ray puts its own copy there).
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    return subprocess.Popen([sys.executable, "-m", __name__, str(os.getpid())], stdin=subprocess.PIPE, env=env,
                            start_new_session=True)


def stop_watchdog(watchdog: subprocess.Popen[bytes]) -> None:
    """Stand the watchdog down once ``ray.shutdown()`` has stopped the instance (it kills nothing then)."""
    watchdog.terminate()
    watchdog.wait()
    assert watchdog.stdin is not None  # started with a pipe
    watchdog.stdin.close()


def _is_ray_process(proc: "psutil.Process", ray_dir: str) -> bool:
    """A process of Ray's (its binaries and scripts, or a worker or agent titled ``ray::...``), not
    any other child a program calling :func:`shadowcorr_batch.ray_engine.run_ray` may have."""
    import psutil

    try:
        cmdline = proc.cmdline()
    except psutil.Error:
        return False
    return bool(cmdline) and (cmdline[0].startswith("ray::") or any(arg.startswith(ray_dir) for arg in cmdline))


def main(argv: list[str]) -> int:
    import psutil

    driver_pid = int(argv[0])
    if os.getppid() != driver_pid:
        return 0  # the driver is gone already, before it started Ray
    spec = importlib.util.find_spec("ray")
    assert spec is not None and spec.submodule_search_locations, "started by the Ray engine"
    ray_dir = spec.submodule_search_locations[0]
    driver = psutil.Process(driver_pid)
    seen: dict[int, psutil.Process] = {}
    # Nothing is ever written to stdin: readable means end-of-file, the driver's end closed.
    while not select.select([sys.stdin], [], [], _POLL_S)[0]:
        try:
            children = driver.children(recursive=True)
        except psutil.NoSuchProcess:
            break
        for proc in children:
            if proc.pid not in seen and _is_ray_process(proc, ray_dir):
                seen[proc.pid] = proc
    for proc in seen.values():
        try:
            proc.kill()  # psutil checks first that the pid is still this process, not a reused one
        except psutil.Error:  # gone already
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
