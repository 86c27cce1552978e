"""Run the service under uvicorn: ``serve(settings)`` (used by ``python -m shadowcorr_service`` and ``shadowcorr serve``)."""

from __future__ import annotations

import logging
import math
from types import FrameType

from .settings import ServiceSettings

__all__ = ["serve", "SHUTDOWN_MARGIN_S"]

#: Seconds between the application's shutdown deadline (503 to what is still running)
#: and uvicorn's (cancel whatever is left): time to write those answers.
SHUTDOWN_MARGIN_S = 3.0


def serve(settings: ServiceSettings | None = None) -> None:
    """Start the HTTP service and block until it is stopped (SIGINT / SIGTERM).

    One uvicorn process serves the event loop; CPU work happens in the service's own
    worker processes (``settings.workers``).  On shutdown uvicorn stops accepting
    connections and lets in-flight requests finish for up to ``graceful_shutdown_s``;
    meanwhile open connections stay open and every request read on them is answered
    JSON 503 ``shutting_down`` with ``Connection: close``; requests still running at the
    end of the grace period get the same 503; then the lifespan stops the batcher and
    the workers.
    """
    import uvicorn

    from .app import create_app
    from .protocol import guarded_protocol

    settings = settings or ServiceSettings()
    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s")
    logging.getLogger("shadowcorr").setLevel(settings.log_level.upper())
    app = create_app(settings)
    runtime = app.state.runtime
    config = uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        lifespan="on",
        # The application answers requests that outlive the grace period itself (JSON 503);
        # uvicorn's own cut-off, which cancels them without an answer, comes a little later.
        timeout_graceful_shutdown=math.ceil(settings.graceful_shutdown_s + SHUTDOWN_MARGIN_S),
        timeout_keep_alive=settings.keep_alive_s,  # type: ignore[arg-type]
        h11_max_incomplete_event_size=settings.max_header_bytes,
        http=guarded_protocol(  # type: ignore[arg-type]
            header_timeout_s=settings.header_timeout_s,
            max_connections=settings.max_connections,
            max_header_bytes=settings.max_header_bytes,
            retry_after_s=settings.retry_after_s,
            graceful_shutdown_s=settings.graceful_shutdown_s,
        ),
        server_header=False,
    )

    class _Server(uvicorn.Server):
        def handle_exit(self, sig: int, frame: FrameType | None) -> None:
            runtime.begin_shutdown()  # in-flight requests learn their deadline
            super().handle_exit(sig, frame)

    _Server(config).run()
