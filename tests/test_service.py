"""HTTP service, end to end: a real ``python -m shadowcorr_service`` process talked to over HTTP.

One server (2 workers, 200 ms batching window) serves the whole module; tests run in
file order and the last one shuts it down gracefully.  Sample-scene requests are few:
each costs about 2 s of CPU.
"""

from __future__ import annotations

import asyncio
import io
import json
import os
import signal
import threading
import time

import httpx
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from .harness import ServerProcess, zip_files, zipped_bundle

from .paths import SAMPLE_DIR

SAMPLE_CAMERAS = (0, 2, 4, 6)
MiB = 1024 * 1024
BODY_LIMIT = 8 * MiB
UNCOMPRESSED_LIMIT = 64 * MiB

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def server():
    srv = ServerProcess(
        [
            "--workers", "2",
            "--max-batch-size", "8",
            "--max-wait-ms", "200",
            "--queue-size", "32",
            "--request-timeout-s", "120",
            "--max-body-bytes", str(BODY_LIMIT),
            "--max-uncompressed-bytes", str(UNCOMPRESSED_LIMIT),
            "--max-views", "8",
            "--max-pixels-per-view", str(4096 * 4096),
            "--max-segments", "500",
            "--graceful-shutdown-s", "60",
        ]
    )
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def client(server):
    with httpx.Client(base_url=server.url, timeout=180.0) as c:
        yield c


@pytest.fixture(scope="module")
def synthetic():
    """A small valid scene: (zip bytes, manifest dict, files dict, local labels)."""
    from shadowcorr import correspond, load_bundle
    from shadowcorr_service.synthetic import synthetic_bundle

    zipped, manifest, files = zipped_bundle(synthetic_bundle(n_rocks=3, n_views=3))
    labels = correspond(load_bundle(zipped)).labels
    return zipped, manifest, files, labels


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    """The real sample scene (set 2001, cameras 0,2,4,6): zip path, parts, local result."""
    if not SAMPLE_DIR.is_dir():
        pytest.skip(f"sample data not found at {SAMPLE_DIR}")
    from shadowcorr import correspond, load_bundle
    from shadowcorr.convert.ue import load_ue_scene
    from shadowcorr.io import bundle_to_parts, write_bundle_archive

    bundle = load_ue_scene(SAMPLE_DIR, 2001, SAMPLE_CAMERAS)
    path = write_bundle_archive(bundle, tmp_path_factory.mktemp("sample") / "scene.zip")
    manifest, files = bundle_to_parts(bundle)
    local = correspond(load_bundle(path))
    return path, manifest, files, local


def _parts(manifest: dict | str, files: dict[str, bytes]) -> list:
    text = manifest if isinstance(manifest, str) else json.dumps(manifest)
    return [("manifest", (None, text.encode()))] + [("files", (name, data)) for name, data in files.items()]


def _metric_samples(text: str) -> dict[str, list]:
    out: dict[str, list] = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out.setdefault(s.name, []).append(s)
    return out


def _labels(result: dict) -> list[int]:
    return [s["object"] for s in result["segments"]]


def _raw_post(server: ServerProcess, headers: bytes, body: bytes = b"") -> tuple[int, dict]:
    """POST /correspond over a plain socket; returns (status, JSON body)."""
    import socket

    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
        sock.sendall(b"POST /correspond HTTP/1.1\r\nHost: x\r\nConnection: close\r\n" + headers + b"\r\n" + body)
        data = b""
        while chunk := sock.recv(65536):
            data += chunk
    head, _, rest = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), json.loads(rest)


def _worker_busy(server: ServerProcess, timeout: float = 60.0):
    """The worker process that starts burning CPU first (it is running our request)."""
    procs = server.worker_processes()
    assert len(procs) == 2, f"expected 2 worker processes, found {len(procs)}"
    base = {p.pid: sum(p.cpu_times()[:2]) for p in procs}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for p in procs:
            if sum(p.cpu_times()[:2]) - base[p.pid] > 0.15:
                return p
        time.sleep(0.02)
    raise AssertionError("no worker became busy")


