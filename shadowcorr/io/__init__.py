"""Reading and writing ShadowCorr inputs: whole scene bundles and their per-view images.

- :func:`load_bundle` (a directory, an archive path or bytes) and :func:`load_bundle_from_parts`
  (a manifest and in-memory files, as the HTTP service receives them), bounded by
  :class:`BundleLimits`; every problem is reported at once in one ``BundleError``;
- :func:`write_bundle`, :func:`write_bundle_archive`, :func:`bundle_to_parts`;
- :mod:`shadowcorr.io.images` - decoding and encoding of depth and mask images (EXR, PNG, NPY);
- :func:`normalize_bundle_path`, :func:`range_to_z` - the path rule and depth conversion the
  loaders apply.

The in-memory scene these produce and consume, :class:`~shadowcorr.bundle.SceneBundle`,
is defined in :mod:`shadowcorr.bundle`.
"""

from ._limits import BundleLimits
from ._read import load_bundle, load_bundle_from_parts
from ._sources import normalize_bundle_path
from ._views import range_to_z
from ._write import bundle_to_parts, write_bundle, write_bundle_archive
from .images import (
    DEFAULT_MAX_PIXELS,
    clean_depth,
    encode_depth_exr,
    encode_depth_png16,
    encode_mask_png,
    encode_mask_png_rgb,
    encode_npy,
    pack_rgb,
    read_depth,
    read_exr_channel,
    read_mask,
    read_npy,
    rgb_to_ids,
)

__all__ = [
    "BundleLimits",
    "bundle_to_parts",
    "load_bundle",
    "load_bundle_from_parts",
    "normalize_bundle_path",
    "range_to_z",
    "write_bundle",
    "write_bundle_archive",
    "DEFAULT_MAX_PIXELS",
    "clean_depth",
    "encode_depth_exr",
    "encode_depth_png16",
    "encode_mask_png",
    "encode_mask_png_rgb",
    "encode_npy",
    "pack_rgb",
    "read_depth",
    "read_exr_channel",
    "read_mask",
    "read_npy",
    "rgb_to_ids",
]
