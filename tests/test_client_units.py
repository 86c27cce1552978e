"""The client's pieces without a server: retry policy, packing, scene discovery, results file.

Retries against a real socket are here too (a closed port refuses connections);
everything that needs the service is in ``test_client.py``.
"""

from __future__ import annotations

import email.utils
import json
import math
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest

from shadowcorr_client import (
    NO_RETRY,
    BundleInputError,
    BundleUpload,
    ClientError,
    ConnectionFailed,
    RetryPolicy,
    ServerError,
    ShadowCorrClient,
    as_upload,
    discover_scenes,
    parse_retry_after,
)
from shadowcorr_client.client import correspond_params, error_from_response
from shadowcorr_client.records import RecordWriter, UploadRecord, format_summary, percentile, read_records, summarize_records
from shadowcorr_client.retry import is_retryable_exception
from shadowcorr_client.request_body import archive_content_type

from .harness import free_port
from .paths import REPO
from .paths import SAMPLE_DIR as UE_SAMPLE
from .scenes import sphere_scene



def small_scene(n: int = 2, seed: int = 0):
    """A tiny sphere scene (fast to encode and to compute)."""
    rng = np.random.default_rng(seed)
    centres = [[150.0 * i, 30.0 * rng.uniform(), 45.0] for i in range(n)]
    return sphere_scene(centres, [45.0] * n, width=160, height_px=90)