def _post_in_background(server: ServerProcess, path) -> tuple[threading.Thread, dict]:
    """POST the bundle archive at ``path`` from a thread; the response lands in ``result["r"]``."""
    result: dict = {}

    def post() -> None:
        with httpx.Client(base_url=server.url, timeout=180.0) as c:
            result["r"] = c.post("/correspond", files={"bundle": ("scene.zip", path.read_bytes())})

    thread = threading.Thread(target=post)
    thread.start()
    return thread, result


# --------------------------------------------------------------------------- basics
def test_health_info_metrics(client, server):
    h = client.get("/health")
    assert h.status_code == 200
    body = h.json()
    assert body["status"] == "ok" and body["ready"] is True
    assert set(body) >= {"status", "model", "uptime_s", "queue_depth", "workers", "ready"}
    assert set(body["model"]) == {"name", "version", "sha256"} and len(body["model"]["sha256"]) == 64
    assert body["workers"]["configured"] == 2 and body["workers"]["ready"] == 2
    assert body["queue_depth"] == 0

    info = client.get("/info").json()
    from shadowcorr import __version__

    assert info["version"] == __version__
    assert info["model"]["sha256"] == body["model"]["sha256"]
    assert info["model"]["card"]["voxel_size"] == 8.0 and info["model"]["card"]["units"] == "cm"
    assert info["limits"]["max_body_bytes"] == BODY_LIMIT and info["limits"]["max_views"] == 8
    assert set(info["request_options"]) == {"bandwidth", "split_components", "min_blob_pixels", "min_cluster_size",
                                            "refine_poses"}
    assert info["settings"]["workers"] == 2 and info["settings"]["auth"] == "none"
    assert "auth_token" not in info["settings"]

    m = client.get("/metrics")
    assert m.status_code == 200 and m.headers["content-type"].startswith("text/plain")
    names = {f.name for f in text_string_to_metric_families(m.text)}
    assert {
        "shadowcorr_http_requests",
        "shadowcorr_http_request_duration_seconds",
        "shadowcorr_stage_duration_seconds",
        "shadowcorr_queue_depth",
        "shadowcorr_batch_size",
        "shadowcorr_workers_ready",
    } <= names
    samples = _metric_samples(m.text)
    assert any(s.labels == {"route": "/health", "status": "200"} for s in samples["shadowcorr_http_requests_total"])

    spec = client.get("/openapi.json").json()
    post = spec["paths"]["/correspond"]["post"]
    assert "multipart/form-data" in post["requestBody"]["content"]
    assert post["responses"]["200"]["content"]["application/json"]["schema"]["$ref"].endswith("/Result")
    assert {p["name"] for p in post["parameters"]} >= {"bandwidth", "split_components", "min_blob_pixels",
                                                        "min_cluster_size", "refine_poses", "method", "metrics"}


def test_refine_poses_query_option_reports_every_view(client, sample):
    path, manifest, _, local = sample
    r = client.post("/correspond", params={"refine_poses": "true"}, files={"bundle": ("scene.zip", path.read_bytes())})
    assert r.status_code == 200, r.text
    body = r.json()
    assert [p["view"] for p in body["poses"]] == [v["name"] for v in manifest["views"]]
    assert all(p["status"] == "unchanged" and p["rotation_deg"] == 0.0 for p in body["poses"])
    assert "poses" in body["timings_ms"]
    assert [p.status for p in local.poses] == [p["status"] for p in body["poses"]]  # on by default
    off = client.post("/correspond", params={"refine_poses": "false"}, files={"bundle": ("scene.zip", path.read_bytes())})
    assert off.status_code == 200, off.text
    assert off.json()["poses"] is None and "poses" not in off.json()["timings_ms"]


