"""The functions worker processes run: decode + prepare, assign, the baseline, warm-up.

Everything here executes in a *spawned* worker process (see ``workers.py``), so these
are module-level functions of plain picklable arguments.  Input errors leave as
:class:`~shadowcorr_service.errors.JobError` (status, code, message, problems), which survives
pickling intact; anything unexpected is logged here, with its traceback, and becomes
a 500 without internals.

Uploaded bytes are only ever *parsed* (multipart, zip/tar, PNG, EXR, npy without
pickle): nothing that came from a client is unpickled.  The only pickles crossing the
process boundary are the service's own objects (``VoxelScene``, arrays, results).
"""

from __future__ import annotations

import io
import logging
import os
import signal
import sys
import threading
import tempfile
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shadowcorr.config import ShadowCorrConfig
from shadowcorr.errors import BundleError
from shadowcorr.io import load_bundle, load_bundle_from_parts
from shadowcorr.pipeline import assign, baseline_embeddings, prepare
from shadowcorr.result import ModelInfo
from shadowcorr.errors import DepthRangeError, SceneLimitError
from shadowcorr.stages import VoxelScene

from .errors import JobError
from .limits import RequestLimits, Upload, check_instances
from .multipart import BodyError, content_kind, parse_body
from .synthetic import synthetic_bundle

__all__ = [
    "Artefact",
    "ExportJob",
    "Prepared",
    "init_worker",
    "hello",
    "decode_and_prepare",
    "assign_scene",
    "baseline",
    "warmup_scene",
]

log = logging.getLogger("shadowcorr.service.worker")


@dataclass
class Prepared:
    """What ``decode_and_prepare`` sends back to the main process."""

    scene: VoxelScene
    decode_ms: float
    prepare_ms: float


# --------------------------------------------------------------------------- process setup
def init_worker(torch_threads: int, parent_pid: int, warm_up: bool = True, memory_bytes: int = 0) -> None:
    """Initializer of every worker process: memory cap, threads, signals, orphan guard, warm-up.

    * ``memory_bytes`` (> 0) caps the process's address space (``RLIMIT_AS``): the input
      limits bound what a request may cost up front, and a case they miss then fails an
      allocation (MemoryError: 413 ``too_large``, or a crashed and replaced worker) in
      this process instead of driving the machine into its OOM killer.

    * torch and BLAS get ``torch_threads`` threads: the pool already runs one scene per
      core, so more threads per worker only oversubscribe the CPU.
    * SIGINT is ignored: Ctrl-C in a terminal reaches the whole process group, and the
      main process must stay in charge of draining in-flight work.
    * a daemon thread exits the worker if the main process disappears (SIGKILL), so no
      orphan keeps memory or CPU.
    * one ``prepare`` + ``assign`` of a small synthetic scene: the first call of each
      stage pays for lazy imports and caches; warmed workers answer the first request
      as fast as the next.
    """
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s worker[%(process)d] %(levelname)s %(message)s")
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if memory_bytes > 0:
        import resource

        try:
            resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))
        except (ValueError, OSError) as e:  # some platforms (macOS) refuse an address-space limit
            log.warning("worker_memory_bytes not applied: %s", e)
    import torch

    torch.set_num_threads(torch_threads)
    try:  # numpy's BLAS pool too (threadpoolctl ships with scikit-learn)
        from threadpoolctl import threadpool_limits

        threadpool_limits(torch_threads)
    except Exception:  # pragma: no cover - optional
        pass

    def _watch_parent() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(0)
            time.sleep(1.0)

    threading.Thread(target=_watch_parent, name="parent-watch", daemon=True).start()
    if warm_up:
        scene = prepare(synthetic_bundle(name="warmup"))
        assign(scene, baseline_embeddings(scene))


def hello() -> int:
    """First job of every worker: returns its pid once the initializer (warm-up) is done."""
    return os.getpid()


