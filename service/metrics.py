"""Prometheus metrics of one service instance (``GET /metrics``).

A private ``CollectorRegistry`` per app: two apps in one process (tests, embedding)
never fight over the global registry.  Label sets are bounded (route templates, status
codes, stage names, error codes) so a client cannot grow the series count.
"""

from __future__ import annotations

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram, generate_latest

__all__ = ["ServiceMetrics", "CONTENT_TYPE_LATEST", "ROUTES", "route_label"]

#: Routes with their own label; everything else is "other".
ROUTES = ("/correspond", "/health", "/info", "/metrics", "/docs", "/openapi.json")

_LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0, 7.5, 10.0, 20.0, 30.0, 60.0, 120.0)
_BATCH_BUCKETS = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 128, 256, 512, 1024)


def route_label(path: str) -> str:
    return path if path in ROUTES else "other"


class ServiceMetrics:
    """All metric objects of the service, registered in one private registry."""

    def __init__(self) -> None:
        r = self.registry = CollectorRegistry(auto_describe=True)
        self.requests = Counter(
            "shadowcorr_http_requests", "HTTP requests by route and status code", ["route", "status"], registry=r
        )
        self.request_latency = Histogram(
            "shadowcorr_http_request_duration_seconds",
            "HTTP request latency, from the first byte received to the response start",
            ["route"],
            buckets=_LATENCY_BUCKETS,
            registry=r,
        )
        self.stage_latency = Histogram(
            "shadowcorr_stage_duration_seconds",
            "time per /correspond stage: read_body, queue (waiting for a worker), decode, prepare, "
            "batch_wait (waiting for the network), network (one forward pass, per batch), assign, baseline, total",
            ["stage"],
            buckets=_LATENCY_BUCKETS,
            registry=r,
        )
        self.errors = Counter("shadowcorr_errors", "error responses by error code", ["code"], registry=r)
        self.queue_depth = Gauge(
            "shadowcorr_queue_depth", "/correspond requests admitted (body received) and not finished, or whose worker job still runs", registry=r
        )
        self.upload_bytes = Gauge(
            "shadowcorr_upload_bytes_in_flight", "bytes of request bodies being received or processed", registry=r
        )
        self.pool_pending = Gauge("shadowcorr_worker_queue_depth", "jobs waiting for a worker process", registry=r)
        self.batcher_pending = Gauge("shadowcorr_batcher_queue_depth", "scenes waiting for the network", registry=r)
        self.batch_size = Histogram(
            "shadowcorr_batch_size", "scenes per network forward pass", buckets=_BATCH_BUCKETS, registry=r
        )
        self.workers_ready = Gauge("shadowcorr_workers_ready", "worker processes started, warmed up and idle or busy", registry=r)
        self.worker_restarts = Counter(
            "shadowcorr_worker_restarts", "worker processes replaced after dying or being stopped", registry=r
        )
        self.ready = Gauge("shadowcorr_ready", "1 when the model is loaded and warmed up and a worker is ready", registry=r)

    def render(self) -> bytes:
        return generate_latest(self.registry)
