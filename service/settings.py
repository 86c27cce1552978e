"""Service settings, read from ``SHADOWCORR_*`` environment variables (pydantic-settings).

Every setting has a safe default for a single small machine; the container or the
``shadowcorr serve`` flags override them.  ``ServiceSettings.public_dict`` is what
``GET /info`` shows: everything except secrets.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

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
    device: str = Field("cpu", pattern=r"^(cpu|cuda(:\d+)?|mps)$", description="torch device of the network: cpu, cuda, cuda:N")
    inference_threads: int = Field(1, ge=1, le=256, description="torch threads of the network in the main process")
    max_batch_size: int = Field(8, ge=1, le=1024, description="most scenes in one network forward pass")
    max_wait_ms: float = Field(10.0, ge=0, le=10_000, description="longest a scene waits for others to batch with")

    # --- admission and time limits
    queue_size: int = Field(32, ge=1, description="requests admitted at once (uploading, queued or running); more get 503")
    request_timeout_s: float = Field(120.0, gt=0, description="a request not finished after this gets 504")
    retry_after_s: int = Field(2, ge=0, description="Retry-After sent with 503 responses")
    graceful_shutdown_s: float = Field(30.0, ge=0, description="on SIGTERM, how long in-flight requests may finish")
    startup_timeout_s: float = Field(600.0, gt=0, description="longest a worker process may take to start and warm up")

    # --- input limits
    max_body_bytes: int = Field(128 * MiB, ge=1024, description="largest request body (413 beyond)")
    max_uncompressed_bytes: int = Field(512 * MiB, ge=1024, description="all bundle files together, after decompression")
    max_files: int = Field(64, ge=1, description="files in an archive / file parts in an upload")
    max_views: int = Field(16, ge=1, description="views per scene")
    max_pixels_per_view: int = Field(4096 * 4096, ge=1, description="width x height of one view")
    max_segments: int = Field(2000, ge=1, description="segments per scene")

    # --- security and logging
    auth_token: SecretStr | None = Field(None, description="when set, every route but /health needs 'Authorization: Bearer <token>'")
    log_level: Literal["critical", "error", "warning", "info", "debug"] = Field(
        "info", description="least severe log messages the server writes: critical, error, warning, info or debug")

    @field_validator("auth_token", mode="before")
    @classmethod
    def _empty_token_is_none(cls, v: Any) -> Any:
        # SHADOWCORR_AUTH_TOKEN="" (a common way to "unset" a variable in compose files) means: no auth.
        return None if v is None or (isinstance(v, str) and v.strip() == "") else v

    @field_validator("log_level", mode="before")
    @classmethod
    def _lower(cls, v: Any) -> Any:
        return v.lower() if isinstance(v, str) else v

    def public_dict(self) -> dict[str, Any]:
        """Settings that are safe to show to any authenticated client (no secrets)."""
        data = self.model_dump(mode="json", exclude={"auth_token"})
        data["auth"] = "bearer" if self.auth_token is not None else "none"
        return data