# --------------------------------------------------------------------------- import weight
def test_import_clients_does_not_import_torch_or_the_server():
    code = ("import sys, shadowcorr_client, shadowcorr_client.cli; "
            "bad = [m for m in ('torch', 'shadowcorr_service', 'shadowcorr.nn', 'fastapi') if m in sys.modules]; "
            "print(','.join(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
    assert out.stdout.strip() == ""


def test_parsing_a_result_does_not_import_torch():
    """The client validates answers with shadowcorr.result.Result; that must stay light.

    Fails while shadowcorr/__init__.py imports its torch-based modules eagerly: any
    ``import shadowcorr.<submodule>`` runs the package ``__init__`` first.
    """
    code = "import sys; from shadowcorr.result import Result; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
    assert out.stdout.strip() == "False"


# --------------------------------------------------------------------------- retry policy
def test_backoff_grows_exponentially_with_bounded_jitter():
    import random

    policy = RetryPolicy(backoff_base=0.5, backoff_factor=2.0, backoff_max=4.0)
    rng = random.Random(1)
    for attempt, ceiling in [(1, 0.5), (2, 1.0), (3, 2.0), (4, 4.0), (5, 4.0), (9, 4.0)]:
        delays = [policy.backoff(attempt, rng) for _ in range(200)]
        assert min(delays) >= ceiling / 2 and max(delays) <= ceiling
        assert max(delays) - min(delays) > ceiling / 4  # there is jitter


def test_retry_after_is_honoured_and_capped():
    import random

    policy = RetryPolicy(retry_after_max=5.0)
    rng = random.Random(0)
    assert all(2.0 <= policy.delay(1, 2.0, rng) <= 2.2 for _ in range(100))  # never sooner than asked
    assert all(5.0 <= policy.delay(1, 3600.0, rng) <= 5.5 for _ in range(100))  # capped
    assert policy.delay(3, 0.0, rng) >= policy.backoff_base * 2  # "0" falls back to backoff


def test_what_is_retried():
    policy = RetryPolicy(max_attempts=3)
    assert policy.should_retry_status(503, 1) and policy.should_retry_status(502, 2)
    assert not policy.should_retry_status(503, 3)  # attempts exhausted
    for status in (400, 401, 404, 413, 422, 429, 500, 504):
        assert not policy.should_retry_status(status, 1)
    with pytest.raises(ValueError, match="only 5xx"):
        RetryPolicy(retry_statuses=frozenset({503, 429}))
    with pytest.raises(ValueError):
        RetryPolicy(max_attempts=0)
    assert not NO_RETRY.should_retry_status(503, 1)
    req = httpx.Request("GET", "http://x/")
    assert is_retryable_exception(httpx.ConnectError("refused", request=req))
    assert is_retryable_exception(httpx.RemoteProtocolError("dropped", request=req))
    assert not is_retryable_exception(httpx.ReadTimeout("slow", request=req))
    assert is_retryable_exception(httpx.ReadTimeout("slow", request=req), retry_timeouts=True)


def test_parse_retry_after():
    assert parse_retry_after("3") == 3.0
    assert parse_retry_after(" 1.5 ") == 1.5
    assert parse_retry_after("-4") == 0.0
    assert parse_retry_after(None) is None and parse_retry_after("") is None and parse_retry_after("soon") is None
    assert parse_retry_after("nan") is None
    now = time.time()
    date = email.utils.formatdate(now + 30, usegmt=True)
    assert parse_retry_after(date, now=now) == pytest.approx(30, abs=1.0)
    assert parse_retry_after(email.utils.formatdate(now - 30, usegmt=True), now=now) == 0.0


def test_connection_refused_is_retried_with_backoff_then_fails(unused_port):
    events = []
    policy = RetryPolicy(max_attempts=4, backoff_base=0.05, backoff_max=1.0)
    start = time.perf_counter()
    with ShadowCorrClient(f"http://127.0.0.1:{unused_port}", retry=policy, on_retry=events.append, seed=0) as client:
        with pytest.raises(ConnectionFailed) as info:
            client.info()
    elapsed = time.perf_counter() - start
    assert info.value.attempts == 4
    assert [e.attempt for e in events] == [1, 2, 3]
    assert all(e.status is None and e.reason == "ConnectError" for e in events)
    assert [e.delay for e in events] == sorted(e.delay for e in events)  # exponential: each wait at least as long
    assert elapsed >= sum(e.delay for e in events)
    # The readiness probe is not retried: it reports the present state at once.
    with ShadowCorrClient(f"http://127.0.0.1:{unused_port}", retry=policy, on_retry=events.append) as client:
        with pytest.raises(ConnectionFailed) as info:
            client.health()
    assert info.value.attempts == 1 and len(events) == 3
    start = time.perf_counter()
    with ShadowCorrClient(f"http://127.0.0.1:{unused_port}") as client, pytest.raises(ConnectionFailed):
        client.wait_until_ready(timeout=0.5, interval=0.1)
    assert 0.3 < time.perf_counter() - start < 5


@pytest.fixture
def unused_port() -> int:
    return free_port()  # bound then closed: nothing listens there for the test's duration


# --------------------------------------------------------------------------- request / response
def test_correspond_params_only_sends_what_is_set():
    assert correspond_params() == {}
    assert correspond_params(bandwidth=0.5, split_components=False, metrics=True, method="meanshift",
                             min_blob_pixels=10, min_cluster_size=3, refine_poses=False) == {
        "bandwidth": "0.5", "split_components": "false", "metrics": "true", "method": "meanshift",
        "min_blob_pixels": "10", "min_cluster_size": "3", "refine_poses": "false"}


def test_error_from_response_reads_the_service_error_body_or_falls_back():
    body = {"error": "invalid_bundle", "message": "1 problem in bundle", "problems": [{"loc": "views[0]", "msg": "bad"}]}
    err = error_from_response(httpx.Response(422, json=body))
    assert isinstance(err, ClientError)
    assert (err.status, err.error, err.problems) == (422, "invalid_bundle", [{"loc": "views[0]", "msg": "bad"}])
    assert "views[0]: bad" in str(err)
    err = error_from_response(httpx.Response(502, text="<html>Bad Gateway</html>", headers={"Retry-After": "7"}))
    assert isinstance(err, ServerError) and err.error == "http_502" and "Bad Gateway" in err.message
    assert err.retry_after == 7.0
    assert err.to_dict()["status"] == 502


# --------------------------------------------------------------------------- packing uploads
def _form(upload: BundleUpload) -> dict[str, tuple[str, bytes]]:
    return {fname: (field, content) for field, (fname, content, _) in upload.parts}


def test_bundle_directory_sends_manifest_and_referenced_files_only(tmp_path):
    from shadowcorr.io import load_bundle_from_parts, write_bundle

    scene = small_scene()
    root = write_bundle(scene, tmp_path / "b")
    (root / "notes.txt").write_text("not part of the bundle")
    upload = BundleUpload.from_path(root)
    form = _form(upload)
    assert form["manifest.json"][0] == "manifest"
    assert form["manifest.json"][1] == (root / "manifest.json").read_bytes()  # sent verbatim
    assert "notes.txt" not in form
    assert len(form) == 1 + 2 * len(scene.views) and upload.name == "b" and not upload.is_archive
    files = {name: content for name, (field, content) in form.items() if field == "files"}
    back = load_bundle_from_parts(form["manifest.json"][1], files)
    assert np.array_equal(back.views[1].mask, scene.views[1].mask)
    assert BundleUpload.from_path(root / "manifest.json").parts == upload.parts


def test_bundle_directory_problems_are_reported_before_sending(tmp_path):
    from shadowcorr.io import write_bundle

    root = write_bundle(small_scene(), tmp_path / "b")
    manifest = json.loads((root / "manifest.json").read_text())
    outside = tmp_path / "secret.png"
    outside.write_bytes(b"x")
    (root / "link.png").symlink_to(outside)
    manifest["views"][0]["depth"]["file"] = "../secret.png"
    manifest["views"][1]["mask"]["file"] = "missing.png"
    manifest["views"][2]["mask"]["file"] = "link.png"
    (root / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleInputError) as info:
        BundleUpload.from_path(root)
    text = str(info.value)
    # Located as the library locates it (view index and name), so both sides point at the same place.
    loc = f"views[0:{manifest['views'][0]['name']}].depth.file"
    assert f"{loc}: path '../secret.png' leaves the bundle" in text
    from shadowcorr.errors import BundleError
    from shadowcorr.io import load_bundle

    with pytest.raises(BundleError) as library:
        load_bundle(root)
    assert loc in {p.loc for p in library.value.problems}
    assert "missing.png" in text and "resolves outside" in text
    with pytest.raises(BundleInputError, match="no manifest.json"):
        BundleUpload.from_path(tmp_path)
    with pytest.raises(BundleInputError, match="no such"):
        BundleUpload.from_path(tmp_path / "nope.zip")


def test_archives_bytes_and_in_memory_bundles(tmp_path):
    from shadowcorr.io import load_bundle_from_parts, write_bundle_archive

    scene = small_scene()
    zpath = write_bundle_archive(scene, tmp_path / "s.zip")
    up = as_upload(zpath)
    assert up.is_archive and up.parts[0][1][0] == "s.zip" and up.parts[0][1][2] == "application/zip"
    up = as_upload(zpath.read_bytes())
    assert up.is_archive and up.parts[0][1][0] == "bundle.zip"
    tpath = write_bundle_archive(scene, tmp_path / "s.tar.gz")
    assert archive_content_type(tpath.read_bytes()) == ("bundle.tar.gz", "application/gzip")
    tar = write_bundle_archive(scene, tmp_path / "s.tar").read_bytes()
    assert archive_content_type(tar)[1] == "application/x-tar"
    with pytest.raises(BundleInputError):
        as_upload(b"")
    with pytest.raises(TypeError):
        as_upload(42)  # type: ignore[arg-type]

    up = as_upload(scene)
    form = _form(up)
    files = {name: content for name, (field, content) in form.items() if field == "files"}
    back = load_bundle_from_parts(form["manifest.json"][1], files)
    for a, b in zip(back.views, scene.views):
        assert np.array_equal(a.depth, b.depth) and np.array_equal(a.mask, b.mask)  # lossless


# --------------------------------------------------------------------------- discovery
def test_discover_scenes_in_a_mixed_tree(tmp_path):
    from shadowcorr.io import write_bundle, write_bundle_archive

    scene = small_scene()
    write_bundle(scene, tmp_path / "a")
    (tmp_path / "nested" / "deeper").mkdir(parents=True)
    write_bundle_archive(scene, tmp_path / "nested" / "deeper" / "b.zip")
    (tmp_path / "nested" / "c.tar.gz").write_bytes(b"")
    write_bundle(scene, tmp_path / ".hidden" / "x")
    (tmp_path / "readme.txt").write_text("ignored")
    ue = tmp_path / "unreal"
    ue.mkdir()
    for cam in (0, 2, 4, 6):
        for kind, ext in (("Depth", "exr"), ("Segment", "png")):
            (ue / f"Set2001_{kind}_{cam}.{ext}").symlink_to(UE_SAMPLE / f"Set2001_{kind}_{cam}.{ext}")
    (ue / "Set2002_Depth_0.exr").write_bytes(b"")  # no mask beside it: not a set

    scenes = discover_scenes(tmp_path)
    assert [(s.name, s.kind) for s in scenes] == [
        ("a", "bundle_dir"), ("nested/c.tar.gz", "archive"), ("nested/deeper/b.zip", "archive"),
        ("unreal/Set2001", "unreal")]
    assert scenes[-1].cameras == (0, 2, 4, 6)
    assert discover_scenes(tmp_path, cameras=[0, 4])[-1].cameras == (0, 4)
    # The root itself may be one scene.
    assert [(s.name, s.kind) for s in discover_scenes(tmp_path / "a")] == [("a", "bundle_dir")]
    assert [s.name for s in discover_scenes(ue)] == ["Set2001"]
    assert [s.name for s in discover_scenes(tmp_path / "nested" / "deeper" / "b.zip")] == ["b.zip"]
    with pytest.raises(FileNotFoundError):
        discover_scenes(tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="holds no"):
        discover_scenes(tmp_path / ".hidden" / "x" / "mask")


# --------------------------------------------------------------------------- results file
def test_results_file_survives_a_torn_line_and_keeps_the_latest_record(tmp_path):
    out = tmp_path / "r.jsonl"
    with RecordWriter(out) as w:
        w.write(UploadRecord("a", "failed", 5.0, error={"message": "boom"}))
        w.write(UploadRecord("b", "ok", 7.0, result={"metrics": {"rock_purity": 90.0}}))
    with open(out, "a") as fh:
        fh.write('{"scene": "c", "status": "o')  # killed mid-write
    latest, bad = read_records(out)
    assert bad == 1 and set(latest) == {"a", "b"}
    with RecordWriter(out) as w:  # terminates the torn line before appending
        w.write(UploadRecord("a", "ok", 3.0, result={"metrics": {"rock_purity": 100.0}}))
    latest, bad = read_records(out)
    assert bad == 1 and latest["a"].ok and latest["b"].ok
    assert read_records(tmp_path / "none.jsonl") == ({}, 0)
    line = json.loads(out.read_text().splitlines()[-1])
    assert set(line) == {"scene", "status", "result", "latency_ms"}


def test_summary_percentiles_and_metrics():
    vals = [float(v) for v in range(1, 101)]
    for q in (0, 50, 95, 100):
        assert percentile(vals, q) == pytest.approx(np.percentile(vals, q))
    assert math.isnan(percentile([], 50))
    run = [UploadRecord("a", "ok", 100.0, result={"metrics": {"rock_purity": 90.0, "cluster_purity": 80.0}}),
           UploadRecord("b", "failed", 50.0, error={"message": "HTTP 422 invalid_bundle: bad"})]
    latest = {r.scene: r for r in run}
    latest["c"] = UploadRecord("c", "ok", 10.0, result={"metrics": {"rock_purity": 100.0, "cluster_purity": math.nan}})
    s = summarize_records(["a", "b", "c", "d"], 1, run, latest, wall_s=2.0)
    assert (s.scenes, s.skipped, s.sent, s.ok, s.failed, s.pending) == (4, 1, 2, 1, 1, 1)
    assert s.metrics["rock_purity"] == pytest.approx((95.0, 5.0, 2))
    assert s.metrics["cluster_purity"] == pytest.approx((80.0, 0.0, 1))  # NaN skipped, as shadowcorr.evaluation.summarize does
    assert s.latency_p50_ms == 100.0
    table = format_summary(s)
    assert "rock purity" in table and "95.00 ± 5.00" in table and "not yet sent" in table
    assert s.failures == [("b", "HTTP 422 invalid_bundle: bad")]


def test_cli_usage_errors_exit_2(tmp_path):
    from shadowcorr_client.cli import main

    assert main(["correspond", str(tmp_path / "missing"), "--server", "http://127.0.0.1:9"]) == 2
    with pytest.raises(SystemExit) as info:
        main(["upload-dataset", str(tmp_path)])  # --out is required
    assert info.value.code == 2


def test_upload_to_an_unreachable_server_fails_fast_without_records(tmp_path, unused_port, capsys):
    from shadowcorr_client.cli import main
    from shadowcorr.io import write_bundle

    write_bundle(small_scene(), tmp_path / "data" / "a")
    out = tmp_path / "r.jsonl"
    rc = main(["upload-dataset", str(tmp_path / "data"), "--out", str(out), "--retries", "1", "--backoff", "0.01",
               "--server", f"http://127.0.0.1:{unused_port}", "--no-progress"])
    assert rc == 1 and "ConnectError" in capsys.readouterr().err
    assert read_records(out) == ({}, 0)
