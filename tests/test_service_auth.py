"""HTTP service with a bearer token, one worker and tight limits: auth, overload (503), timeout (504).

The main service tests (``test_service.py``) run without a token: every route is open there.
"""

from __future__ import annotations

import threading
import time

import httpx
import pytest

from .harness import SLOW_SCENE_VIEWS, ServerProcess, slow_sample_parts, zipped_bundle

from .paths import SAMPLE_DIR

TOKEN = "s3cret-token-for-tests"
#: The slow scene (harness.slow_sample_parts) takes about 1 s on a fast 2-core machine: the timeout
#: plus the grace must stay well under that, or the job ends before its worker is killed.
TIMEOUT_S = 0.5
#: A timed-out job's worker is killed this long after the timeout.
CANCEL_GRACE_S = 0.1


@pytest.fixture(scope="module")
def server():
    srv = ServerProcess(
        ["--workers", "1", "--queue-size", "1", "--request-timeout-s", str(TIMEOUT_S), "--max-wait-ms", "0",
         "--retry-after-s", "3", "--cancel-grace-s", str(CANCEL_GRACE_S), "--max-views", str(SLOW_SCENE_VIEWS)],
        env={"SHADOWCORR_AUTH_TOKEN": TOKEN},
        token=TOKEN,
    )
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def tiny():
    """A very small valid scene as a zip (answers well within the 1 s timeout)."""
    from shadowcorr_service.synthetic import synthetic_bundle

    return zipped_bundle(synthetic_bundle(n_rocks=2, n_views=2, width=96, height=72))[0]


def test_bearer_token_guards_everything_but_health(server, tiny):
    url = server.url
    ok = {"Authorization": f"Bearer {TOKEN}"}
    assert httpx.get(url + "/health").status_code == 200
    for path in ("/info", "/metrics", "/openapi.json", "/docs", "/nope"):
        r = httpx.get(url + path)
        assert r.status_code == 401, path
        assert r.json()["error"] == "unauthorized" and "bearer" in r.json()["message"].lower()
        assert r.headers["www-authenticate"].startswith("Bearer")
        assert httpx.get(url + path, headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert httpx.get(url + path, headers={"Authorization": TOKEN}).status_code == 401
    r = httpx.post(url + "/correspond", files={"bundle": ("s.zip", tiny)})
    assert r.status_code == 401
    info = httpx.get(url + "/info", headers=ok)
    assert info.status_code == 200 and info.json()["settings"]["auth"] == "bearer"
    assert TOKEN not in info.text
    assert httpx.get(url + "/info", headers={"Authorization": f"bearer {TOKEN}"}).status_code == 200
    assert httpx.get(url + "/metrics", headers=ok).status_code == 200
    r = httpx.post(url + "/correspond", files={"bundle": ("s.zip", tiny)}, headers=ok, timeout=60)
    assert r.status_code == 200, r.text
    assert len(r.json()["segments"]) >= 2


def test_overload_gets_503_and_slow_request_gets_504(server, tiny):
    if not SAMPLE_DIR.is_dir():
        pytest.skip("sample data not available")
    # seconds of work, beyond the 1 s timeout plus the 0.2 s a timed-out job may still run
    # before its worker is killed
    parts = slow_sample_parts(SAMPLE_DIR)
    ok = {"Authorization": f"Bearer {TOKEN}"}
    result: dict = {}

    def slow() -> None:
        result["r"] = httpx.post(server.url + "/correspond", files=parts, headers=ok, timeout=60)

    (worker,) = server.worker_processes()
    base = sum(worker.cpu_times()[:2])
    t = threading.Thread(target=slow)
    t.start()
    while sum(worker.cpu_times()[:2]) - base < 0.1 and t.is_alive():
        time.sleep(0.02)
    busy = httpx.post(server.url + "/correspond", files={"bundle": ("s.zip", tiny)}, headers=ok, timeout=60)
    t.join(60)
    assert busy.status_code == 503, busy.text
    assert busy.json()["error"] == "overloaded" and busy.headers["retry-after"] == "3"
    r = result["r"]
    assert r.status_code == 504, r.text
    assert r.json()["error"] == "timeout" and f"{TIMEOUT_S:g} s" in r.json()["message"]

    # The timed-out job's worker was stopped and replaced; the service recovers by itself.
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        h = httpx.get(server.url + "/health").json()
        if h["workers"]["ready"] == 1 and h["workers"]["restarts"] >= 1:
            break
        time.sleep(0.5)
    assert h["workers"]["restarts"] == 1 and h["ready"], h
    r = httpx.post(server.url + "/correspond", files={"bundle": ("s.zip", tiny)}, headers=ok, timeout=60)
    assert r.status_code == 200, r.text
    assert httpx.get(server.url + "/health").json()["queue_depth"] == 0


def test_settings_from_env_and_flags(monkeypatch):
    from shadowcorr_service.cli import build_parser, settings_from_args
    from shadowcorr_service.settings import ServiceSettings

    monkeypatch.setenv("SHADOWCORR_WORKERS", "5")
    monkeypatch.setenv("SHADOWCORR_MAX_WAIT_MS", "25")
    monkeypatch.setenv("SHADOWCORR_AUTH_TOKEN", "")
    s = settings_from_args(build_parser().parse_args(["--max-wait-ms", "7", "--port", "9000"]))
    assert (s.workers, s.max_wait_ms, s.port, s.auth_token) == (5, 7.0, 9000, None)
    assert ServiceSettings().public_dict()["auth"] == "none"
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match=r"workers\n.*greater than or equal to 1"):
        settings_from_args(build_parser().parse_args(["--workers", "0"]))


def test_bad_model_or_setting_fails_fast(tmp_path):
    """A container must crash loudly on a bad model file or setting, not serve 503s forever."""
    import subprocess
    import sys

    from .harness import REPO_ROOT

    env = {k: v for k, v in __import__("os").environ.items() if not k.startswith("SHADOWCORR_")}
    bad = tmp_path / "model.safetensors"
    bad.write_bytes(b"not a model")
    r = subprocess.run([sys.executable, "-m", "shadowcorr_service", "--port", "0", "--model", str(bad)], cwd=REPO_ROOT,
                       env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and "model.safetensors" in r.stderr, r.stderr[-2000:]
    r = subprocess.run([sys.executable, "-m", "shadowcorr_service"], cwd=REPO_ROOT, env={**env, "SHADOWCORR_WORKERS": "zero"},
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "workers" in r.stderr, r.stderr[-2000:]
