"""Service settings, read from ``SHADOWCORR_*`` environment variables (pydantic-settings).

Every setting has a safe default for a single small machine; the container or the
``shadowcorr serve`` flags override them.  ``ServiceSettings.public_dict`` is what
``GET /info`` shows: everything except secrets.
"""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from shadowcorr.config import DEVICE_PATTERN

__all__ = ["ServiceSettings", "MiB"]

MiB = 1024 * 1024


class ServiceSettings(BaseSettings):
    """Configuration of the HTTP inference service (env prefix ``SHADOWCORR_``)."""

    # Other tools of the project may define SHADOWCORR_* variables of their own: ignore them.
    model_config = SettingsConfigDict(env_prefix="SHADOWCORR_", extra="ignore", frozen=True)

    # --- network
    host: str = Field("127.0.0.1", description="interface to listen on (0.0.0.0 in a container)")
    port: int = Field(8000, ge=0, le=65535, description="TCP port (0 = any free port)")

    # --- model and compute
    model_path: Path | None = Field(None, description="model file; unset = the packaged default model")
    workers: int = Field(2, ge=1, le=256, description="worker processes for decoding, prepare and assign")
    torch_threads: int = Field(1, ge=1, le=256, description="torch / BLAS threads in each worker process")
    device: str = Field("cpu", pattern=DEVICE_PATTERN, description="torch device of the network: cpu, cuda, cuda:N, mps")
    inference_threads: int = Field(1, ge=1, le=256, description="torch threads of the network in the main process")
    max_batch_size: int = Field(8, ge=1, le=1024, description="most scenes in one network forward pass")
    max_wait_ms: float = Field(10.0, ge=0, le=10_000, description="longest a scene waits for others to batch with")

    # --- admission and time limits
    queue_size: int = Field(32, ge=1, description="requests admitted at once (uploading, queued or running); more get 503")
    max_requests_per_client: int = Field(
        16, ge=1, description="requests one client address may have admitted at once; more get 429"
    )
    request_timeout_s: float = Field(120.0, gt=0, description="a request not finished after this gets 504")
    max_stage_seconds: float = Field(30.0, gt=0, description="a scene whose one stage of prepare or assign ran longer "
                                     "than this is refused (413 stage_too_slow) before its next stage starts")
    retry_after_s: int = Field(2, ge=0, description="Retry-After sent with 503 responses")
    graceful_shutdown_s: float = Field(30.0, ge=0, description="on SIGTERM, how long in-flight requests may finish")
    startup_timeout_s: float = Field(600.0, gt=0, description="longest a worker process may take to start and warm up")
    cancel_grace_s: float = Field(
        2.0, ge=0, description="a job whose request gave up (timeout, disconnect) may run this long before its worker is killed"
    )

    # --- connections and uploads (a slow or stalled client must not hold anything others need)
    max_connections: int = Field(256, ge=1, description="open connections at once; more are answered 503 and closed")
    header_timeout_s: float = Field(5.0, gt=0, description="longest a connection may take to send a request's headers (408 beyond)")
    keep_alive_s: float = Field(5.0, gt=0, description="idle keep-alive connections are closed after this")
    body_timeout_s: float = Field(300.0, gt=0, description="longest a request body may take to arrive (408 beyond)")
    body_grace_s: float = Field(5.0, ge=0, description="an upload may be slower than min_upload_bytes_per_s for its first seconds")
    min_upload_bytes_per_s: int = Field(
        32 * 1024, ge=0, description="an upload must average at least this rate after body_grace_s (408 below)"
    )
    max_upload_bytes_in_flight: int = Field(
        1024 * MiB, ge=1024, description="bytes of all bodies being received or processed at once; more get 503"
    )
    max_header_bytes: int = Field(64 * 1024, ge=1024, description="largest request line + headers (431 beyond)")
    spool_bytes: int = Field(1 * MiB, ge=0, description="bodies larger than this go to a temporary file, not memory")

    # --- input limits
    max_body_bytes: int = Field(128 * MiB, ge=1024, description="largest request body (413 beyond)")
    max_uncompressed_bytes: int = Field(512 * MiB, ge=1024, description="all bundle files together, after decompression")
    max_files: int = Field(64, ge=1, description="files in an archive / file parts in an upload")
    max_views: int = Field(16, ge=1, description="views per scene")
    max_pixels_per_view: int = Field(4096 * 4096, ge=1, description="width x height of one view")
    # prepare's cost grows about linearly with the segments (about 2,000 segments in 17 s on one
    # core, benchmarks/bench_scale.py); this bound, max_scene_points and max_stage_seconds keep a
    # cheap upload from holding a worker for long.
    max_segments: int = Field(500, ge=1, description="segments per scene (counted from the masks before prepare)")
    max_scene_points: int = Field(
        8_000_000, ge=1, description="instance pixels with valid depth in all views (the points prepare back-projects), "
        "or the points of a point-segment bundle (checked before its array is decompressed)"
    )
    # What one request may cost in memory is bounded up front by what the bundle declares:
    # decoded pixels (a few bytes of PNG can declare 4096 x 4096), mask runs (the blob
    # finder's work and memory grow with them, about 300 bytes a run) and points.
    max_scene_pixels: int = Field(
        64 * MiB, ge=1, description="width x height summed over all views, checked before any image is decoded"
    )
    max_mask_runs: int = Field(
        500_000, ge=1, description="runs of one instance id along the mask rows, summed over all views "
        "(a real mask has a few thousand; a speckled one millions)"
    )
    worker_memory_bytes: int = Field(
        6 * 1024 * MiB, ge=0, description="address-space limit (RLIMIT_AS) of each worker process, a last line of "
        "defence under the input limits; 0 = none"
    )

    # --- site maps
    maps_dir: Path | None = Field(None, description="directory of the site maps (/maps routes), one file per map; "
                                  "unset: the server keeps no maps")

    # --- security and logging
    auth_token: SecretStr | None = Field(None, description="when set, every route but /health needs 'Authorization: Bearer <token>'")
    allow_no_auth: bool = Field(
        False, description="serve without auth_token on a host that is not a loopback address; without this the "
        "service refuses to start there, so that a server reachable from other machines is never open by mistake")
    log_level: Literal["critical", "error", "warning", "info", "debug"] = Field(
        "info", description="least severe log messages the server writes: critical, error, warning, info or debug")

    @field_validator("auth_token", mode="before")
    @classmethod
    def _empty_token_is_none(cls, v: Any) -> Any:
        # SHADOWCORR_AUTH_TOKEN="" (a common way to "unset" a variable in compose files) means: no auth.
        return None if v is None or (isinstance(v, str) and v.strip() == "") else v

    @model_validator(mode="after")
    def _no_open_server_by_mistake(self) -> "ServiceSettings":
        if self.auth_token is None and not self.allow_no_auth and not _is_loopback(self.host):
            raise ValueError(
                f"refusing to listen on {self.host}, which other machines can reach, without authentication: "
                "set SHADOWCORR_AUTH_TOKEN (or pass --auth-token-file) to require a bearer token, "
                "or set SHADOWCORR_ALLOW_NO_AUTH=1 to serve without one"
            )
        return self

    @field_validator("log_level", mode="before")
    @classmethod
    def _lower(cls, v: Any) -> Any:
        return v.lower() if isinstance(v, str) else v

    def public_dict(self) -> dict[str, Any]:
        """Settings that are safe to show to any authenticated client (no secrets, no file-system paths)."""
        # /info names the model by name, version and checksum instead of model_path.
        data = self.model_dump(mode="json", exclude={"auth_token", "model_path", "maps_dir"})
        data["maps"] = self.maps_dir is not None
        data["auth"] = "bearer" if self.auth_token is not None else "none"
        return data


def _is_loopback(host: str) -> bool:
    """Whether ``host`` is reachable from this machine only (``localhost``, ``127.0.0.0/8``, ``::1``)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name other than localhost, or "" (every interface)
        return False
