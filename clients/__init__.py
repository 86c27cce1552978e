"""Python client of the ShadowCorr HTTP service, and the ``shadowcorr-client`` CLI.

::

    from clients import ShadowCorrClient

    with ShadowCorrClient("http://127.0.0.1:8000", token=None) as client:
        result = client.correspond("scene_bundle/", metrics=True)   # -> shadowcorr.result.Result
        print(result.labels, result.metrics)

Importing this package is light: it needs ``httpx`` (and ``pydantic`` once a result is
parsed), never torch or the server.  Packing an in-memory ``SceneBundle`` or converting
Unreal-layout data imports the matching parts of :mod:`shadowcorr` on first use.
"""

from .client import DEFAULT_SERVER, DEFAULT_TIMEOUT, AsyncShadowCorrClient, RetryEvent, ShadowCorrClient
from .dataset import SceneSource, discover_scenes
from .errors import (
    BundleInputError,
    ClientError,
    ConnectionFailed,
    InvalidResponse,
    ResponseError,
    ServerError,
    ShadowCorrError,
)
from .records import UploadRecord, read_records
from .retry import NO_RETRY, RetryPolicy, parse_retry_after
from .upload import BundleUpload, as_upload
from .uploader import upload_scene, upload_scenes

__all__ = [
    "AsyncShadowCorrClient",
    "BundleInputError",
    "BundleUpload",
    "ClientError",
    "ConnectionFailed",
    "DEFAULT_SERVER",
    "DEFAULT_TIMEOUT",
    "InvalidResponse",
    "NO_RETRY",
    "ResponseError",
    "RetryEvent",
    "RetryPolicy",
    "SceneSource",
    "ServerError",
    "ShadowCorrClient",
    "ShadowCorrError",
    "UploadRecord",
    "as_upload",
    "discover_scenes",
    "parse_retry_after",
    "read_records",
    "upload_scene",
    "upload_scenes",
]
