"""ShadowCorr HTTP inference service (FastAPI + uvicorn).

``create_app(settings)`` builds the ASGI app; ``serve(settings)`` runs it under uvicorn;
``shadowcorr_service.cli`` provides ``shadowcorr serve``.  Settings come from ``SHADOWCORR_*``
environment variables (``ServiceSettings``).  Heavy modules (torch, the engine) are
imported only when an app is created, so ``import service`` stays cheap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from shadowcorr._lazy import lazy_exports

if TYPE_CHECKING:  # pragma: no cover
    from fastapi import FastAPI

    from .server import serve
    from .settings import ServiceSettings

__all__ = ["ServiceSettings", "create_app", "serve"]
# Lazy, so that `shadowcorr --help` can list `serve` without loading pydantic-settings and uvicorn.
__getattr__, __dir__ = lazy_exports(__name__, {"serve": "server", "ServiceSettings": "settings"}, globals())


def create_app(settings: "ServiceSettings | None" = None) -> "FastAPI":
    from .app import create_app as _create_app

    return _create_app(settings)