def test_sample_scene_parts_and_zip_match_local(client, sample):
    path, manifest, files, local = sample
    r1 = client.post("/correspond", files=_parts(manifest, files))
    assert r1.status_code == 200, r1.text
    r2 = client.post("/correspond", params={"metrics": "true"}, files={"bundle": ("scene.zip", path.read_bytes())})
    assert r2.status_code == 200, r2.text
    a, b = r1.json(), r2.json()
    assert len(a["segments"]) == len(local.segments) == 77
    assert _labels(a) == _labels(b) == local.labels
    assert [(s["view"], s["instance"], s["component"]) for s in a["segments"]] == [
        (s.view, s.instance, s.component) for s in local.segments
    ]
    assert a["metrics"] is None  # not asked for
    assert b["metrics"]["rock_purity"] == local.metrics["rock_purity"]
    assert a["model"]["sha256"] == client.get("/health").json()["model"]["sha256"]
    assert {"decode", "network", "surface_evidence", "grouping"} <= set(b["timings_ms"])


def test_concurrent_requests_are_batched(client, server, synthetic):
    zipped, manifest, files, labels = synthetic
    before = _metric_samples(client.get("/metrics").text)

    async def run() -> list[httpx.Response]:
        async with httpx.AsyncClient(base_url=server.url, timeout=180.0) as ac:
            reqs = [
                ac.post("/correspond", files={"bundle": ("s.zip", zipped)}) if i % 2 else
                ac.post("/correspond", files=_parts(manifest, files))
                for i in range(16)
            ]
            return await asyncio.gather(*reqs)

    responses = asyncio.run(run())
    assert [r.status_code for r in responses] == [200] * 16, [r.text for r in responses if r.status_code != 200]
    assert all(_labels(r.json()) == labels for r in responses)

    after = _metric_samples(client.get("/metrics").text)

    def batches(samples: dict, le: str | None) -> float:
        name = "shadowcorr_batch_size_bucket" if le else "shadowcorr_batch_size_count"
        return sum(s.value for s in samples.get(name, []) if le is None or s.labels.get("le") == le)

    multi_after = batches(after, None) - batches(after, "1.0")
    multi_before = batches(before, None) - batches(before, "1.0")
    assert multi_after - multi_before >= 1, "no batch of more than one scene"
    total = sum(s.value for s in after["shadowcorr_http_requests_total"] if s.labels["route"] == "/correspond"
                and s.labels["status"] == "200")
    assert total >= 16


def test_meanshift_and_options(client, synthetic):
    zipped, _, _, labels = synthetic
    r = client.post("/correspond", params={"method": "meanshift", "metrics": "true"}, files={"bundle": ("s.zip", zipped)})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["method"] == "meanshift" and body["model"] is None and len(body["segments"]) == len(labels)
    # Every per-request option, each away from its default, reaches the computation: the
    # result's configuration says so and the labels are the library's under those options.
    from shadowcorr import ShadowCorrConfig, correspond, load_bundle

    options = {"method": "shadowcorr", "bandwidth": 0.5, "split_components": False, "min_blob_pixels": 120,
               "min_cluster_size": 3, "refine_poses": False}
    defaults = ShadowCorrConfig()
    assert all(getattr(defaults, k) != v for k, v in options.items())
    r = client.post("/correspond", params={k: str(v).lower() for k, v in options.items()},
                    files={"bundle": ("s.zip", zipped)})
    assert r.status_code == 200, r.text
    assert {k: r.json()["config"][k] for k in options} == options
    local = correspond(load_bundle(zipped), config=ShadowCorrConfig(**options), metrics=False)
    assert _labels(r.json()) == local.labels
    # a bare archive body works too
    r = client.post("/correspond", content=zipped, headers={"Content-Type": "application/zip"})
    assert r.status_code == 200 and _labels(r.json()) == labels


def test_tar_bundle_and_manifest_as_file_part(client, synthetic):
    import tarfile

    _, manifest, files, labels = synthetic
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        for name, data in {"manifest.json": json.dumps(manifest).encode(), **files}.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    r = client.post("/correspond", files={"bundle": ("scene.tar.gz", buf.getvalue())})
    assert r.status_code == 200, r.text
    assert _labels(r.json()) == labels
    parts = [("files", ("manifest.json", json.dumps(manifest).encode()))] + [("files", (k, v)) for k, v in files.items()]
    r = client.post("/correspond", files=parts)
    assert r.status_code == 200, r.text
    assert _labels(r.json()) == labels


