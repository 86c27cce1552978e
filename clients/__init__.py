"""Python client of the ShadowCorr HTTP service, and the ``shadowcorr-client`` CLI.

::

    from shadowcorr_client import ShadowCorrClient

    with ShadowCorrClient("http://127.0.0.1:8000", token=None) as client:
        result = client.correspond("scene_bundle/", metrics=True)   # -> shadowcorr.result.Result
        print(result.labels, result.metrics)

Importing this package is light: it needs ``httpx`` only, never torch or the server.
``pip install ./clients`` installs the client alone (httpx and tqdm: no torch, numpy or
pydantic); results then come back as :class:`shadowcorr_client.result.ResultView`, and converting
Unreal-layout folders or ROS bags locally says which ``pip install`` adds the library.
With the library installed, results are :class:`shadowcorr.result.Result` and packing an
in-memory ``SceneBundle`` or converting data imports the matching parts of :mod:`shadowcorr`.
"""

from .client import DEFAULT_SERVER, DEFAULT_TIMEOUT, AsyncShadowCorrClient, RetryEvent, ShadowCorrClient
from .dataset import BagOptions, SceneSource, discover_scenes
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
from .result import ResultView
from .retry import NO_RETRY, RetryPolicy, parse_retry_after
from .request_body import BundleUpload, as_upload
from .bulk_upload import upload_scene, upload_scenes

__all__ = [
    "AsyncShadowCorrClient",
    "BagOptions",
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
    "ResultView",
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