# --------------------------------------------------------------------------- jobs
def _load(upload: Upload, content_type: str, limits: RequestLimits):
    try:
        if content_kind(content_type) == "archive" and upload.path is not None:
            # A large bare archive is read from its file: only the members it needs are
            # ever decompressed, and the archive itself never has to be in memory.
            return load_bundle(Path(upload.path), limits=limits.bundle)
        parsed = parse_body(upload.read(), content_type, max_files=limits.bundle.max_files)
    except BodyError as e:
        code = "unsupported_media_type" if e.status == 415 else "bad_multipart"
        raise JobError(e.status, code, str(e), [{"loc": e.loc, "msg": str(e)}]) from None
    except BundleError as e:
        raise JobError(422, "invalid_bundle", str(e), e.to_dicts()) from None
    except FileNotFoundError:  # the request ended (and its upload was deleted) before the job started
        raise JobError(400, "client_disconnected", "the request ended before its upload was read") from None
    try:
        if parsed.archive is not None:
            return load_bundle(parsed.archive, limits=limits.bundle)
        return load_bundle_from_parts(parsed.manifest, parsed.files, limits=limits.bundle)
    except BundleError as e:
        raise JobError(422, "invalid_bundle", str(e), e.to_dicts()) from None


#: Error code of a :class:`SceneLimitError`, by the limit it names.
_LIMIT_CODES = {"max_segments": "too_many_segments", "max_voxels": "too_many_voxels", "max_stage_seconds": "stage_too_slow",
                "max_scene_pixels": "too_many_pixels", "max_scene_points": "too_many_points"}


def _guarded(what: str, fn, *args):
    """Run ``fn``: input errors pass through, the rest is logged and becomes a clean JobError.

    The public job functions below call this instead of being decorated, so that pickle
    (which finds functions by qualified name) sends the guarded function to the worker.
    """
    try:
        return fn(*args)
    except JobError:
        raise
    except SceneLimitError as e:  # a scene over a size limit, or a stage too slow: refused before the next stage
        code = _LIMIT_CODES.get(e.limit, "scene_too_large")
        raise JobError(413, code, str(e), [{"loc": "scene", "msg": str(e)}]) from None
    except DepthRangeError as e:  # nearly every segment lost its depth: wrong units or max_depth
        raise JobError(422, "no_valid_depth", str(e), [{"loc": "manifest.units", "msg": str(e)}]) from None
    except MemoryError:
        raise JobError(413, "too_large", f"{what}: the scene needs more memory than this service has") from None
    except ValueError as e:  # the engine's way of saying "this input cannot be processed"
        raise JobError(422, "unprocessable_scene", f"{what}: {e}", [{"loc": "scene", "msg": str(e)}]) from None
    except Exception as e:
        log.exception("%s failed", what)
        raise JobError(500, "internal_error", f"{what} failed ({type(e).__name__}); see the server log") from None


@dataclass(frozen=True)
class Artefact:
    """What a request asked for instead of the result JSON (``?format=``), see ``shadowcorr.export``."""

    format: str  # bag | ply | rrd
    frame_id: str = "map"
    storage: str = "mcap"


@dataclass
class ExportJob:
    """An artefact and the upload its bundle is read from again (the worker that assigns has no bundle)."""

    artefact: Artefact
    upload: Upload
    content_type: str
    limits: RequestLimits


def _load_checked(upload: Upload, content_type: str, config: ShadowCorrConfig, limits: RequestLimits):
    bundle = _load(upload, content_type, limits)
    check_instances(bundle, limits, config.min_blob_pixels)
    return bundle


def _prepare_checked(bundle, config: ShadowCorrConfig, limits: RequestLimits) -> VoxelScene:
    # The library checks the segment count right after cutting, before any heavy stage.
    return prepare(bundle, config.with_options(max_segments=min(config.max_segments, limits.max_segments)))


def _decode_and_prepare(upload: Upload, content_type: str, config: ShadowCorrConfig, limits: RequestLimits) -> Prepared:
    t0 = time.perf_counter()
    bundle = _load_checked(upload, content_type, config, limits)
    t1 = time.perf_counter()
    scene = _prepare_checked(bundle, config, limits)
    t2 = time.perf_counter()
    return Prepared(scene=scene, decode_ms=(t1 - t0) * 1e3, prepare_ms=(t2 - t1) * 1e3)


