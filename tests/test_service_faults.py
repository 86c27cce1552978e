"""A hostile or broken client cannot take the service down: a real server on 127.0.0.1, raw sockets.

Covers stalled and slow uploads (no admission slot while the body arrives, 408 below
the minimum rate), slow-loris headers (408 and closed), the connection limit, the byte
budget over bodies in flight and spooling to temporary files, JSON bodies for what
uvicorn / h11 refuse themselves, the OpenAPI limits, archive members the manifest does
not name, the bad-units scene, ``timings_ms.total``, cancelled jobs (worker freed
promptly, slot held until the job has stopped) and the JSON 503 at the shutdown
deadline.  One server serves the module; the last test shuts it down.
"""

from __future__ import annotations

import json
import signal
import socket
import threading
import time

import httpx
import pytest

from .harness import SLOW_SCENE_VIEWS, ServerProcess, add_zeros_member, slow_sample_parts, zip_files, zipped_bundle

from .paths import SAMPLE_DIR

MiB = 1024 * 1024
HEADER_TIMEOUT_S = 2.0
BODY_GRACE_S = 3.0
MIN_RATE = 64 * 1024
BUDGET = 48 * MiB
SPOOL = 64 * 1024
MAX_HEADER = 16 * 1024
MAX_CONNECTIONS = 48
GRACE_S = 1.0
# well under the seconds the slow request still has to run once its client gives up
CANCEL_GRACE_S = 0.3

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def spool_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("spool")


@pytest.fixture(scope="module")
def server(spool_dir):
    srv = ServerProcess(
        [
            "--workers", "1",
            "--queue-size", "4",
            "--max-requests-per-client", "1",
            "--max-wait-ms", "0",
            "--header-timeout-s", str(HEADER_TIMEOUT_S),
            "--body-grace-s", str(BODY_GRACE_S),
            "--min-upload-bytes-per-s", str(MIN_RATE),
            "--max-upload-bytes-in-flight", str(BUDGET),
            "--spool-bytes", str(SPOOL),
            "--max-body-bytes", str(32 * MiB),
            "--max-header-bytes", str(MAX_HEADER),
            "--max-connections", str(MAX_CONNECTIONS),
            "--max-uncompressed-bytes", str(32 * MiB),
            "--cancel-grace-s", str(CANCEL_GRACE_S),
            "--max-views", str(SLOW_SCENE_VIEWS),
            "--graceful-shutdown-s", str(GRACE_S),
            "--retry-after-s", "7",
        ],
        env={"TMPDIR": str(spool_dir)},
    )
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def tiny() -> tuple[bytes, dict, dict]:
    """A small valid scene: (zip bytes, manifest, files)."""
    from shadowcorr_service.synthetic import synthetic_bundle

    return zipped_bundle(synthetic_bundle(n_rocks=3, n_views=3))


@pytest.fixture(scope="module")
def slow_parts():
    """A request that takes seconds of worker CPU (see :func:`~tests.harness.slow_sample_parts`)."""
    if not SAMPLE_DIR.is_dir():
        pytest.skip("sample data not available")
    return slow_sample_parts(SAMPLE_DIR)


def _connect(server: ServerProcess, timeout: float = 30.0) -> socket.socket:
    return socket.create_connection(("127.0.0.1", server.port), timeout=timeout)


def _read_response(sock: socket.socket) -> tuple[int, dict[str, str], dict]:
    """Read until the server closes; (status, headers, JSON body)."""
    data = b""
    while chunk := sock.recv(65536):
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    return int(lines[0].split()[1]), headers, json.loads(body)


def _exchange(server: ServerProcess, raw: bytes) -> tuple[int, dict[str, str], dict]:
    with _connect(server) as sock:
        sock.sendall(raw)
        return _read_response(sock)


def _stalled_upload(server: ServerProcess, declared: int, sent: bytes = b"x" * 100) -> socket.socket:
    """A POST that declares ``declared`` bytes, sends ``sent`` and then nothing."""
    sock = _connect(server)
    sock.sendall(b"POST /correspond HTTP/1.1\r\nHost: x\r\nContent-Type: application/zip\r\n"
                 b"Content-Length: %d\r\n\r\n" % declared + sent)
    return sock


def _health(server: ServerProcess) -> dict:
    return httpx.get(server.url + "/health", timeout=30).json()


