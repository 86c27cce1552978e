"""A real server's start and end: answers on kept-alive connections after SIGTERM, spool
directories that crashed servers left behind, no open server on a public address by
mistake, and what ``/info`` and error messages must not reveal (file-system paths,
Python object reprs).

One server (on 0.0.0.0, allowed without a token, with a model file given by path) serves
the tests that only talk to it; the others start servers of their own.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path

import httpx
import pytest

from .harness import REPO_ROOT, SLOW_SCENE_VIEWS, ServerProcess, slow_sample_parts, zip_files, zipped_bundle
from .paths import SAMPLE_DIR

MiB = 1024 * 1024
RETRY_AFTER_S = 7

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def model_file(tmp_path_factory) -> Path:
    """The packaged model, copied to an absolute path that /info must not show."""
    from shadowcorr.nn import load_model

    path = tmp_path_factory.mktemp("models") / "rocks.safetensors"
    shutil.copyfile(load_model(None).path, path)
    return path


@pytest.fixture(scope="module")
def server(model_file):
    with ServerProcess(["--host", "0.0.0.0", "--workers", "1", "--model", str(model_file)],
                       env={"SHADOWCORR_ALLOW_NO_AUTH": "1"}) as srv:
        yield srv


@pytest.fixture(scope="module")
def tiny() -> tuple[bytes, dict, dict]:
    """A small valid scene: (zip bytes, manifest, files)."""
    from shadowcorr_service.synthetic import synthetic_bundle

    return zipped_bundle(synthetic_bundle(n_rocks=2, n_views=2, width=96, height=72))


def _read_one(sock: socket.socket) -> tuple[int, dict[str, str], dict]:
    """One response from a kept-alive connection (it need not close): (status, headers, JSON body)."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionError(f"the server closed the connection without an answer (got {data!r})")
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    while len(body) < int(headers["content-length"]):
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionError("the server closed the connection mid-answer")
        body += chunk
    return int(lines[0].split()[1]), headers, json.loads(body)


def _spooled(tmp: Path) -> list[Path]:
    return sorted(tmp.glob("shadowcorr-spool-*/shadowcorr-upload-*"))


def _stalled_upload(server: ServerProcess, tmp: Path, before: list[Path]) -> tuple[socket.socket, Path]:
    """A 4 MiB upload that sends 256 KiB (over spool_bytes) and stalls; its spool file, once written."""
    sock = socket.create_connection(("127.0.0.1", server.port), timeout=30)
    sock.sendall(b"POST /correspond HTTP/1.1\r\nHost: x\r\nContent-Type: application/zip\r\n"
                 b"Content-Length: %d\r\n\r\n" % (4 * MiB) + b"\0" * (256 * 1024))
    deadline = time.monotonic() + 30
    while not (new := [p for p in _spooled(tmp) if p not in before]) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert new, f"no spool file appeared in {tmp}: {list(tmp.iterdir())}"
    return sock, new[0]


# --------------------------------------------------------------------------- shutdown
def test_requests_on_kept_alive_connections_get_503_during_the_grace_period():
    if not SAMPLE_DIR.is_dir():
        pytest.skip("sample data not available")
    parts = slow_sample_parts(SAMPLE_DIR)
    srv = ServerProcess(["--workers", "1", "--max-views", str(SLOW_SCENE_VIEWS), "--graceful-shutdown-s", "60",
                         "--retry-after-s", str(RETRY_AFTER_S), "--header-timeout-s", "30", "--keep-alive-s", "30"])
    with srv, socket.create_connection(("127.0.0.1", srv.port), timeout=30) as kept:
        kept.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n")
        status, headers, _ = _read_one(kept)
        assert status == 200 and headers.get("connection") != "close"

        (worker,) = srv.worker_processes()
        base = sum(worker.cpu_times()[:2])
        result: dict = {}

        def slow() -> None:
            with httpx.Client(timeout=120) as client:
                result["r"] = client.post(srv.url + "/correspond", files=parts)

        t = threading.Thread(target=slow)
        t.start()
        while sum(worker.cpu_times()[:2]) - base < 0.1 and t.is_alive():
            time.sleep(0.02)
        srv.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 30
        while "Shutting down" not in srv.log_tail() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert "Shutting down" in srv.log_tail()  # uvicorn has shut every connection down by now

        kept.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n")
        status, headers, body = _read_one(kept)
        assert status == 503 and body["error"] == "shutting_down", body
        assert set(body) == {"error", "message", "problems"}
        assert headers["retry-after"] == str(RETRY_AFTER_S) and headers["connection"] == "close", headers
        assert kept.recv(1) == b""  # and the server closed it

        t.join(120)
        r = result["r"]  # the request in flight finishes within the grace period, closing its connection
        assert r.status_code == 200 and r.headers["connection"] == "close", r.text[:300]
        assert srv.proc.wait(60) in (0, -signal.SIGTERM)
    assert "Application shutdown complete" in srv.log_tail()
    assert "Traceback" not in srv.log_tail(400)


