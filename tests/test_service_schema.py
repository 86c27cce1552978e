"""Schemathesis (``--checks all``) against a real server on 127.0.0.1: the OpenAPI schema and the service agree.

Every check is on: no 5xx, every status and header documented, every body matching
its schema, schema-invalid requests refused, schema-valid ones accepted (with the two
exceptions of ``tests/schemathesis.toml``, which OpenAPI cannot express).  The run is
bounded by ``--max-time``.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from .harness import ServerProcess

CONFIG = Path(__file__).with_name("schemathesis.toml")
MAX_TIME_S = 40


def test_schemathesis_finds_no_failure(tmp_path):
    st = shutil.which("st", path=str(Path(sys.executable).parent)) or shutil.which("st")
    if st is None:
        pytest.skip("schemathesis is not installed (dev extra)")
    with ServerProcess(["--workers", "1", "--max-wait-ms", "0"]) as server:
        run = subprocess.run(
            [st, "--config-file", str(CONFIG), "run", server.url + "/openapi.json", "--checks", "all",
             "--workers", "1", "--max-time", str(MAX_TIME_S), "--no-color"],
            capture_output=True, text=True, timeout=MAX_TIME_S + 240,
            cwd=tmp_path,  # schemathesis keeps a cache in its working directory
        )
        log = server.log_tail(400)
    report = run.stdout[-8000:] + run.stderr[-2000:]
    assert run.returncode == 0, report
    assert "Test cases:" in run.stdout and "failure" not in run.stdout.split("Test cases:")[1], report
    assert "Traceback" not in log, log