def _artefact_bytes(result, bundle, artefact: Artefact) -> bytes:
    """The export as one body: a ``.rrd`` file as it is; a bag or PLY directory as a zip, with the result JSON."""
    from shadowcorr.export import export

    with tempfile.TemporaryDirectory(prefix="shadowcorr-export-") as tmp:
        out = Path(tmp) / (f"{result.scene}.rrd" if artefact.format == "rrd" else f"{result.scene}_{artefact.format}")
        export(result, bundle, artefact.format, out, frame_id=artefact.frame_id, storage=artefact.storage)
        if out.is_file():
            return out.read_bytes()
        body = io.BytesIO()
        with zipfile.ZipFile(body, "w", compression=zipfile.ZIP_DEFLATED) as archive:
            for path in sorted(out.iterdir()):
                archive.write(path, f"{out.name}/{path.name}")
            archive.writestr("result.json", result.model_dump_json(indent=1))
        return body.getvalue()


def _assign_scene(
    scene: VoxelScene,
    embeddings: np.ndarray,
    config: ShadowCorrConfig,
    model: ModelInfo | None,
    metrics: bool,
    extra_timings: dict[str, float],
    started: float | None,
    export: ExportJob | None = None,
    bundle=None,
) -> bytes:
    result = assign(scene, embeddings, config, model=model, metrics=metrics)
    result.timings_ms.update({k: round(v, 3) for k, v in extra_timings.items()})
    if started is not None:  # the whole request as the service saw it: body, queues, decode, batch, network
        # time.monotonic is CLOCK_MONOTONIC, one clock for every process on the machine.
        result.timings_ms["total"] = round((time.monotonic() - started) * 1e3, 3)
    if export is None:
        return result.model_dump_json().encode()
    if bundle is None:  # the bundle, read again under the same limits, supplies the cameras and images
        bundle = _load(export.upload, export.content_type, export.limits)
    return _artefact_bytes(result, bundle, export.artefact)


def _baseline(upload: Upload, content_type: str, config: ShadowCorrConfig, limits: RequestLimits, metrics: bool,
              extra_timings: dict[str, float], started: float | None, artefact: Artefact | None = None) -> bytes:
    """A method without a network ('projection', 'meanshift'): no batcher; one job does it all."""
    t0 = time.perf_counter()
    bundle = _load_checked(upload, content_type, config, limits)
    decode_ms = (time.perf_counter() - t0) * 1e3
    scene = _prepare_checked(bundle, config, limits)
    export = ExportJob(artefact, upload, content_type, limits) if artefact is not None else None
    return _assign_scene(scene, baseline_embeddings(scene), config, None, metrics,
                         {**extra_timings, "decode": decode_ms}, started, export, bundle)


def _warmup_scene() -> VoxelScene:
    """A prepared synthetic scene, for the network's warm-up forward pass in the main process."""
    return prepare(synthetic_bundle(name="warmup"))


def decode_and_prepare(upload: Upload, content_type: str, config: ShadowCorrConfig, limits: RequestLimits) -> Prepared:
    """Parse the upload, load and check the bundle, run ``prepare``."""
    return _guarded("decoding and preparing the scene", _decode_and_prepare, upload, content_type, config, limits)


def assign_scene(
    scene: VoxelScene,
    embeddings: np.ndarray,
    config: ShadowCorrConfig,
    model: ModelInfo | None,
    metrics: bool,
    extra_timings: dict[str, float],
    started: float | None = None,
    export: ExportJob | None = None,
) -> bytes:
    """Cluster the embeddings and label the segments; returns the Result JSON bytes (or ``export``'s artefact).

    ``started`` (``time.monotonic()`` when the request began) makes ``timings_ms.total``
    the request's wall time in the service.
    """
    return _guarded("assigning objects", _assign_scene, scene, embeddings, config, model, metrics, extra_timings,
                    started, export)


def baseline(upload: Upload, content_type: str, config: ShadowCorrConfig, limits: RequestLimits, metrics: bool,
             extra_timings: dict[str, float], started: float | None = None, artefact: Artefact | None = None) -> bytes:
    """Decode, prepare and assign with a method without a network; returns the Result JSON bytes (or the artefact)."""
    return _guarded(f"method {config.method!r}", _baseline, upload, content_type, config, limits, metrics,
                    extra_timings, started, artefact)


def warmup_scene() -> VoxelScene:
    """A prepared synthetic scene for the network warm-up."""
    return _guarded("warm-up", _warmup_scene)
