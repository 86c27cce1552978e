"""Uploads that cost far more than their size are refused before they cost it: a real server on
127.0.0.1 at its default input limits, one worker.

Each hostile body (built in :mod:`tests.hostile`) gets a JSON 413 naming the limit, while
the worker's peak resident memory grows by less than 0.5 GB; corrupt archives and numbers
that would overflow downstream arithmetic get a 422 naming the field; the worker runs under
its address-space cap; and the server keeps serving throughout.
"""

from __future__ import annotations

import json
import re

import httpx
import pytest

from . import hostile
from .harness import ServerProcess, zipped_bundle

GB = 1e9
WORKER_MEMORY = 5 * 1024**3

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def server():
    srv = ServerProcess(["--workers", "1", "--worker-memory-bytes", str(WORKER_MEMORY)]).start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def tiny() -> tuple[bytes, dict, dict]:
    from shadowcorr_service.synthetic import synthetic_bundle

    return zipped_bundle(synthetic_bundle(n_rocks=3, n_views=3))


def _worker(server: ServerProcess):
    (worker,) = server.worker_processes()
    return worker


def _post_measured(server: ServerProcess, body: bytes, content_type: str) -> tuple[httpx.Response, float]:
    """The response and how far the worker's peak resident memory rose above its resident
    memory before the request."""
    pid = _worker(server).pid
    r, growth = hostile.peak_memory_growth(pid, lambda: httpx.post(
        server.url + "/correspond", content=body, headers={"Content-Type": content_type}, timeout=300))
    assert _worker(server).pid == pid, "the worker crashed and was replaced"
    return r, growth


@pytest.mark.parametrize("build, code, limit", [
    (hostile.checkerboard_mask_bundle, "too_many_runs", "max_mask_runs"),
    (hostile.huge_point_npz_bundle, "too_many_points", "max_scene_points"),
    (hostile.dense_instance_bundle, "too_many_points", "max_scene_points"),
    (hostile.many_empty_pixels_bundle, "too_many_pixels", "max_scene_pixels"),
])
def test_costly_uploads_get_413_naming_the_limit_before_the_memory_is_spent(server, build, code, limit):
    body, content_type = build()
    assert len(body) < 2_000_000
    r, growth = _post_measured(server, body, content_type)
    assert r.status_code == 413, r.text
    assert r.json()["error"] == code and limit in r.json()["message"]
    assert growth < 0.5 * GB, f"worker memory grew {growth / GB:.2f} GB"


def test_corrupt_deflate_data_is_a_422_naming_the_member(server):
    body, content_type = hostile.corrupt_deflate_bundle()
    r = httpx.post(server.url + "/correspond", content=body, headers={"Content-Type": content_type}, timeout=120)
    assert r.status_code == 422, r.text
    assert r.json()["error"] == "invalid_bundle"
    assert any(p["loc"].startswith("archive[") and "cannot extract" in p["msg"] for p in r.json()["problems"])


def _with(manifest: dict, change) -> dict:
    m = json.loads(json.dumps(manifest))
    change(m)
    return m


@pytest.mark.parametrize("change, loc", [
    (lambda m: m["views"][0]["intrinsics"].update(fx=1e308), "views[0:cam0].intrinsics.fx"),
    (lambda m: m["views"][1]["intrinsics"].update(cy=-1e300), "views[1:cam1].intrinsics.cy"),
    (lambda m: m["views"][0]["depth"].update(scale=1e-30), "views[0:cam0].depth.scale"),
    (lambda m: m["views"][2]["pose"]["matrix"][0].__setitem__(3, 1e300), "views[2] (cam2): pose translation"),
    (lambda m: m["views"][0]["pose"]["matrix"][1].__setitem__(3, 1e12), "views[0] (cam0): pose translation"),
])
def test_numbers_that_would_overflow_are_a_422_naming_the_field(server, tiny, change, loc):
    _, manifest, files = tiny
    parts = [("manifest", (None, json.dumps(_with(manifest, change)).encode()))]
    parts += [("f", (k, v)) for k, v in files.items()]
    r = httpx.post(server.url + "/correspond", files=parts, timeout=120)
    assert r.status_code == 422, r.text
    assert r.json()["error"] == "invalid_bundle"
    assert any(loc in p["loc"] or loc in p["msg"] for p in r.json()["problems"]), r.json()["problems"]


def test_workers_run_under_the_address_space_cap(server):
    with open(f"/proc/{_worker(server).pid}/limits") as fh:
        line = next(line for line in fh if line.startswith("Max address space"))
    assert re.split(r"\s{2,}", line.strip())[1:3] == [str(WORKER_MEMORY)] * 2


def test_the_server_keeps_serving_and_logs_nothing_from_the_registration_library(server, tiny):
    """After every refusal above (and a far-off but allowed camera, whose points small_gicp's
    voxel grid cannot hold), a valid scene is still labelled and the log has no line of
    small_gicp's console warnings."""
    _, manifest, files = tiny
    far = _with(manifest, lambda m: m["views"][0]["pose"]["matrix"][0].__setitem__(3, 0.99e8))  # 990 km, in cm
    for m in (far, manifest):
        parts = [("manifest", (None, json.dumps(m).encode()))] + [("f", (k, v)) for k, v in files.items()]
        r = httpx.post(server.url + "/correspond", files=parts, params={"refine_poses": "true"}, timeout=120)
        assert r.status_code == 200, r.text
    assert len(r.json()["segments"]) > 0
    assert "voxel coord is out of range" not in server.log_path.read_text(errors="replace")