def _is_error(body: dict, code: str) -> bool:
    return set(body) == {"error", "message", "problems"} and body["error"] == code


# --------------------------------------------------------------------------- what uvicorn answers itself
def test_protocol_errors_are_json(server):
    status, headers, body = _exchange(server, b"POST /correspond HTTP/1.1\r\nHost: x\r\nContent-Length: lots\r\n\r\n")
    assert status == 400 and headers["content-type"] == "application/json" and _is_error(body, "bad_request"), body
    assert "content-length" in body["message"].lower()
    status, _, body = _exchange(server, b"GARBAGE\r\n\r\n")
    assert status == 400 and _is_error(body, "bad_request"), body
    # a header over the limit, arriving in pieces (h11 refuses it before it is complete)
    with _connect(server) as sock:
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\nX-Big: ")
        try:
            for _ in range(4 * MAX_HEADER // 1024):
                sock.sendall(b"a" * 1024)
                time.sleep(0.001)
        except OSError:
            pass  # closed by the server mid-send: the answer is already there
        status, _, body = _read_response(sock)
    assert status == 431 and _is_error(body, "headers_too_large") and "max_header_bytes" in body["message"], body
    # a query string over the limit, arriving in one piece (measured by the application)
    status, _, body = _exchange(server, b"GET /health?" + b"q" * (2 * MAX_HEADER) + b" HTTP/1.1\r\nHost: x\r\n\r\n")
    assert status == 431 and _is_error(body, "headers_too_large"), body
    assert _health(server)["ready"]


def test_openapi_documents_the_limits(server):
    spec = httpx.get(server.url + "/openapi.json").json()
    post = spec["paths"]["/correspond"]["post"]
    params = {p["name"]: p["schema"] for p in post["parameters"]}
    assert params["bandwidth"]["exclusiveMinimum"] == 0 and params["min_cluster_size"]["minimum"] == 1
    assert params["min_blob_pixels"]["minimum"] == 0
    form = post["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert [s["required"] for s in form["oneOf"]] == [["bundle"], ["manifest"]]
    assert all(s["additionalProperties"] is False for s in form["oneOf"])
    assert {"400", "401", "408", "413", "415", "422", "429", "431", "500", "503", "504"} <= set(post["responses"])
    assert "Retry-After" in post["responses"]["503"]["headers"]
    # refused up front (before a byte of the body is read), as the schema says
    for value, needle in (("inf", "finite"), ("nan", "finite"), ("-inf", "finite"), ("0", "greater than 0")):
        r = httpx.post(server.url + "/correspond", params={"bandwidth": value}, content=b"x",
                       headers={"Content-Type": "application/zip"})
        assert r.status_code == 422 and "bandwidth" in r.text and needle in r.text, (value, r.text)


# --------------------------------------------------------------------------- slow clients
def test_slow_loris_headers_are_cut_off(server):
    """One header byte every 0.2 s: 408 and closed after header_timeout_s (the issue's limit: 10 s)."""
    start = time.monotonic()
    with _connect(server) as sock:
        request = b"GET /health HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"z" * 200
        try:
            for byte in request:
                sock.sendall(bytes([byte]))
                time.sleep(0.2)
        except OSError:
            pass
        status, headers, body = _read_response(sock)
    elapsed = time.monotonic() - start
    assert status == 408 and _is_error(body, "header_timeout") and headers["connection"] == "close", body
    assert elapsed < 10.0, elapsed
    # also on a kept-alive connection, for the next request's headers
    with _connect(server) as sock:
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n")
        first = sock.recv(65536)
        assert first.startswith(b"HTTP/1.1 200")
        sock.sendall(b"GET /hea")
        status, _, body = _read_response(sock)
    assert status == 408 and _is_error(body, "header_timeout")


def test_connection_limit(server):
    socks = [_connect(server) for _ in range(MAX_CONNECTIONS)]
    try:
        status, headers, body = _exchange(server, b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n")
    finally:
        for s in socks:
            s.close()
    assert status == 503 and _is_error(body, "too_many_connections") and headers["retry-after"] == "7", body
    time.sleep(0.3)
    assert _health(server)["ready"]


def test_stalled_uploads_hold_no_admission_slot(server, tiny):
    """32 uploads that declare 1 MB and stall: a valid request still gets 200; they get 408."""
    zipped, _, _ = tiny
    stalled = [_stalled_upload(server, 1_000_000) for _ in range(32)]
    try:
        time.sleep(0.3)
        assert _health(server)["queue_depth"] == 0  # the queue holds 4; none is taken by an upload
        for s in stalled:
            s.setblocking(False)
            with pytest.raises(BlockingIOError):
                s.recv(1)  # not answered yet: the uploads are still open while the valid request runs
            s.setblocking(True)
        t0 = time.monotonic()
        r = httpx.post(server.url + "/correspond", files={"bundle": ("s.zip", zipped)}, timeout=60)
        latency = time.monotonic() - t0
        assert r.status_code == 200, r.text
        print(f"valid request with 32 stalled uploads open: {latency * 1e3:.0f} ms")
        answers = [_read_response(s) for s in stalled]
    finally:
        for s in stalled:
            s.close()
    assert all(status == 408 and _is_error(body, "body_timeout") for status, _, body in answers), answers[0]
    assert "min_upload_bytes_per_s" in answers[0][2]["message"]


def test_large_bodies_are_spooled_and_budgeted(server, spool_dir):
    # an upload over spool_bytes goes to a file in the server's spool directory while it arrives ...
    first = _stalled_upload(server, 30 * MiB, sent=b"\0" * (4 * SPOOL))
    try:
        def spooled_bytes() -> int:  # the file appears before the server has written all it received
            files = list(spool_dir.glob("shadowcorr-spool-*/shadowcorr-upload-*"))
            try:
                return sum(f.stat().st_size for f in files)
            except FileNotFoundError:
                return 0

        deadline = time.monotonic() + 10
        while spooled_bytes() < 4 * SPOOL and time.monotonic() < deadline:
            time.sleep(0.05)
        assert spooled_bytes() >= 4 * SPOOL
        # ... and holds 30 MiB of the 48 MiB budget: a second 20 MiB upload is refused
        status, headers, body = _exchange(server, b"POST /correspond HTTP/1.1\r\nHost: x\r\nContent-Type: "
                                          b"application/zip\r\nContent-Length: %d\r\n\r\n" % (20 * MiB))
        assert status == 503 and _is_error(body, "overloaded") and headers["retry-after"] == "7", body
        assert "max_upload_bytes_in_flight" in body["message"]
        status, _, body = _read_response(first)  # then it stalls: 408, and its file is deleted
        assert status == 408 and _is_error(body, "body_timeout"), body
    finally:
        first.close()
    assert not list(spool_dir.glob("shadowcorr-spool-*/shadowcorr-upload-*"))
    text = httpx.get(server.url + "/metrics").text
    assert "shadowcorr_upload_bytes_in_flight 0.0" in text


# --------------------------------------------------------------------------- scenes and archives
def test_bad_units_are_refused_naming_units_and_max_depth(server, tiny):
    _, manifest, files = tiny
    wrong = dict(manifest, units="m")  # a centimetre scene declared in metres: every depth beyond max_depth
    r = httpx.post(server.url + "/correspond", files={"bundle": ("s.zip", zip_files({"manifest.json": json.dumps(wrong).encode(),
                                                                                 **files}))}, timeout=60)
    assert r.status_code == 422 and r.json()["error"] == "no_valid_depth", r.text
    assert "units" in r.json()["message"] and "max_depth" in r.json()["message"]


def test_archive_members_the_manifest_does_not_name_are_never_decompressed(server, tiny):
    zipped, manifest, files = tiny
    # 256 MiB of zeros (~250 KiB compressed, 1000:1) beside the bundle, over the 32 MiB limit
    padded = add_zeros_member(zipped, 256, "extra/padding.bin")
    r = httpx.post(server.url + "/correspond", files={"bundle": ("s.zip", padded)}, timeout=60)
    assert r.status_code == 200, r.text
    assert any("extra/padding.bin" in w for w in r.json()["warnings"]), r.json()["warnings"]


def test_timings_total_covers_the_whole_request(server, tiny):
    zipped, _, _ = tiny
    r = httpx.post(server.url + "/correspond", files={"bundle": ("s.zip", zipped)}, timeout=60)
    assert r.status_code == 200, r.text
    t = r.json()["timings_ms"]
    assert {"read_body", "decode", "batch_wait", "network", "grouping", "total"} <= set(t)
    parts = sum(v for k, v in t.items() if k != "total")
    assert t["total"] >= parts - 1.0, t  # every stage is inside the wall time (1 ms of rounding)


# --------------------------------------------------------------------------- cancellation and shutdown
def test_cancelled_job_frees_its_worker_and_holds_its_slot_until_stopped(server, slow_parts):
    restarts = _health(server)["workers"]["restarts"]
    (worker,) = server.worker_processes()
    base = sum(worker.cpu_times()[:2])
    done: dict = {}

    def post() -> None:
        try:
            httpx.post(server.url + "/correspond", files=slow_parts, timeout=httpx.Timeout(60.0, read=0.5))
        except httpx.ReadTimeout:  # the client gives up once the worker is busy
            done["gave_up"] = time.monotonic()

    t = threading.Thread(target=post)
    t.start()
    while sum(worker.cpu_times()[:2]) - base < 0.1 and t.is_alive():
        time.sleep(0.02)
    t.join(60)
    assert "gave_up" in done
    # the job still runs after the disconnect: its slot stays taken ...
    assert _health(server)["queue_depth"] == 1
    # ... until its worker is killed, cancel_grace_s later, and replaced
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        h = _health(server)
        if h["queue_depth"] == 0 and h["workers"]["restarts"] == restarts + 1:
            break
        time.sleep(0.1)
    assert h["queue_depth"] == 0 and h["workers"]["restarts"] == restarts + 1, h
    assert not worker.is_running()
    while _health(server)["workers"]["ready"] < 1 and time.monotonic() < deadline:
        time.sleep(0.2)


def test_shutdown_answers_json_503_to_what_cannot_finish(server, slow_parts, tiny):
    """Last test of the module: SIGTERM with a long request running and an upload stalled (and per-client fairness)."""
    while _health(server)["workers"]["ready"] < 1:
        time.sleep(0.2)
    (worker,) = server.worker_processes()
    base = sum(worker.cpu_times()[:2])
    result: dict = {}

    def post() -> None:
        result["r"] = httpx.post(server.url + "/correspond", files=slow_parts, timeout=60)

    t = threading.Thread(target=post)
    t.start()
    while sum(worker.cpu_times()[:2]) - base < 0.1 and t.is_alive():
        time.sleep(0.02)
    # one client may hold one of the 4 slots here (max_requests_per_client 1): a second request gets 429
    zipped, _, _ = tiny
    busy = httpx.post(server.url + "/correspond", files={"bundle": ("s.zip", zipped)}, timeout=60)
    assert busy.status_code == 429 and busy.headers["retry-after"] == "7", busy.text
    assert busy.json()["error"] == "too_many_requests" and "max_requests_per_client" in busy.json()["message"]
    # an upload that trickles just fast enough to stay open past the grace period
    upload = _stalled_upload(server, 10_000, sent=b"\0" * 4000)
    time.sleep(0.1)
    sent_at = time.monotonic()
    server.proc.send_signal(signal.SIGTERM)
    t.join(60)
    status, headers, body = _read_response(upload)
    upload.close()
    r = result["r"]
    assert r.status_code == 503 and r.headers["retry-after"] == "7", r.text
    assert r.json()["error"] == "shutting_down" and "graceful_shutdown_s" in r.json()["message"]
    assert status == 503 and _is_error(body, "shutting_down") and headers["retry-after"] == "7", body
    assert time.monotonic() - sent_at < GRACE_S + 10
    assert server.proc.wait(60) in (0, -signal.SIGTERM)
    assert "Application shutdown complete" in server.log_tail()
    assert "Traceback" not in server.log_tail(400)


def test_a_stage_over_its_time_budget_is_refused_and_the_server_keeps_serving(tiny):
    # A budget no stage can meet: every scene is refused after its first stage, with a 413
    # naming the limit and the stage; the worker stays up and /health stays ready.
    zipped, _, _ = tiny
    with ServerProcess(["--workers", "1", "--max-wait-ms", "0"], env={"SHADOWCORR_MAX_STAGE_SECONDS": "1e-6"}) as srv:
        for _ in range(2):
            r = httpx.post(srv.url + "/correspond", files={"bundle": ("s.zip", zipped)}, timeout=60)
            assert r.status_code == 413 and _is_error(r.json(), "stage_too_slow"), r.text
            assert "max_stage_seconds" in r.json()["message"] and "stage '" in r.json()["message"]
        assert _health(srv)["status"] == "ok"
