"""The client installed alone (``pip install ./clients`` in a fresh venv) against the real server.

The venv has no pip of its own (pip runs from the test's interpreter with ``--python``),
so its site-packages holds exactly what installing the client brought: httpx, tqdm and
their pure-Python dependencies -- no torch, numpy, pydantic or the library.  Every client
command that does not convert data must work there; converting an Unreal folder or a bag
must fail with the ``pip install`` to run.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import shadowcorr
from .harness import ServerProcess
from shadowcorr.io import write_bundle, write_bundle_archive

from .paths import REPO, SAMPLE_DIR
from .scenes import sphere_scene

pytestmark = pytest.mark.slow

TOKEN = "standalone-token-not-secret"
HEAVY = ("torch", "numpy", "scipy", "pydantic", "fastapi", "shadowcorr", "shadowcorr_service", "PIL")


def _site_packages(venv: Path) -> Path:
    (site,) = venv.glob("lib/python*/site-packages")
    return site


@pytest.fixture(scope="module")
def venv(tmp_path_factory) -> Path:
    """A fresh venv with only ``pip install ./clients`` in it (the pip cache is reused)."""
    root = tmp_path_factory.mktemp("standalone")
    # Installed from a copy: the in-tree build would leave build/ and egg-info in the checkout.
    shutil.copytree(REPO / "clients", root / "clients", ignore=shutil.ignore_patterns("__pycache__", "build", "*.egg-info"))
    venv = root / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    subprocess.run([sys.executable, "-m", "pip", "--python", str(venv / "bin" / "python"), "install", "--quiet",
                    str(root / "clients")], check=True, timeout=240)
    return venv


@pytest.fixture(scope="module")
def server():
    with ServerProcess(env={"SHADOWCORR_WORKERS": "1", "SHADOWCORR_LOG_LEVEL": "warning",
                            "SHADOWCORR_AUTH_TOKEN": TOKEN}, token=TOKEN) as proc:
        yield proc


def _clean_env() -> dict[str, str]:
    """This environment without SHADOWCORR_* settings and PYTHON* paths (which could reach the library)."""
    return {k: v for k, v in os.environ.items() if not k.startswith(("SHADOWCORR_", "PYTHON"))}


def client(venv: Path, *args: str, cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """``shadowcorr-client ARGS`` of the standalone venv, outside the checkout, without SHADOWCORR_* settings."""
    return subprocess.run([str(venv / "bin" / "shadowcorr-client"), *args], cwd=cwd, env={**_clean_env(), **(env or {})},
                          capture_output=True, text=True, timeout=120)


def test_installs_only_light_pure_python_packages(venv) -> None:
    site = _site_packages(venv)
    installed = {p.name.split("-")[0].lower() for p in site.glob("*.dist-info")}
    assert {"httpx", "tqdm", "shadowcorr_client"} <= installed
    assert not [h for h in HEAVY if (site / h).exists() or h.lower() in installed]
    size_mb = sum(f.stat().st_size for f in site.rglob("*") if f.is_file()) / 2**20
    print(f"standalone client install: {size_mb:.1f} MB in site-packages", file=sys.stderr)
    assert size_mb < 30
    assert not list(site.rglob("*.so")), "a compiled extension is not pure Python"
    probe = subprocess.run([str(venv / "bin" / "python"), "-c", "import shadowcorr_client, sys; import shadowcorr"],
                           cwd=venv, capture_output=True, text=True, env=_clean_env())
    assert "No module named 'shadowcorr'" in probe.stderr  # clients imports; the library is not there


def test_client_commands_against_the_real_server(venv, server, tmp_path) -> None:
    scene = sphere_scene([[0.0, 0.0, 45.0], [160.0, 30.0, 45.0]], [44.0, 40.0], width=160, height_px=90)
    data = tmp_path / "data"
    bundle = write_bundle(scene, data / "spheres")
    write_bundle_archive(scene, data / "archived.zip")
    expected = shadowcorr.correspond(scene).labels  # the library, in this process, on the same scene

    # Global options before the command, token from the environment after it.
    r = client(venv, "--server", server.url, "--token", TOKEN, "health", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["ready"] is True
    r = client(venv, "info", "--server", server.url, cwd=tmp_path, env={"SHADOWCORR_TOKEN": TOKEN})
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["model"]["name"]
    r = client(venv, "--server", server.url, "info", cwd=tmp_path)  # no token: the server's own 401 code
    assert r.returncode == 1 and "401 unauthorized" in r.stderr

    out = tmp_path / "result.json"
    r = client(venv, "--server", server.url, "-v", "correspond", str(bundle), "--metrics", "--out", str(out),
               "--token", TOKEN, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    result = json.loads(out.read_text())
    assert [s["object"] for s in result["segments"]] == expected
    assert f"-> {len(set(expected))} objects" in r.stdout

    # --cameras on a bundle is refused, not ignored.
    r = client(venv, "--server", server.url, "--token", TOKEN, "correspond", str(bundle), "--cameras", "0,2",
               cwd=tmp_path)
    assert r.returncode == 2 and "--cameras" in r.stderr and "holds none" in r.stderr

    # A dataset with bundles (sent) and an Unreal folder (needs the library: a clear error per scene).
    unreal = data / "unreal"
    unreal.mkdir()
    for name in ("Set2001_Depth_0.exr", "Set2001_Segment_0.png"):
        (unreal / name).symlink_to(SAMPLE_DIR / name)
    results = tmp_path / "results.jsonl"
    r = client(venv, "upload-dataset", str(data), "--out", str(results), "--no-progress", "--server", server.url,
               "--token", TOKEN, cwd=tmp_path)
    assert r.returncode == 1  # one scene failed
    records = {rec["scene"]: rec for rec in map(json.loads, results.read_text().splitlines())}
    assert records["spheres"]["status"] == records["archived.zip"]["status"] == "ok"
    failed = records["unreal/Set2001"]
    assert failed["status"] == "failed" and "pip install shadowcorr" in failed["error"]["message"]
    assert "pip install shadowcorr" in r.stderr
    assert [s["object"] for s in records["archived.zip"]["result"]["segments"]] == expected