# --------------------------------------------------------------------------- bad input
def _bad_cases(synthetic) -> list[tuple[str, dict, tuple[int, ...], str]]:
    """(name, httpx request kwargs, allowed statuses, text the error must contain)."""
    from shadowcorr.io.images import encode_depth_exr

    zipped, manifest, files, _ = synthetic
    depth_key = manifest["views"][0]["depth"]["file"]
    mask_key = manifest["views"][0]["mask"]["file"]

    def with_view(change) -> dict:
        m = json.loads(json.dumps(manifest))
        change(m)
        return m

    def nan_pose(m):
        m["views"][1]["pose"]["matrix"][0][3] = float("nan")

    def scaled_pose(m):
        for row in m["views"][0]["pose"]["matrix"][:3]:
            row[:3] = [2 * x for x in row[:3]]

    def huge(m):
        m["views"][0]["intrinsics"].update(width=100_000, height=100_000)

    def many_views(m):
        m["views"] = [dict(m["views"][0], name=f"v{i}") for i in range(12)]

    empty_mask = files.copy()
    from shadowcorr.io.images import encode_mask_png

    for v in manifest["views"]:
        empty_mask[v["mask"]["file"]] = encode_mask_png(np.zeros((120, 160), np.uint8))

    confetti = np.zeros((120, 160), np.uint16)
    confetti.ravel()[: 600 * 2 : 2] = np.arange(1, 601)  # 600 one-pixel instances
    many_ids = {**files, mask_key: encode_mask_png(confetti)}
    no_depth = {k: (encode_depth_exr(np.zeros((120, 160), np.float32)) if k.startswith("depth/") else v)
                for k, v in files.items()}

    pickled = io.BytesIO()
    np.save(pickled, np.array([{"evil": 1}], dtype=object), allow_pickle=True)
    npz = zip_files({"points.npy": pickled.getvalue()})
    seg_manifest = {
        "units": "cm",
        "views": [{"name": v["name"], "pose": v["pose"]} for v in manifest["views"]],
        "segments": {"file": "segments.npz"},
    }

    traversal = zip_files({"manifest.json": json.dumps(manifest).encode(), "../evil.txt": b"x",
                      **files})
    # ~65 KiB compressed in place of a mask the manifest names: a bomb (members it does not
    # name are never decompressed, see test_service_faults)
    bomb = zip_files({"manifest.json": json.dumps(manifest).encode(), **files, mask_key: b"\0" * (UNCOMPRESSED_LIMIT + MiB)})

    truncated_body = (
        b"--XyZ\r\nContent-Disposition: form-data; name=\"bundle\"; filename=\"a.zip\"\r\n\r\n" + zipped[:200]
    )
    return [
        ("not multipart", {"content": b"hello", "headers": {"Content-Type": "text/plain"}}, (415,), "content-type"),
        ("no content type", {"content": b"hello", "headers": {"Content-Type": ""}}, (415,), "content-type"),
        ("garbage multipart", {"content": b"no boundaries here at all",
                               "headers": {"Content-Type": "multipart/form-data; boundary=XyZ"}}, (400,), "multipart"),
        ("truncated multipart", {"content": truncated_body,
                                 "headers": {"Content-Type": "multipart/form-data; boundary=XyZ"}}, (400,), "truncated"),
        ("no bundle part", {"files": [("stuff", (None, b"x"))]}, (400,), "unexpected form field"),
        ("bundle and manifest", {"files": [("bundle", ("a.zip", zipped)), ("manifest", (None, b"{}"))]}, (400,), "not both"),
        ("bundle not an archive", {"files": {"bundle": ("a.zip", os.urandom(4096))}}, (422,), "archive"),
        ("truncated zip", {"files": {"bundle": ("a.zip", zipped[: len(zipped) // 2])}}, (422,), "archive"),
        ("manifest not json", {"files": _parts("{not json", files)}, (422,), "manifest"),
        ("missing file", {"files": _parts(manifest, {k: v for k, v in files.items() if k != mask_key})}, (422,),
         mask_key),
        ("duplicate file part", {"files": _parts(manifest, files) + [("files", (depth_key, files[depth_key]))]},
         (400,), "twice"),
        ("path traversal in archive", {"files": {"bundle": ("a.zip", traversal)}}, (422,), ".."),
        ("absolute path in manifest",
         {"files": _parts(with_view(lambda m: m["views"][0]["depth"].update(file="/etc/passwd")), files)}, (422,),
         "absolute"),
        ("zip bomb", {"files": {"bundle": ("a.zip", bomb)}}, (413, 422), "expand"),
        ("corrupt png", {"files": _parts(manifest, {**files, mask_key: files[mask_key][:60]})}, (422,), "mask"),
        ("corrupt exr", {"files": _parts(manifest, {**files, depth_key: b"\x76\x2f\x31\x01" + b"\0" * 100})},
         (422,), "depth"),
        ("depth size mismatch", {"files": _parts(manifest, {**files, depth_key: encode_depth_exr(np.ones((10, 10),
                                                                                                         np.float32))})},
         (422,), "depth"),
        ("non-finite pose", {"files": _parts(json.dumps(with_view(nan_pose)), files)}, (422,), "pose"),
        ("non-rigid pose", {"files": _parts(with_view(scaled_pose), files)}, (422,), "rotation"),
        ("wrong units", {"files": _parts(with_view(lambda m: m.update(units="inch")), files)}, (422,), "units"),
        ("huge dimensions", {"files": _parts(with_view(huge), files)}, (413, 422), "pixels"),
        ("too many views", {"files": _parts(with_view(many_views), files)}, (413, 422), "views"),
        ("empty masks", {"files": _parts(manifest, empty_mask)}, (422,), "no segments"),
        ("no valid depth", {"files": _parts(manifest, no_depth)}, (422,), "valid depth"),
        ("too many segments", {"params": {"min_blob_pixels": "1"}, "files": _parts(manifest, many_ids)}, (413,),
         "600"),
        ("pickled npz", {"files": _parts(seg_manifest, {"segments.npz": npz})}, (422,), "segments"),
        ("bad option value", {"params": {"bandwidth": "-1"}, "files": {"bundle": ("a.zip", zipped)}}, (422,),
         "bandwidth"),
        ("option of wrong type", {"params": {"min_blob_pixels": "lots"}, "files": {"bundle": ("a.zip", zipped)}},
         (422,), "min_blob_pixels"),
        ("unknown option", {"params": {"bandwith": "0.5"}, "files": {"bundle": ("a.zip", zipped)}}, (422,),
         "bandwith"),
        ("unknown method", {"params": {"method": "magic"}, "files": {"bundle": ("a.zip", zipped)}}, (422,), "method"),
        ("streamed body too large", {"content": (b"\0" * MiB for _ in range(BODY_LIMIT // MiB + 2)),
                                     "headers": {"Content-Type": "application/zip"}}, (413,), "too large"),
        ("empty body", {"content": b"", "headers": {"Content-Type": "application/zip"}}, (400,), "empty"),
    ]


def test_bad_inputs_get_4xx_naming_the_problem(client, server, synthetic):
    cases = _bad_cases(synthetic)
    assert len(cases) >= 15
    failures = []
    for name, kwargs, statuses, needle in cases:
        try:
            r = client.post("/correspond", **kwargs)
        except httpx.HTTPError as e:  # the server may close early on an oversized upload
            failures.append(f"{name}: {type(e).__name__}: {e}")
            continue
        body = r.json() if r.headers.get("content-type", "").startswith("application/json") else {}
        text = json.dumps(body).lower()
        ok = (
            r.status_code in statuses
            and set(body) == {"error", "message", "problems"}
            and needle.lower() in text
        )
        if not ok:
            failures.append(f"{name}: {r.status_code} {r.text[:300]}")
    assert not failures, "\n".join(failures)
    # A declared Content-Length over the limit is refused before the body is read
    # (raw socket: HTTP clients refuse to send a body shorter than its declared length).
    status, payload = _raw_post(server, b"Content-Type: application/zip\r\nContent-Length: %d\r\n" % (BODY_LIMIT + 1))
    assert status == 413 and "too large" in payload["message"], payload
    assert client.get("/nope").json()["error"] == "not_found"
    assert client.get("/correspond").status_code == 405
    h = client.get("/health")
    assert h.status_code == 200 and h.json()["workers"]["ready"] == 2 and h.json()["workers"]["restarts"] == 0


# --------------------------------------------------------------------------- failures
@pytest.fixture(scope="module")
def all_cameras(tmp_path_factory):
    """The real sample scene with all 8 cameras (the most this server takes): a request that keeps
    a worker busy for about a second of CPU, long enough to be caught at it."""
    if not SAMPLE_DIR.is_dir():
        pytest.skip(f"sample data not found at {SAMPLE_DIR}")
    from shadowcorr.convert.ue import load_ue_scene
    from shadowcorr.io import write_bundle_archive

    return write_bundle_archive(load_ue_scene(SAMPLE_DIR, 2001, range(8)),
                                tmp_path_factory.mktemp("all_cameras") / "scene.zip")


def test_killed_worker_fails_its_request_and_is_replaced(client, server, all_cameras, synthetic):
    zipped, _, _, labels = synthetic
    t, result = _post_in_background(server, all_cameras)
    victim = _worker_busy(server)
    victim.send_signal(signal.SIGKILL)
    t.join(180)
    r = result["r"]
    assert r.status_code == 500, r.text
    assert r.json()["error"] == "worker_crashed" and "worker" in r.json()["message"]

    # the other worker keeps serving while the replacement warms up
    r = client.post("/correspond", files={"bundle": ("s.zip", zipped)})
    assert r.status_code == 200 and _labels(r.json()) == labels
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        h = client.get("/health").json()
        if h["workers"]["ready"] == 2:
            break
        time.sleep(0.5)
    assert h["workers"] == {"configured": 2, "ready": 2, "restarts": 1}, h
    assert victim.pid not in {p.pid for p in server.worker_processes()}
    rs = [client.post("/correspond", files={"bundle": ("s.zip", zipped)}) for _ in range(3)]
    assert all(r.status_code == 200 and _labels(r.json()) == labels for r in rs)
    text = client.get("/metrics").text
    assert _metric_samples(text)["shadowcorr_worker_restarts_total"][0].value == 1


def test_client_disconnect_cancels_the_request(client, server, sample):
    path, *_ = sample
    # The sample scene needs several hundred ms of CPU; the client gives up after 0.1 s of waiting.
    with pytest.raises(httpx.ReadTimeout):
        httpx.post(server.url + "/correspond", files={"bundle": ("scene.zip", path.read_bytes())},
                   timeout=httpx.Timeout(30.0, read=0.1))
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        samples = _metric_samples(client.get("/metrics").text)
        if any(s.labels.get("code") == "client_disconnected" for s in samples.get("shadowcorr_errors_total", [])):
            break
        time.sleep(0.2)
    else:
        raise AssertionError("the disconnect was not noticed")
    # The slot is held until the cancelled job has really stopped (it finishes or its worker is killed).
    deadline = time.monotonic() + 60
    while client.get("/health").json()["queue_depth"] != 0 and time.monotonic() < deadline:
        time.sleep(0.2)
    assert client.get("/health").json()["queue_depth"] == 0


def test_graceful_shutdown_drains_in_flight_requests(server, all_cameras):
    """Last test of the module: SIGTERM during a request; the request still completes.  The
    8-camera scene: the 4-camera one can finish on a fast core before its worker is seen busy."""
    from shadowcorr import correspond, load_bundle

    local = correspond(load_bundle(all_cameras))
    t, result = _post_in_background(server, all_cameras)
    _worker_busy(server)
    server.proc.send_signal(signal.SIGTERM)
    t.join(180)
    assert result["r"].status_code == 200, result["r"].text
    assert _labels(result["r"].json()) == local.labels
    # uvicorn re-raises the signal after a clean shutdown, so "killed by SIGTERM" is success too
    assert server.proc.wait(60) in (0, -signal.SIGTERM)
    assert "Application shutdown complete" in server.log_tail()
    with pytest.raises(httpx.HTTPError):
        httpx.get(server.url + "/health", timeout=2.0)
