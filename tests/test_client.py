"""The client and ``shadowcorr-client`` against the real service on loopback.

Two servers run as subprocesses (``python -m shadowcorr_service``, one worker each, to spare the CPU):

* ``server`` -- token-protected, default queue: the API, the CLI, dataset uploads, resuming;
* ``tiny_server`` -- one request admitted at a time (``queue_size=1``, ``Retry-After: 1``): 503
  retries, and a server stopped (then restarted on the same port) in the middle of an upload.

Request counts come from the server's own ``/metrics`` (``shadowcorr_http_requests_total``), so
"a resumed upload does not re-send finished scenes" is checked where it matters.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest

from shadowcorr_client import (
    NO_RETRY,
    AsyncShadowCorrClient,
    ClientError,
    ConnectionFailed,
    RetryPolicy,
    ServerError,
    ShadowCorrClient,
    read_records,
)
from shadowcorr_client.cli import main as cli_main
from shadowcorr.result import Result

from .harness import ServerProcess
from .paths import REPO
from .paths import SAMPLE_DIR as UE_SAMPLE
from .scenes import sphere_scene

TOKEN = "test-token-not-secret"
SYNTH_SCENES = 5

pytestmark = pytest.mark.skipif(not (UE_SAMPLE / "Set2001_Depth_0.exr").exists(), reason="sample data missing")


@pytest.fixture(scope="module")
def servers(tmp_path_factory) -> Iterator[tuple[ServerProcess, ServerProcess]]:
    logs = tmp_path_factory.mktemp("server-logs")
    quiet = {"SHADOWCORR_WORKERS": "1", "SHADOWCORR_LOG_LEVEL": "warning"}
    main = ServerProcess(env=quiet, log_path=logs / "main.log", token=TOKEN, auth=True)
    tiny = ServerProcess(env={**quiet, "SHADOWCORR_QUEUE_SIZE": "1", "SHADOWCORR_RETRY_AFTER_S": "1"},
                         log_path=logs / "tiny.log")
    # Both start at once: loading torch and warming up overlaps with the other's I/O.
    main.launch()
    tiny.launch()
    try:
        yield main.wait_ready(150), tiny.wait_ready(150)
    finally:
        main.stop()
        tiny.stop()


@pytest.fixture(scope="module")
def server(servers) -> ServerProcess:
    return servers[0]


@pytest.fixture(scope="module")
def tiny_server(servers) -> ServerProcess:
    return servers[1]


# --------------------------------------------------------------------------- data
def small_scene(i: int):
    """Small, quick sphere scenes that differ from each other (2-3 rocks)."""
    rng = np.random.default_rng(i)
    n = 2 + i % 2
    centres = [[160.0 * k, 40.0 * rng.uniform(), 45.0] for k in range(n)]
    return sphere_scene(centres, list(rng.uniform(38, 48, n)), width=160, height_px=90)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """The real sample scene twice (converted bundle, Unreal layout with cameras 0,2,4,6) + small synthetic bundles."""
    from shadowcorr.convert import convert_ue
    from shadowcorr.io import write_bundle, write_bundle_archive

    root = tmp_path_factory.mktemp("dataset")
    ue = root / "real" / "unreal"
    ue.mkdir(parents=True)
    for cam in (0, 2, 4, 6):
        for kind, ext in (("Depth", "exr"), ("Segment", "png")):
            (ue / f"Set2001_{kind}_{cam}.{ext}").symlink_to(UE_SAMPLE / f"Set2001_{kind}_{cam}.{ext}")
    convert_ue(UE_SAMPLE, 2001, [0, 2, 4, 6], root / "real" / "converted")
    synth = root / "synth"
    synth.mkdir()
    for i in range(SYNTH_SCENES):
        kind = ("dir", "zip", "tar.gz")[i % 3]
        if kind == "dir":
            write_bundle(small_scene(i), synth / f"s{i}")
        else:
            write_bundle_archive(small_scene(i), synth / f"s{i}.{kind}")
    return root


def same_partition(a: list[int], b: list[int]) -> bool:
    pairs = set(zip(a, b))
    return len(pairs) == len(set(a)) == len(set(b))


def lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def cli(server: ServerProcess, *args: str) -> int:
    """Run ``shadowcorr-client`` in-process (the test process has already paid for its imports)."""
    conn = ["--server", server.url] + (["--token", server.token] if server.token else [])
    command, rest = args[0], list(args[1:])
    return cli_main([command, *rest, *conn])


def cli_subprocess(server: ServerProcess, *args: str, out: Path) -> subprocess.Popen[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("SHADOWCORR_")}
    env["SHADOWCORR_SERVER"] = server.url  # the environment variables work as well as the flags
    if server.token:
        env["SHADOWCORR_TOKEN"] = server.token
    # A test run started in the background of a non-interactive shell (`cmd &`, as a CI script may do)
    # ignores SIGINT, and a child inherits that: Python then installs no KeyboardInterrupt handler and
    # a Ctrl-C would do nothing.  The child gets the default disposition a terminal gives a user.
    return subprocess.Popen([sys.executable, "-m", "shadowcorr_client", *args], cwd=REPO, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def wait_for_lines(path: Path, n: int, proc: subprocess.Popen | None = None, timeout: float = 90.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and len([x for x in path.read_text().splitlines() if x.strip()]) >= n:
            return
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"client exited early ({proc.returncode}): {proc.stderr.read() if proc.stderr else ''}")
        time.sleep(0.05)
    raise TimeoutError(f"{path} did not reach {n} lines")


# --------------------------------------------------------------------------- API
def test_health_info_and_bearer_token(server):
    events = []
    with ShadowCorrClient(server.url, on_retry=events.append) as anonymous:
        assert anonymous.health()["ready"] is True  # /health needs no token
        with pytest.raises(ClientError) as info:
            anonymous.info()
        assert info.value.status == 401 and info.value.attempts == 1 and events == []  # 4xx: never retried
    with ShadowCorrClient(server.url, token="wrong") as wrong, pytest.raises(ClientError) as info:
        wrong.info()
    assert info.value.status == 401 and info.value.error
    with ShadowCorrClient(server.url, token=TOKEN) as client:
        assert client.wait_until_ready(timeout=10)["status"] in ("ok", "degraded")
        info_body = client.info()
        assert info_body["model"]["sha256"] and "version" in info_body
        assert "shadowcorr_http_requests_total" in client.metrics_text()


def test_correspond_accepts_paths_bytes_and_in_memory_bundles(server, dataset):
    scene = small_scene(1)
    with ShadowCorrClient(server.url, token=TOKEN) as client:
        from_memory = client.correspond(scene, metrics=True)
        from_dir = client.correspond(dataset / "synth" / "s3")  # small_scene(3), a directory
        from_zip_path = client.correspond(dataset / "synth" / "s1.zip")
        from_zip_bytes = client.correspond((dataset / "synth" / "s1.zip").read_bytes(), metrics=True)
        baseline = client.correspond(scene, method="meanshift")
        unrefined = client.correspond(scene, refine_poses=False)
    assert isinstance(from_memory, Result) and from_memory.method == "fused" and from_memory.model is not None
    assert len(from_memory.segments) == 4 * 3 and from_memory.metrics["rock_purity"] == 100.0
    assert from_dir.metrics is None  # only when asked for
    assert same_partition(from_memory.labels, from_zip_path.labels) and from_zip_bytes.labels == from_zip_path.labels
    assert from_zip_bytes.metrics is not None
    assert len(from_dir.segments) == 4 * 3
    assert baseline.method == "meanshift" and baseline.model is None
    # per-request options reach the server's configuration (refine_poses is on by default)
    assert from_memory.config["refine_poses"] is True and unrefined.config["refine_poses"] is False


def test_bad_bundles_and_options_are_client_errors_and_not_retried(server, tmp_path):
    events = []
    with ShadowCorrClient(server.url, token=TOKEN, on_retry=events.append) as client:
        with pytest.raises(ClientError) as info:
            client.correspond(b"PK\x03\x04 this is not a zip archive")
        assert 400 <= info.value.status < 500 and info.value.problems and info.value.attempts == 1
        with pytest.raises(ClientError) as info:
            client.correspond(small_scene(0), bandwidth=-1.0)
        assert info.value.status == 422 and info.value.error == "invalid_options"
        assert any("bandwidth" in p["loc"] for p in info.value.problems)
    assert events == []


def test_async_client_runs_requests_concurrently(server):
    async def run():
        async with AsyncShadowCorrClient(server.url, token=TOKEN, max_connections=2) as client:
            health = await client.health()
            results = await asyncio.gather(*(client.correspond(small_scene(i), metrics=True) for i in (0, 1)))
            return health, results, await client.info()

    health, results, info = asyncio.run(run())
    assert health["ready"] and info["model"]
    assert [len(r.objects) for r in results] == [2, 3]
    assert all(r.metrics["average_purity"] == 100.0 for r in results)


# --------------------------------------------------------------------------- CLI
def test_cli_health_info_correspond_and_render(server, dataset, tmp_path, capsys):
    assert cli(server, "health") == 0
    assert json.loads(capsys.readouterr().out)["ready"] is True
    assert cli(server, "info") == 0
    assert json.loads(capsys.readouterr().out)["model"]["name"]
    out = tmp_path / "result.json"
    assert cli(server, "correspond", str(dataset / "synth" / "s1.zip"), "--metrics", "--out", str(out),
               "--render", str(tmp_path / "pictures")) == 0
    result = Result.model_validate_json(out.read_text())
    assert result.metrics and result.metrics["rock_purity"] == 100.0
    assert "segments ->" in capsys.readouterr().out
    assert list((tmp_path / "pictures").glob("*.png"))
    # The Unreal layout works for one scene too, converted on the fly with --cameras.
    assert cli(server, "correspond", str(dataset / "real" / "unreal"), "--cameras", "0,2,4,6") == 0
    printed = Result.model_validate_json(capsys.readouterr().out)
    assert {s.view for s in printed.segments} == {"cam0", "cam2", "cam4", "cam6"}
    assert printed.config["refine_poses"] is True
    assert cli(server, "correspond", str(dataset / "synth" / "s1.zip"), "--no-refine-poses") == 0
    assert Result.model_validate_json(capsys.readouterr().out).config["refine_poses"] is False
    # A 4xx from the server exits 1 with the server's message.
    assert cli(server, "correspond", str(dataset / "synth" / "s1.zip"), "--bandwidth", "-2") == 1
    assert "invalid_options" in capsys.readouterr().err


def test_upload_dataset_real_and_synthetic_scenes(server, dataset, tmp_path, capsys):
    out = tmp_path / "results.jsonl"
    before = server.requests().get("200", 0)
    start = time.perf_counter()
    assert cli(server, "upload-dataset", str(dataset), "--out", str(out), "--metrics", "--concurrency", "2",
               "--cameras", "0,2,4,6", "--no-progress") == 0
    elapsed = time.perf_counter() - start
    stdout = capsys.readouterr().out
    records = lines(out)
    names = sorted(r["scene"] for r in records)
    assert names == sorted(["real/converted", "real/unreal/Set2001", "synth/s0", "synth/s1.zip", "synth/s2.tar.gz",
                            "synth/s3", "synth/s4.zip"])
    assert server.requests().get("200", 0) - before == len(records)
    for r in records:
        assert r["status"] == "ok" and r["latency_ms"] > 0 and "error" not in r
        Result.model_validate(r["result"])
    by_name = {r["scene"]: Result.model_validate(r["result"]) for r in records}
    converted, unreal = by_name["real/converted"], by_name["real/unreal/Set2001"]
    # The same scene, once from a bundle directory and once converted on the fly: the same answer.
    assert len(converted.segments) == len(unreal.segments) == 77
    assert same_partition(converted.labels, unreal.labels)
    assert converted.metrics["average_purity"] > 95
    for key in ("rock purity", "cluster purity", "average purity", "voxel ARI", "coverage %", "latency p50", "latency p95"):
        assert key in stdout
    assert re.search(r"^scenes\s+7$", stdout, re.M) and re.search(r"^failed\s+0$", stdout, re.M)
    print(f"upload of 7 scenes: {elapsed:.1f} s", file=sys.stderr)


def test_interrupted_upload_resumes_without_resending_finished_scenes(server, dataset, tmp_path):
    out = tmp_path / "results.jsonl"
    synth = dataset / "synth"
    # 1. --limit stops after two scenes; the rerun sends only the other three.
    assert cli(server, "upload-dataset", str(synth), "--out", str(out), "--limit", "2", "--no-progress") == 0
    assert [r["status"] for r in lines(out)] == ["ok", "ok"]
    before = server.requests().get("200", 0)
    assert cli(server, "upload-dataset", str(synth), "--out", str(out), "--no-progress") == 0
    assert server.requests().get("200", 0) - before == SYNTH_SCENES - 2
    assert sorted(r["scene"] for r in lines(out)) == sorted({r["scene"] for r in lines(out)})  # none twice
    assert len(lines(out)) == SYNTH_SCENES

    # 2. A real interruption: Ctrl-C once the first scene is written; the rerun sends only what is missing.
    # Twelve copies of the real scene (about 0.2 s each to label), so that the upload is still running
    # when the signal comes.
    many = tmp_path / "many"
    many.mkdir()
    for copy in range(12):
        shutil.copytree(dataset / "real" / "converted", many / f"real{copy}")
    total = len(list(many.iterdir()))
    out2 = tmp_path / "interrupted.jsonl"
    proc = cli_subprocess(server, "upload-dataset", str(many), "--out", str(out2), "--concurrency", "1", out=out2)
    try:
        wait_for_lines(out2, 1, proc)
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    done, _ = read_records(out2)
    assert 1 <= len(done) < total, "the upload finished before it could be interrupted"
    assert proc.returncode == 130 and "resume" in stderr
    before = server.requests().get("200", 0)
    assert cli(server, "upload-dataset", str(many), "--out", str(out2), "--no-progress") == 0
    assert server.requests().get("200", 0) - before == total - len(done)
    assert len(read_records(out2)[0]) == total


# --------------------------------------------------------------------------- retries
def test_503_is_retried_honouring_retry_after(tiny_server):
    """queue_size=1: concurrent requests are refused with 503 + Retry-After: 1 until the first is done."""
    events = []
    policy = RetryPolicy(max_attempts=12, backoff_base=0.05, retry_after_max=5.0)

    async def burst(client_policy, n):
        async with AsyncShadowCorrClient(tiny_server.url, retry=client_policy, on_retry=events.append,
                                         max_connections=n) as client:
            return await asyncio.gather(*(client.correspond(small_scene(i)) for i in range(n)),
                                        return_exceptions=True)

    before = tiny_server.requests()
    results = asyncio.run(burst(policy, 3))
    assert all(isinstance(r, Result) for r in results), results
    after = tiny_server.requests()
    refused = after.get("503", 0) - before.get("503", 0)
    assert refused >= 1 and after.get("200", 0) - before.get("200", 0) == 3
    assert events, "nothing was retried"
    for e in events:
        if e.status == 503:
            assert e.delay >= 1.0  # never sooner than Retry-After
        else:  # the server may answer 503 before reading the body, and drop the connection on the rest
            assert e.status is None

    events.clear()
    results = asyncio.run(burst(NO_RETRY, 2))
    errors = [r for r in results if not isinstance(r, Result)]
    assert events == [] and len(errors) == 1, results
    # The refusal is the server's 503 or, when it answered before reading the body and dropped
    # the connection on the rest, a connection failure: nothing else.
    err = errors[0]
    if isinstance(err, ServerError):
        assert err.status == 503 and err.error == "overloaded" and err.retry_after == 1.0
    else:
        assert isinstance(err, ConnectionFailed) and err.attempts == 1, repr(err)


def test_server_stopped_mid_upload_then_restarted(tiny_server, dataset, tmp_path, capsys):
    out = tmp_path / "results.jsonl"
    synth = dataset / "synth"

    def stop_after_first_line() -> None:
        wait_for_lines(out, 1)
        tiny_server.stop()

    stopper = threading.Thread(target=stop_after_first_line, daemon=True)
    stopper.start()
    rc = cli(tiny_server, "upload-dataset", str(synth), "--out", str(out), "--concurrency", "1",
             "--retries", "2", "--backoff", "0.1", "--abort-after", "2", "--no-progress")
    stopper.join(60)
    captured = capsys.readouterr()
    records = lines(out)
    failed = [r for r in records if r["status"] == "failed"]
    # Two scenes in a row found no server: the upload stopped instead of failing every remaining scene.
    assert rc == 1 and len(failed) == 2 and records[-1]["status"] == records[-2]["status"] == "failed"
    for r in failed:
        assert r["error"]["type"] == "ConnectionFailed" and r["error"]["attempts"] == 3
        assert "latency_ms" in r and "result" not in r
    assert re.search(rf"^failed\s+{len(failed)}$", captured.out, re.M)
    pending = SYNTH_SCENES - len(records)
    if pending:
        assert re.search(rf"^not yet sent\s+{pending}$", captured.out, re.M) and "run the same command" in captured.err
    for r in failed:  # named in the final report, with the reason
        assert f"failed {r['scene']}: " in captured.err and "ConnectError" in captured.err

    tiny_server.launch()  # same port
    tiny_server.wait_ready()
    before = tiny_server.requests().get("200", 0)
    assert cli(tiny_server, "upload-dataset", str(synth), "--out", str(out), "--no-progress") == 0
    assert tiny_server.requests().get("200", 0) - before == len(failed) + pending  # not the finished ones
    latest, _ = read_records(out)
    assert len(latest) == SYNTH_SCENES and all(r.ok for r in latest.values())
