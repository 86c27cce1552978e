"""Optional packages (the extras): a test that needs one is skipped without it, and only that test."""

from __future__ import annotations

import importlib

import pytest


def importable(module: str) -> bool:
    """Whether ``module`` imports here (MuJoCo through the library, which picks a headless GL first)."""
    try:
        if module == "mujoco":
            from shadowcorr.synth.physics import import_mujoco

            import_mujoco()
        else:
            importlib.import_module(module)
    except ImportError:
        return False
    return True


needs_mujoco = pytest.mark.skipif(not importable("mujoco"), reason='needs MuJoCo: pip install "shadowcorr[synth]"')
needs_ray = pytest.mark.skipif(not importable("ray"), reason='needs Ray: pip install "shadowcorr[ray]"')
