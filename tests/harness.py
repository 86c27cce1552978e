"""Run a real service process for tests and benchmarks (``python -m service`` on a free port).

Only the standard library and httpx at import time; ``psutil`` (a dev dependency) is
imported when worker processes are looked up.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import httpx

__all__ = ["ServerProcess", "free_port", "REPO_ROOT"]

REPO_ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    """A TCP port that was free a moment ago on 127.0.0.1."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ServerProcess:
    """``python -m service`` as a subprocess; ``start()`` waits until ``/health`` is 200.

    ``args`` are extra command-line flags (``["--workers", "2"]``); ``env`` adds
    environment variables.  ``SHADOWCORR_*`` variables of the calling environment are
    dropped, so the server runs with exactly the settings given here.
    """

    def __init__(
        self,
        args: Sequence[str] = (),
        env: Mapping[str, str] | None = None,
        *,
        python: str | None = None,
        log_path: str | Path | None = None,
        token: str | None = None,
    ) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.args = list(args)
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("SHADOWCORR_")}
        self.env.update(env or {})
        self.python = python or sys.executable
        self.token = token
        if log_path is None:
            fd, name = tempfile.mkstemp(prefix="shadowcorr-service-", suffix=".log")
            os.close(fd)
            log_path = name
        self.log_path = Path(log_path)
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def pid(self) -> int:
        assert self.proc is not None, "not started"
        return self.proc.pid

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"} if self.token else {}

    def start(self, timeout: float = 300.0) -> "ServerProcess":
        cmd = [self.python, "-m", "service", "--host", "127.0.0.1", "--port", str(self.port), *self.args]
        log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(cmd, cwd=REPO_ROOT, env=self.env, stdout=log, stderr=subprocess.STDOUT)
        log.close()
        deadline = time.monotonic() + timeout
        with httpx.Client(timeout=5.0) as client:
            while time.monotonic() < deadline:
                if self.proc.poll() is not None:
                    raise RuntimeError(f"server exited with {self.proc.returncode}:\n{self.log_tail()}")
                try:
                    if client.get(self.url + "/health").status_code == 200:
                        return self
                except httpx.HTTPError:
                    pass
                time.sleep(0.25)
        self.stop()
        raise TimeoutError(f"server not ready after {timeout:.0f} s:\n{self.log_tail()}")

    def log_tail(self, n: int = 60) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return "(no log)"

    def worker_processes(self) -> list[Any]:
        """psutil.Process objects of the worker processes (spawned children, not the resource tracker)."""
        import psutil

        out = []
        for child in psutil.Process(self.pid).children(recursive=False):
            try:
                cmd = " ".join(child.cmdline())
            except psutil.Error:
                continue
            if "multiprocessing.spawn" in cmd or "spawn_main" in cmd:
                if "resource_tracker" not in cmd:
                    out.append(child)
        return out

    def stop(self, timeout: float = 60.0) -> int | None:
        """SIGTERM (graceful), then SIGKILL after ``timeout``; returns the exit code."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        return self.proc.returncode

    def __enter__(self) -> "ServerProcess":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
