"""Packaging: every importable name of the distribution starts with ``shadowcorr``, so a robot
stack's own ``service`` or ``batch`` module cannot shadow the service or the batch runner."""

from __future__ import annotations

import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import httpx
import pytest

from tests.harness import ServerProcess

REPO = Path(__file__).resolve().parents[1]
#: Modules a user's working directory may well hold; each one fails loudly when imported.
SHADOWING = ("service", "batch", "clients")


def _shadowing_dir(tmp_path: Path) -> Path:
    for name in SHADOWING:
        (tmp_path / f"{name}.py").write_text(f"raise SystemExit('the user\\'s own {name}.py was imported')\n")
    return tmp_path


def test_package_list_matches_the_folders():
    """``pyproject.toml`` lists the packages by hand (the folders are mapped to new names): every
    library folder with an ``__init__.py`` is in the list, and nothing else is."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    on_disk = {str(p.parent.relative_to(REPO)).replace("/", ".") for p in (REPO / "shadowcorr").rglob("__init__.py")}
    mapped = set(config["package-dir"])
    assert set(config["packages"]) == on_disk | mapped
    for name, folder in config["package-dir"].items():
        assert name.startswith("shadowcorr_") and (REPO / folder / "__init__.py").is_file()


@pytest.mark.slow
def test_wheel_holds_only_shadowcorr_packages(tmp_path):
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                    str(tmp_path), str(REPO)], check=True, timeout=300, capture_output=True)
    (wheel,) = tmp_path.glob("shadowcorr-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == {"shadowcorr", "shadowcorr_service", "shadowcorr_client", "shadowcorr_batch"}
    assert "shadowcorr/models/default.safetensors" in names
    assert "shadowcorr_service/app.py" in names and "shadowcorr_client/cli.py" in names


def test_serve_from_a_directory_with_its_own_service_and_batch(tmp_path):
    """``python -m shadowcorr.cli serve`` puts the working directory first on ``sys.path``; the
    server must still start and answer."""
    cwd = _shadowing_dir(tmp_path)
    server = ServerProcess(["--workers", "1"], command=[sys.executable, "-m", "shadowcorr.cli", "serve"], cwd=cwd)
    try:
        server.start()
        assert httpx.get(server.url + "/health", timeout=10).json()["status"] == "ok"
    finally:
        server.stop()


@pytest.mark.parametrize("argv", [["-m", "shadowcorr.cli", "batch", "--help"], ["-m", "shadowcorr_client", "--help"]])
def test_batch_and_client_from_a_directory_with_shadowing_modules(tmp_path, argv):
    cwd = _shadowing_dir(tmp_path)
    r = subprocess.run([sys.executable, *argv], cwd=cwd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "usage:" in r.stdout and "was imported" not in r.stdout + r.stderr
