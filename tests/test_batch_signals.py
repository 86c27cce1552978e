"""``shadowcorr batch`` leaves no process behind when its driver is stopped, by SIGTERM, SIGINT or SIGKILL.

Each test runs the real CLI as a subprocess on a dataset of many tiny scenes (hard links
of one sphere-scene archive, so the run is still going when it is signalled), records
every process the driver starts (its descendants, until the signal) and signals the
driver once the first results line is written: the workers are up and busy by then.
Every recorded process must be gone ``GONE_WITHIN_S`` later.  The local engine's pool
(forkserver, workers, resource tracker) and the Ray engine's local instance (gcs_server,
raylet, agents, workers, the watchdog) both; the Ray tests need the ``ray`` extra.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from tests.harness import REPO_ROOT
from tests.scenes import sphere_scene

SCENES = 1000  # tens of milliseconds each on a warm worker: the run goes on well past the signal (checked)
WORKERS = 2
GONE_WITHIN_S = 10.0
Descendants = dict[int, tuple[psutil.Process, str]]  # pid: the process, its latest command line


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    from shadowcorr.io import write_bundle_archive

    root = tmp_path_factory.mktemp("signals_dataset")
    rng = np.random.default_rng(3)
    spheres = sphere_scene([[0.0, 0.0, 45.0], [150.0, 30.0, 45.0], [60.0, 160.0, 45.0]], list(rng.uniform(38, 48, 3)),
                           width=160, height_px=90)
    first = root / "scene_0000.zip"
    write_bundle_archive(spheres, first)
    for i in range(1, SCENES):
        os.link(first, root / f"scene_{i:04d}.zip")
    return root


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines() if path.exists() else []


def _record(driver: psutil.Process, descendants: Descendants) -> None:
    for child in driver.children(recursive=True):
        try:  # the latest command line: Ray's workers and agents retitle themselves "ray::..." once started
            descendants[child.pid] = (child, " ".join(child.cmdline()))
        except psutil.NoSuchProcess:
            pass


def _alive(descendants: Descendants) -> list[str]:
    out = []
    for proc, cmdline in descendants.values():
        try:
            if proc.is_running() and proc.status() != psutil.STATUS_ZOMBIE:
                out.append(f"{proc.pid} {cmdline[:100]}")
        except psutil.NoSuchProcess:
            pass
    return out


def _signal_mid_run(engine: str, sig: signal.Signals, dataset: Path,
                    tmp_path: Path) -> tuple[int, str, Path, Descendants]:
    """Run ``shadowcorr batch`` and send ``sig`` to the driver once a scene is done; returns its exit
    status, its stderr, the results file and its descendants."""
    if engine == "ray":
        pytest.importorskip("ray", reason='the Ray engine needs pip install "shadowcorr[ray]"')
    out = tmp_path / "results.jsonl"
    err_path = tmp_path / "stderr.log"
    cmd = [sys.executable, "-m", "shadowcorr.cli", "batch", str(dataset), "--out", str(out), "--engine", engine,
           "--workers", str(WORKERS), "--no-progress"]
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}  # a local Ray instance of its own
    with open(err_path, "wb") as err:
        # Its own session: a Ctrl-C of the test run does not reach it.  SIGINT at its default, as
        # under a terminal, whatever this test run inherited (a background job ignores it).
        proc = subprocess.Popen(cmd, cwd=REPO_ROOT, env=env, stdout=subprocess.DEVNULL, stderr=err,
                                start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    driver = psutil.Process(proc.pid)
    descendants: Descendants = {}
    try:
        deadline = time.monotonic() + 180
        while not _lines(out):
            assert proc.poll() is None, f"the run ended before a scene was done:\n{err_path.read_text()}"
            assert time.monotonic() < deadline, f"no scene done in time:\n{err_path.read_text()}"
            _record(driver, descendants)
            time.sleep(0.1)
        _record(driver, descendants)
        assert proc.poll() is None, "the run finished before the signal: make the dataset larger"
        proc.send_signal(sig)
        status = proc.wait(60)
        deadline = time.monotonic() + GONE_WITHIN_S
        while _alive(descendants) and time.monotonic() < deadline:
            time.sleep(0.2)
        return status, err_path.read_text(), out, descendants
    finally:
        for p in [driver, *(p for p, _ in descendants.values())]:
            try:
                p.kill()  # whatever the fix should have ended: a failing test leaks nothing
            except psutil.NoSuchProcess:
                pass


def _check_started(engine: str, descendants: Descendants) -> None:
    """The driver had really started what must end with it (else the test would prove nothing)."""
    cmdlines = [cmdline for _, cmdline in descendants.values()]
    if engine == "local":
        assert sum("forkserver" in c for c in cmdlines) == WORKERS + 1, cmdlines  # the server and its workers
        assert any("resource_tracker" in c for c in cmdlines), cmdlines
    else:
        assert any("raylet" in c for c in cmdlines), cmdlines
        # The raylet's agents: those that outlived a SIGKILLed driver before the watchdog.
        assert {"ray::DashboardAgent", "ray::RuntimeEnvAgent"} <= {c.strip() for c in cmdlines}, cmdlines


@pytest.mark.parametrize("engine", ["local", "ray"])
def test_sigterm_stops_the_run_keeps_its_results_and_leaves_no_process(engine, dataset, tmp_path):
    from shadowcorr_batch.runner import BatchOptions, plan_batch

    status, stderr, out, descendants = _signal_mid_run(engine, signal.SIGTERM, dataset, tmp_path)
    _check_started(engine, descendants)
    assert not (left := _alive(descendants)), f"still running after the driver's SIGTERM: {left}"
    assert status == 128 + signal.SIGTERM, stderr
    assert "terminated (SIGTERM)" in stderr and "run the same command again to resume" in stderr
    records = [json.loads(line) for line in _lines(out)]
    assert records and all(r["status"] == "ok" for r in records)
    # The next run skips exactly the scenes written.
    run, _ = plan_batch(dataset, out, BatchOptions())
    assert (run.skipped, len(run.todo), run.unreadable_lines) == (len(records), SCENES - len(records), 0)


def test_sigint_stops_the_run_with_status_130_keeps_its_results_and_leaves_no_process(dataset, tmp_path):
    # Ctrl-C: the same orderly stop as SIGTERM, told apart by its exit status and message.
    status, stderr, out, descendants = _signal_mid_run("local", signal.SIGINT, dataset, tmp_path)
    _check_started("local", descendants)
    assert not (left := _alive(descendants)), f"still running after the driver's SIGINT: {left}"
    assert status == 130, stderr
    assert "interrupted: finished scenes are in" in stderr and "terminated" not in stderr, stderr
    records = [json.loads(line) for line in _lines(out)]
    assert records and all(r["status"] == "ok" for r in records)


@pytest.mark.parametrize("engine", ["local", "ray"])
def test_sigkill_of_the_driver_leaves_no_process(engine, dataset, tmp_path):
    status, stderr, _, descendants = _signal_mid_run(engine, signal.SIGKILL, dataset, tmp_path)
    _check_started(engine, descendants)
    assert status == -signal.SIGKILL, stderr
    assert not (left := _alive(descendants)), f"still running after the driver's SIGKILL: {left}"
