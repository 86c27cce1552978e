"""Write scene bundles: a directory, a ``.zip`` / ``.tar`` archive, or the in-memory parts of an upload."""

from __future__ import annotations

import io
import json
import re
import tarfile
import zipfile
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import ValidationError

from ..bundle import Manifest, SceneBundle
from ..errors import BundleError, problems_from_validation_error
from . import images
from ._limits import MANIFEST_NAME

_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


def _file_stem(i: int, name: str) -> str:
    # Index first: two view names may sanitise to the same text.
    return f"{i:02d}_{_SAFE.sub('_', name)[:64].strip('._') or 'view'}"


def bundle_to_parts(
    bundle: SceneBundle,
    *,
    depth_format: Literal["exr", "npy", "png"] = "exr",
    mask_format: Literal["png", "npy"] = "png",
    depth_png_scale: float | None = None,
) -> tuple[dict, dict[str, bytes]]:
    """Encode a ``SceneBundle`` as (manifest dict, {path: bytes}) -- the upload form of a bundle.

    ``exr`` depth is float32 (lossless for ``View.depth``); ``png`` depth is 16-bit and
    quantised to ``depth_png_scale`` units (default: max depth / 65535, i.e. lossy);
    ``png`` masks are 8-bit when ids <= 255, else 16-bit.  Poses are written in the
    OpenCV convention.  The manifest is validated before it is returned.
    """
    if depth_format not in ("exr", "npy", "png"):
        raise ValueError(f"depth_format must be 'exr', 'npy' or 'png', got {depth_format!r}")
    if mask_format not in ("png", "npy"):
        raise ValueError(f"mask_format must be 'png' or 'npy', got {mask_format!r}")
    files: dict[str, bytes] = {}
    views: list[dict] = []
    for i, v in enumerate(bundle.views):
        stem = _file_stem(i, v.name)
        entry: dict[str, Any] = {"name": v.name, "pose": {"matrix": np.asarray(v.pose, float).tolist(), "convention": "opencv"}}
        if v.intrinsics is not None:
            entry["intrinsics"] = v.intrinsics.model_dump()
        if v.depth is not None:
            path = f"depth/{stem}.{depth_format}"
            spec: dict[str, Any] = {"file": path, "format": depth_format}
            if depth_format == "exr":
                files[path] = images.encode_depth_exr(v.depth)
            elif depth_format == "npy":
                files[path] = images.encode_npy(np.asarray(v.depth, dtype=np.float32))
            else:
                d = np.asarray(v.depth, dtype=np.float64)
                dmax = float(d[np.isfinite(d)].max(initial=0.0))
                scale = depth_png_scale or (dmax / 65535.0 if dmax > 0 else 1.0)
                files[path] = images.encode_depth_png16(d, scale)
                spec["scale"] = scale
            entry["depth"] = spec
        if v.mask is not None:
            path = f"mask/{stem}.{mask_format}"
            files[path] = images.encode_mask_png(v.mask) if mask_format == "png" else images.encode_npy(
                np.asarray(v.mask, dtype=np.int32)
            )
            entry["mask"] = {"file": path, "format": mask_format}
        if v.instance_objects is not None:
            entry["instance_objects"] = {str(k): int(o) for k, o in v.instance_objects.items()}
        views.append(entry)
    manifest: dict[str, Any] = {
        "format": "shadowcorr-bundle",
        "version": 1,
        "name": bundle.name,
        "units": bundle.units,
        "ground_truth": bundle.ground_truth,
        "views": views,
    }
    ps = bundle.point_segments
    if ps is not None:
        arrays = {
            "points": np.asarray(ps.points, dtype=np.float64),
            "lengths": np.asarray(ps.lengths, dtype=np.int64),
            "view": np.asarray(ps.view, dtype=np.int64),
            "instance": np.asarray(ps.instance, dtype=np.int64),
        }
        if ps.object is not None:
            arrays["object"] = np.asarray(ps.object, dtype=np.int64)
        buf = io.BytesIO()
        np.savez_compressed(buf, allow_pickle=False, **arrays)
        files["segments.npz"] = buf.getvalue()
        manifest["segments"] = {"file": "segments.npz"}
    try:
        Manifest.model_validate(manifest)
    except ValidationError as e:  # a bundle we cannot write validly is a caller bug: say exactly what
        raise BundleError(problems_from_validation_error(e, manifest)) from None
    return manifest, files


def write_bundle(
    bundle: SceneBundle,
    out_dir: str | Path,
    *,
    depth_format: Literal["exr", "npy", "png"] = "exr",
    mask_format: Literal["png", "npy"] = "png",
    depth_png_scale: float | None = None,
) -> Path:
    """Write ``bundle`` as a bundle directory; returns the directory.

    The manifest is written last, so an interrupted write leaves no loadable half-bundle.
    """
    out = Path(out_dir)
    manifest, files = bundle_to_parts(
        bundle, depth_format=depth_format, mask_format=mask_format, depth_png_scale=depth_png_scale
    )
    out.mkdir(parents=True, exist_ok=True)
    for rel, data in files.items():
        p = out / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    (out / MANIFEST_NAME).write_text(json.dumps(manifest, indent=1))
    return out


_STORED_SUFFIXES = (".exr", ".png")  # already compressed: deflating again costs CPU for nothing


def write_bundle_archive(
    bundle: SceneBundle,
    path: str | Path,
    *,
    depth_format: Literal["exr", "npy", "png"] = "exr",
    mask_format: Literal["png", "npy"] = "png",
    depth_png_scale: float | None = None,
) -> Path:
    """Write ``bundle`` as a ``.zip`` (or ``.tar`` / ``.tar.gz`` / ``.tgz``, by suffix); returns the path.

    Files sit at the archive root next to ``manifest.json``.
    """
    p = Path(path)
    manifest, files = bundle_to_parts(
        bundle, depth_format=depth_format, mask_format=mask_format, depth_png_scale=depth_png_scale
    )
    files = {MANIFEST_NAME: json.dumps(manifest, indent=1).encode(), **files}
    name = p.name.lower()
    if name.endswith(".zip"):
        with zipfile.ZipFile(p, "w") as zf:
            for rel, data in files.items():
                ct = zipfile.ZIP_STORED if rel.endswith(_STORED_SUFFIXES) else zipfile.ZIP_DEFLATED
                zf.writestr(rel, data, compress_type=ct)
    elif name.endswith((".tar", ".tar.gz", ".tgz")):
        mode = "w" if name.endswith(".tar") else "w:gz"
        with tarfile.open(p, mode) as tf:  # type: ignore[call-overload]
            for rel, data in files.items():
                info = tarfile.TarInfo(rel)
                info.size = len(data)
                info.mode = 0o644
                tf.addfile(info, io.BytesIO(data))
    else:
        raise ValueError(f"archive path must end in .zip, .tar, .tar.gz or .tgz: {str(p)!r}")
    return p
