"""Small uploads that would cost a worker far more than their size: the builders shared by the
fault tests and ``benchmarks/bench_faults.py``.

Each returns ``(body, content_type)`` ready to ``POST /correspond``.  None needs much memory
or time to build here: the point is that the *server* would.
"""

from __future__ import annotations

import dataclasses
import io
import json
import zipfile
from typing import Callable, TypeVar

import numpy as np

from .harness import MiB, zip_files, zipped_bundle

__all__ = ["checkerboard_mask_bundle", "huge_point_npz_bundle", "many_empty_pixels_bundle", "corrupt_deflate_bundle",
           "peak_memory_growth"]

ZIP = "application/zip"
T = TypeVar("T")


def peak_memory_growth(pid: int, send: Callable[[], T]) -> tuple[T, int]:
    """``send()``'s result and how many bytes process ``pid``'s peak resident memory rose above its
    resident memory before (the kernel's high-water mark, reset first; Linux)."""
    def status_bytes(field: str) -> int:
        with open(f"/proc/{pid}/status") as fh:
            return 1024 * int(next(line for line in fh if line.startswith(field + ":")).split()[1])

    with open(f"/proc/{pid}/clear_refs", "w") as fh:
        fh.write("5")  # VmHWM starts again from the current RSS
    before = status_bytes("VmRSS")
    result = send()
    return result, status_bytes("VmHWM") - before


def checkerboard_mask_bundle(width: int = 1920, height: int = 1080) -> tuple[bytes, str]:
    """A 3-view scene whose first mask is one id in a checkerboard: every pixel its own run,
    all joined through their corners (~1 M runs at 1080p, a few kB of PNG)."""
    from shadowcorr_service.synthetic import synthetic_bundle

    bundle = synthetic_bundle(n_rocks=3, n_views=3, width=width, height=height)
    view = bundle.views[0]
    mask = ((np.arange(height)[:, None] + np.arange(width)[None, :]) % 2).astype(np.uint8)
    depth = np.full(mask.shape, 500.0, np.float32)
    bundle.views[0] = dataclasses.replace(view, mask=mask, depth=depth)
    return zipped_bundle(bundle)[0], ZIP


def _npy_header(shape: tuple[int, ...], descr: str = "<f8") -> bytes:
    header = repr({"descr": descr, "fortran_order": False, "shape": shape}).encode()
    header += b" " * (63 - (10 + len(header)) % 64) + b"\n"  # pad to a multiple of 64 bytes
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header


def huge_point_npz_bundle(points: int = 20_000_000) -> tuple[bytes, str]:
    """A point-segment bundle whose ``points`` array is ``points`` x 3 zeros: about 2 MB of
    upload for ``points * 24`` bytes decompressed (the array is streamed, never held here)."""
    npz = io.BytesIO()
    with zipfile.ZipFile(npz, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("points.npy", "w", force_zip64=True) as member:
            member.write(_npy_header((points, 3)))
            zero = bytes(MiB)
            left = points * 24
            while left > 0:
                member.write(zero[: min(left, MiB)])
                left -= MiB
        for key, value in (("lengths", [points]), ("view", [0]), ("instance", [1])):
            buf = io.BytesIO()
            np.save(buf, np.asarray(value, dtype=np.int64))
            zf.writestr(f"{key}.npy", buf.getvalue())
    identity = np.eye(4).tolist()
    manifest = {"units": "m", "views": [{"name": "a", "pose": {"matrix": identity}}],
                "segments": {"file": "segments.npz"}}
    return zip_files({"manifest.json": json.dumps(manifest).encode(), "segments.npz": npz.getvalue()}), ZIP


def _one_image_pair_bundle(mask: np.ndarray, depth: np.ndarray, views: int) -> tuple[bytes, str]:
    """A zipped bundle of ``views`` views at one pose that all share one mask and one depth PNG."""
    from shadowcorr.io import encode_depth_png16, encode_mask_png

    height, width = mask.shape
    files = {"mask.png": encode_mask_png(mask), "depth.png": encode_depth_png16(depth, 0.001)}
    intrinsics = {"fx": 1000.0, "fy": 1000.0, "cx": width / 2, "cy": height / 2, "width": width, "height": height}
    manifest = {"units": "m", "views": [
        {"name": f"v{i}", "pose": {"matrix": np.eye(4).tolist()}, "intrinsics": intrinsics,
         "depth": {"file": "depth.png", "format": "png", "scale": 0.001},
         "mask": {"file": "mask.png", "format": "png"}} for i in range(views)]}
    return zip_files({"manifest.json": json.dumps(manifest).encode(), **files}), ZIP


def many_empty_pixels_bundle(views: int = 16, side: int = 4096) -> tuple[bytes, str]:
    """``views`` views of ``side`` x ``side`` pixels with one tiny instance each: a few kB of PNG
    that would decode to gigabytes."""
    mask = np.zeros((side, side), np.uint8)
    mask[:8, :8] = 1
    return _one_image_pair_bundle(mask, np.where(mask > 0, 5.0, 0.0), views)


def dense_instance_bundle(views: int = 3, side: int = 1700) -> tuple[bytes, str]:
    """``views`` views of ``side`` x ``side`` pixels that are all one instance with valid depth
    (8.7 million points at the defaults, over the service's 8 million): a few kB of PNG whose
    back-projection alone would take hundreds of MB, and ``prepare`` much longer."""
    return _one_image_pair_bundle(np.ones((side, side), np.uint8), np.full((side, side), 5.0), views)


def corrupt_deflate_bundle() -> tuple[bytes, str]:
    """A valid small bundle whose first deflated member starts with a block of the reserved type
    (BFINAL 1, BTYPE 11): the archive's directory is intact, the member fails while inflating."""
    from shadowcorr_service.synthetic import synthetic_bundle

    body = bytearray(zipped_bundle(synthetic_bundle(n_rocks=3, n_views=3))[0])
    with zipfile.ZipFile(io.BytesIO(bytes(body))) as zf:
        info = next(i for i in zf.infolist() if i.compress_type == zipfile.ZIP_DEFLATED and i.compress_size > 64
                    and i.filename != "manifest.json")
    name_len = int.from_bytes(body[info.header_offset + 26:info.header_offset + 28], "little")
    extra_len = int.from_bytes(body[info.header_offset + 28:info.header_offset + 30], "little")
    data = info.header_offset + 30 + name_len + extra_len
    body[data] = 0b111
    return bytes(body), ZIP
