"""Run the service under uvicorn: ``serve(settings)`` (used by ``python -m service`` and ``shadowcorr serve``)."""

from __future__ import annotations

import logging
import math

from .settings import ServiceSettings

__all__ = ["serve"]


def serve(settings: ServiceSettings | None = None) -> None:
    """Start the HTTP service and block until it is stopped (SIGINT / SIGTERM).

    One uvicorn process serves the event loop; CPU work happens in the service's own
    worker processes (``settings.workers``).  On shutdown uvicorn stops accepting
    connections, lets in-flight requests finish for up to ``graceful_shutdown_s``, then
    the lifespan stops the batcher and the workers.
    """
    import uvicorn

    from .app import create_app

    settings = settings or ServiceSettings()
    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s")
    logging.getLogger("shadowcorr").setLevel(settings.log_level.upper())
    app = create_app(settings)
    config = uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        lifespan="on",
        timeout_graceful_shutdown=math.ceil(settings.graceful_shutdown_s),
        server_header=False,
    )
    uvicorn.Server(config).run()
