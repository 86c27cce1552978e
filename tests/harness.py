"""The one test harness of the tests and the benchmarks: a real service process, free ports, zip bytes.

:class:`ServerProcess` runs ``python -m shadowcorr_service`` on a free loopback port in its own
process group.  Only the standard library and httpx at import time; ``psutil`` (a dev
dependency) is imported when worker processes are looked up.  The benchmarks import this
module as ``tests.harness`` (they put the repository root on ``sys.path``).
"""

from __future__ import annotations

import io
import json
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Any, Mapping, Sequence

import httpx

__all__ = ["ServerProcess", "free_port", "REPO_ROOT", "add_zeros_member", "load_bench_quality", "load_benchmark",
           "zip_files", "zipped_bundle"]

REPO_ROOT = Path(__file__).resolve().parent.parent
MiB = 1024 * 1024


def load_benchmark(name: str) -> Any:
    """``benchmarks/NAME.py`` as a module (the benchmarks are scripts, not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO_ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve their annotations through it
    spec.loader.exec_module(module)
    return module


def load_bench_quality() -> Any:
    """``benchmarks/bench_quality.py`` as a module."""
    return load_benchmark("bench_quality")


def free_port() -> int:
    """A TCP port that was free a moment ago on 127.0.0.1."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ServerProcess:
    """``python -m shadowcorr_service`` as a subprocess; ``start()`` waits until ``/health`` is 200.

    ``args`` are extra command-line flags (``["--workers", "2"]``); ``env`` adds
    environment variables.  ``SHADOWCORR_*`` variables of the calling environment are
    dropped, so the server runs with exactly the settings given here.  ``token`` goes into
    :attr:`headers`; with ``auth`` the server is also started requiring it.  ``start()`` is
    ``launch()`` then ``wait_ready()``: launch several servers first to start them at once.
    ``command`` replaces ``python -m shadowcorr_service`` (e.g. ``shadowcorr serve``); ``cwd``
    is the working directory (the repository by default).
    """

    def __init__(
        self,
        args: Sequence[str] = (),
        env: Mapping[str, str] | None = None,
        *,
        python: str | None = None,
        log_path: str | Path | None = None,
        token: str | None = None,
        auth: bool = False,
        command: Sequence[str] | None = None,
        cwd: str | Path | None = None,
    ) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.args = list(args)
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("SHADOWCORR_")}
        self.env.update(env or {})
        self.python = python or sys.executable
        self.command = list(command) if command else [self.python, "-m", "shadowcorr_service"]
        self.cwd = Path(cwd) if cwd else REPO_ROOT
        self.token = token
        if auth and token:
            self.env["SHADOWCORR_AUTH_TOKEN"] = token
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
        self.launch()
        return self.wait_ready(timeout)

    def launch(self) -> None:
        """Start the process (in a session of its own, so that ``stop`` can end its workers too)."""
        cmd = [*self.command, "--host", "127.0.0.1", "--port", str(self.port), *self.args]
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(cmd, cwd=self.cwd, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                         start_new_session=True)

    def wait_ready(self, timeout: float = 300.0) -> "ServerProcess":
        """Wait until ``/health`` is 200; the log's tail in the error when the server exits or times out."""
        assert self.proc is not None, "not launched"
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

    def requests(self, route: str = "/correspond") -> dict[str, int]:
        """Requests served so far on ``route``, by status code (from ``/metrics``)."""
        text = httpx.get(self.url + "/metrics", headers=self.headers, timeout=10).text
        counts: dict[str, int] = {}
        pattern = re.compile(r'^shadowcorr_http_requests_total\{(.*)\} ([0-9.e+]+)$')
        for line in text.splitlines():
            m = pattern.match(line)
            if not m:
                continue
            labels = dict(re.findall(r'(\w+)="([^"]*)"', m.group(1)))
            if labels.get("route") == route:
                counts[labels["status"]] = counts.get(labels["status"], 0) + int(float(m.group(2)))
        return counts

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
        """SIGTERM (graceful), then SIGKILL after ``timeout``, and of any process left in its group; the exit code."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)  # its own group: leftover workers, if any
        except (ProcessLookupError, PermissionError):
            pass
        return self.proc.returncode

    def __enter__(self) -> "ServerProcess":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def zip_files(files: Mapping[str, bytes], compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    """The bytes of a zip archive holding ``files`` (name -> content)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=compression) as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    return buf.getvalue()


def add_zeros_member(zipped: bytes, mib: int, name: str = "extra/padding.bin") -> bytes:
    """``zipped`` with one more member of ``mib`` MiB of zeros (deflated about 1000:1), written in 1 MiB pieces."""
    buf = io.BytesIO(zipped)
    with zipfile.ZipFile(buf, "a", zipfile.ZIP_DEFLATED) as zf:
        with zf.open(name, "w", force_zip64=True) as member:
            zero = bytes(MiB)
            for _ in range(mib):
                member.write(zero)
    return buf.getvalue()


def zipped_bundle(bundle: Any) -> tuple[bytes, dict, dict[str, bytes]]:
    """A :class:`~shadowcorr.bundle.SceneBundle` as an uploadable zip: (zip bytes, manifest, files)."""
    from shadowcorr.io import bundle_to_parts

    manifest, files = bundle_to_parts(bundle)
    return zip_files({"manifest.json": json.dumps(manifest).encode(), **files}), manifest, files


#: Views in :func:`slow_sample_parts`; servers that take it need ``--max-views`` this high.
SLOW_SCENE_VIEWS = 24


def slow_sample_parts(sample_dir: Path) -> list[tuple[str, tuple[str | None, bytes]]]:
    """Multipart parts of a request that keeps a worker busy for seconds (about 3.5 s on one
    idle core of the 2-core CI machine): the sample's 8 cameras, each view three times.

    Tests that need a job still running after a timeout or a disconnect use it with grace
    periods well under that, so that it outlasts them on a faster machine too.
    """
    import dataclasses

    from shadowcorr.convert.ue import load_ue_scene
    from shadowcorr.io import bundle_to_parts

    bundle = load_ue_scene(sample_dir, 2001, range(8))
    copies = SLOW_SCENE_VIEWS // len(bundle.views)
    bundle.views += [dataclasses.replace(v, name=f"{v.name}_{k}") for k in range(2, copies + 1) for v in bundle.views]
    manifest, files = bundle_to_parts(bundle)
    return [("manifest", (None, json.dumps(manifest).encode()))] + [("f", (k, v)) for k, v in files.items()]