# --------------------------------------------------------------------------- spool directories
def test_spool_directories_of_dead_servers_are_removed_at_start(tmp_path):
    """A SIGKILLed server's half-received body is removed by the next server to start; a live server's is not."""
    args = ["--workers", "1", "--spool-bytes", str(64 * 1024), "--body-grace-s", "120"]
    env = {"TMPDIR": str(tmp_path)}
    crashed = ServerProcess(args, env).start()
    try:
        sock, stale = _stalled_upload(crashed, tmp_path, [])
        crashed.proc.send_signal(signal.SIGKILL)
        crashed.proc.wait(30)
        sock.close()
    finally:
        crashed.stop()  # its worker processes
    assert stale.exists()  # nothing removes it at the crash itself

    with ServerProcess(args, env) as live:
        sock, held = _stalled_upload(live, tmp_path, [stale])
        try:
            assert not stale.parent.exists(), list(tmp_path.iterdir())
            with ServerProcess(args, env):  # a third server on the same temporary directory
                assert held.exists()  # the running server's upload is left alone
        finally:
            sock.close()
    assert not list(tmp_path.glob("shadowcorr-spool-*")), list(tmp_path.iterdir())  # clean exits leave nothing


# --------------------------------------------------------------------------- no open server by mistake
def test_a_public_address_needs_a_token_or_an_explicit_opt_out(server):
    env = {k: v for k, v in os.environ.items() if not k.startswith("SHADOWCORR_")}
    r = subprocess.run([sys.executable, "-m", "shadowcorr_service", "--host", "0.0.0.0", "--port", "0"], cwd=REPO_ROOT,
                       env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr[-2000:]
    assert "SHADOWCORR_AUTH_TOKEN" in r.stderr and "SHADOWCORR_ALLOW_NO_AUTH=1" in r.stderr, r.stderr[-2000:]
    assert "Started server process" not in r.stderr
    # the module's server listens on every interface with SHADOWCORR_ALLOW_NO_AUTH=1, reached here via loopback
    info = httpx.get(server.url + "/info", timeout=30).json()
    assert info["settings"]["host"] == "0.0.0.0" and info["settings"]["allow_no_auth"] is True
    assert info["settings"]["auth"] == "none"


# --------------------------------------------------------------------------- what answers must not reveal
def test_info_shows_no_file_system_paths(server, model_file):
    info = httpx.get(server.url + "/info", timeout=30).json()
    strings: list[str] = []

    def walk(value) -> None:
        if isinstance(value, dict):
            strings.extend(value)
            for v in value.values():
                walk(v)
        elif isinstance(value, list):
            for v in value:
                walk(v)
        elif isinstance(value, str):
            strings.append(value)

    walk(info)
    absolute = re.compile(r"(?:^|[\s=('\"])(?:/\w|[A-Za-z]:[\\/])")
    assert not [s for s in strings if absolute.search(s)]
    text = json.dumps(info)
    for leak in (str(REPO_ROOT), str(model_file.parent), "site-packages", "/tmp/"):
        assert leak not in text, leak
    # the model is named instead
    assert info["model"]["name"] and info["model"]["version"] and len(info["model"]["sha256"]) == 64
    assert info["model"]["packaged"] is False and info["model"]["card"]["units"] == "cm"


def _png_with_ihdr(width: int, height: int, bit_depth: int, colour_type: int) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b"")


def test_error_messages_show_no_python_reprs(server, tiny):
    zipped, manifest, files = tiny
    view = manifest["views"][0]
    mask_key, depth_key = view["mask"]["file"], view["depth"]["file"]

    def parts(m: object, fs: dict[str, bytes]) -> list:
        return [("manifest", (None, json.dumps(m).encode()))] + [("f", (k, v)) for k, v in fs.items()]

    def changed(change) -> dict:
        m = json.loads(json.dumps(manifest))
        change(m)
        return m

    w, h = view["intrinsics"]["width"], view["intrinsics"]["height"]
    cases = {
        # colour type 7 does not exist: Pillow cannot identify the image and names its file object
        "invalid png header": {"files": parts(manifest, {**files, mask_key: _png_with_ihdr(w, h, 8, 7)})},
        "corrupt exr": {"files": parts(manifest, {**files, depth_key: b"\x76\x2f\x31\x01" + b"\xff" * 200})},
        "garbage npy": {"files": parts(changed(lambda m: m["views"][0]["mask"].update(file="m.npy", format="npy")),
                                       {**files, "m.npy": b"\x93NUMPY\x01\x00garbage"})},
        "wrong type in a manifest field": {"files": parts(changed(lambda m: m["views"][0].update(pose=[1, 2])), files)},
        "manifest a list": {"files": parts([manifest], files)},
        "not a zip": {"files": {"bundle": ("a.zip", b"PK\x03\x04" + b"\0" * 64)}},
        "not a tar": {"content": b"\x1f\x8b" + b"\0" * 64, "headers": {"Content-Type": "application/x-tar"}},
        "zip without manifest": {"files": {"bundle": ("a.zip", zip_files(files))}},
        "option of a wrong type": {"params": {"min_cluster_size": "[1]", "refine_poses": "{}"},
                                   "files": {"bundle": ("a.zip", zipped)}},
        "unknown route": {"url": "/correspond/x"},
    }
    reprs = re.compile(r"0x[0-9a-f]{6,}|<[^<>]* object at ")
    failures = []
    for name, kwargs in cases.items():
        url = server.url + kwargs.pop("url", "/correspond")
        r = httpx.post(url, timeout=60, **kwargs)
        if not 400 <= r.status_code < 500 or "error" not in r.json():
            failures.append(f"{name}: {r.status_code} {r.text[:300]}")
        elif reprs.search(r.text):
            failures.append(f"{name}: {r.text[:500]}")
    assert not failures, "\n".join(failures)
