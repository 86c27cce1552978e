"""Training data: voxel scenes prepared once from bundle directories and cached as ``.npz``.

Preparing a scene (segments, shadows, consensus voxels, segment-id embeddings) costs
seconds; the network step costs a fraction of that.  So every bundle is prepared exactly
once with :func:`shadowcorr.pipeline.prepare` - the same code path as inference - and
stored together with its per-voxel training target (:func:`shadowcorr.evaluation.voxel_truth`,
the object whose segments give the voxel the most confidence).  Later runs and epochs
read the cache.

Cache files are plain ``.npz`` archives of numeric and unicode arrays, written and read
with ``allow_pickle=False`` (no code can hide in them).  The file name is the bundle
directory name plus a hash of (absolute bundle path, manifest size and mtime, the full
``ShadowCorrConfig``, the cache format version): a changed configuration or a
regenerated bundle gets a new entry instead of stale data.

Preparation runs in spawned worker processes (one torch thread each, the workers fill the
cores) with a tqdm bar.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..config import ShadowCorrConfig
from ..stages import VoxelScene

__all__ = ["TrainScene", "find_bundles", "cache_key", "save_scene", "load_scene", "prepare_scenes", "default_cache_dir"]

CACHE_FORMAT = "shadowcorr-train-cache-1"

# VoxelScene array fields stored as they are.
_ARRAYS = (
    "segment_view", "segment_instance", "segment_component", "segment_num_points", "segment_centroid",
    "segment_bbox_min", "segment_bbox_max", "voxel_index", "gamma", "features", "member_voxel", "member_segment",
    "member_confidence", "orphan_segment", "orphan_index",
)  # fmt: skip


@dataclass
class TrainScene:
    """A prepared scene with its training target, as the trainer needs it."""

    path: str  # the bundle directory it came from
    scene: VoxelScene
    target: np.ndarray  # (V,) int64 ground-truth object per voxel

    @property
    def num_voxels(self) -> int:
        return self.scene.num_voxels


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/shadowcorr/voxel_scenes`` (``~/.cache/...`` by default)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "shadowcorr" / "voxel_scenes"


def find_bundles(directory: str | Path, limit: int | None = None) -> list[Path]:
    """Bundle directories (holding ``manifest.json``) directly under ``directory``, sorted by name.

    ``directory`` may itself be a bundle.  ``limit`` keeps the first ``limit`` of them
    (name order, so the subset is the same on every run).
    """
    d = Path(directory)
    if (d / "manifest.json").is_file():
        found = [d]
    elif d.is_dir():
        found = sorted(c for c in d.iterdir() if (c / "manifest.json").is_file())
    else:
        raise FileNotFoundError(f"{d}: no such directory")
    if not found:
        raise FileNotFoundError(f"{d}: holds no bundle directory (with manifest.json)")
    return found[:limit] if limit is not None else found


def cache_key(bundle_dir: str | Path, config: ShadowCorrConfig) -> str:
    """Hex digest identifying (bundle, its manifest's size and mtime, config, cache format)."""
    p = Path(bundle_dir).resolve()
    st = (p / "manifest.json").stat()
    # Only the fields that differ from their defaults: a field added to ShadowCorrConfig
    # later (with a default that keeps the old behaviour) does not invalidate the cache.
    text = json.dumps(
        {"path": str(p), "size": st.st_size, "mtime_ns": st.st_mtime_ns,
         "config": config.model_dump(mode="json", exclude_defaults=True), "format": CACHE_FORMAT},
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def cache_path(bundle_dir: str | Path, config: ShadowCorrConfig, cache_dir: str | Path) -> Path:
    return Path(cache_dir) / f"{Path(bundle_dir).name}-{cache_key(bundle_dir, config)}.npz"


def save_scene(path: str | Path, scene: VoxelScene, target: np.ndarray, source: str) -> None:
    """Write a prepared scene + target as an ``.npz`` of plain arrays (atomic rename)."""
    arrays: dict[str, np.ndarray] = {k: np.asarray(getattr(scene, k)) for k in _ARRAYS}
    arrays["target"] = np.asarray(target, dtype=np.int64)
    arrays["has_truth"] = np.array(scene.segment_truth is not None)
    arrays["segment_truth"] = (
        np.asarray(scene.segment_truth, dtype=np.int64) if scene.segment_truth is not None else np.zeros(0, np.int64)
    )
    # Strings and small metadata as unicode arrays / JSON text: no object arrays, no pickle.
    meta = {"name": scene.name, "units": scene.units, "unit_scale": scene.unit_scale, "source": source,
            "config": scene.config.model_dump(mode="json"), "warnings": scene.warnings,
            "timings_ms": scene.timings_ms, "format": CACHE_FORMAT}  # fmt: skip
    arrays["meta_json"] = np.array(json.dumps(meta))
    arrays["view_names"] = np.array(list(scene.view_names), dtype=np.str_)
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + f".{os.getpid()}.tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, p)


def load_scene(path: str | Path) -> TrainScene:
    """Read a cache file written by :func:`save_scene` (``allow_pickle=False``)."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta_json"]))
        if meta.get("format") != CACHE_FORMAT:
            raise ValueError(f"{path}: cache format {meta.get('format')!r}, expected {CACHE_FORMAT!r}")
        fields = {k: z[k] for k in _ARRAYS}
        scene = VoxelScene(
            name=meta["name"],
            units=meta["units"],
            unit_scale=float(meta["unit_scale"]),
            config=ShadowCorrConfig.model_validate(meta["config"]),
            view_names=[str(v) for v in z["view_names"]],
            segment_truth=z["segment_truth"] if bool(z["has_truth"]) else None,
            warnings=list(meta["warnings"]),
            timings_ms=dict(meta["timings_ms"]),
            **fields,
        )
        return TrainScene(path=meta["source"], scene=scene, target=z["target"])


def _prepare_one(job: tuple[str, str, str]) -> tuple[str, float, str | None]:
    """Worker: prepare one bundle and write its cache file; returns (path, seconds, error)."""
    from ..evaluation import voxel_truth
    from ..io import load_bundle
    from ..pipeline import prepare

    bundle_dir, config_json, out = job
    t0 = time.perf_counter()
    try:
        config = ShadowCorrConfig.model_validate_json(config_json)
        scene = prepare(load_bundle(bundle_dir), config)
        if scene.segment_truth is None:
            raise ValueError("bundle carries no ground truth; it cannot be used for training")
        save_scene(out, scene, voxel_truth(scene), str(Path(bundle_dir).resolve()))
    except Exception as exc:  # report per bundle; one broken scene must not stop the others
        return bundle_dir, time.perf_counter() - t0, f"{type(exc).__name__}: {exc}"
    return bundle_dir, time.perf_counter() - t0, None


def _init_worker() -> None:
    # One thread per worker: the pool already uses every core.
    import torch

    torch.set_num_threads(1)


def training_pipeline() -> ShadowCorrConfig:
    """The pipeline configuration scenes are prepared with for training.

    The network learns from the volumetric stages alone: the cross-view surface evidence
    (method ``fused``) is not an input of it, and synthetic training scenes have exact
    poses; validation clusters the network's embeddings as the paper does (``shadowcorr``).
    """
    return ShadowCorrConfig(method="shadowcorr", refine_poses=False)


def prepare_scenes(
    bundles: Sequence[str | Path],
    config: ShadowCorrConfig | None = None,
    cache_dir: str | Path | None = None,
    *,
    workers: int = 1,
    progress: bool = True,
    desc: str = "prepare",
) -> tuple[list[TrainScene], dict[str, float | int]]:
    """Prepare (or read from the cache) every bundle; returns the scenes and a summary.

    Bundles that fail to prepare are skipped with a message in the summary's
    ``failures`` count (and printed); the order of the returned scenes follows
    ``bundles``.  The summary has ``prepared`` (newly), ``cached``, ``failures`` and
    ``prepare_seconds`` (summed worker time of the new ones).
    """
    from tqdm import tqdm

    config = config or training_pipeline()
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    paths = [cache_path(b, config, cache) for b in bundles]
    todo = [(str(b), config.model_dump_json(), str(p)) for b, p in zip(bundles, paths) if not p.is_file()]
    failures: dict[str, str] = {}
    seconds = 0.0
    if todo:
        bar = tqdm(total=len(todo), desc=desc, unit="scene", disable=not progress)
        if workers <= 1:
            for job in todo:
                b, s, err = _prepare_one(job)
                seconds += s
                if err:
                    failures[b] = err
                bar.update(1)
        else:
            # spawn: the parent may hold torch/OpenMP threads that do not survive a fork.
            with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_init_worker) as pool:
                for fut in as_completed([pool.submit(_prepare_one, j) for j in todo]):
                    b, s, err = fut.result()
                    seconds += s
                    if err:
                        failures[b] = err
                    bar.update(1)
        bar.close()
    for b, err in failures.items():
        print(f"warning: skipping {b}: {err}")
    scenes = [load_scene(p) for b, p in zip(bundles, paths) if str(b) not in failures]
    summary = {"prepared": len(todo) - len(failures), "cached": len(bundles) - len(todo), "failures": len(failures),
               "prepare_seconds": round(seconds, 2)}  # fmt: skip
    return scenes, summary
