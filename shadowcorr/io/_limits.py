"""Resource limits applied while loading one bundle, and the manifest's file name."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

MiB = 1024 * 1024
MANIFEST_NAME = "manifest.json"
#: Archive members expanding to less than this are not ratio-checked one by one (a small
#: file of zeros compresses far beyond any bomb ratio and is harmless).
MEMBER_RATIO_MIN_BYTES = 1 * MiB


class BundleLimits(BaseModel):
    """Resource limits applied while loading one bundle (defaults suit the HTTP service; :meth:`local`
    is what the library and the command line apply to a user's own files)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_views: int = Field(16, ge=1)
    max_pixels_per_view: int = Field(4096 * 4096, ge=1)
    max_total_bytes: int = Field(512 * MiB, ge=1, description="uncompressed bytes of all files together")
    max_files: int = Field(64, ge=1, description="regular files in an archive / parts in an upload")
    max_manifest_bytes: int = Field(1 * MiB, ge=1)
    max_compression_ratio: float = Field(
        200.0, gt=1, description="uncompressed / compressed archive bytes; zip bombs reach ~1000"
    )
    ratio_check_min_bytes: int = Field(
        32 * MiB, ge=0, description="archives expanding to less than this are not ratio-checked (harmless)"
    )
    max_scene_pixels: int = Field(
        64 * MiB, ge=1,
        description="width x height summed over the views, checked from the manifest before any image is decoded "
        "(413 too_many_pixels in the service): a few bytes of PNG can declare a 4096x4096 image",
    )
    max_segments: int = Field(100_000, ge=1, description="point-segment bundles: number of segments")
    max_scene_points: int = Field(
        20_000_000, ge=1,
        description="point-segment bundles: total points, checked from the array header before it is decompressed",
    )

    @classmethod
    def local(cls) -> "BundleLimits":
        """No limit on views, pixels, files, bytes, segments or points: the limits protect a shared
        server from its clients, not a user's own machine from the user's own data.  The archive's
        safety checks stay (paths inside the bundle, no links, the compression-ratio check of zip bombs)."""
        unlimited = 1 << 62
        return cls(max_views=unlimited, max_pixels_per_view=unlimited, max_total_bytes=unlimited, max_files=unlimited,
                   max_manifest_bytes=LOCAL_MAX_MANIFEST_BYTES, max_scene_pixels=unlimited, max_segments=unlimited,
                   max_scene_points=unlimited)


#: A manifest is read into memory whole: even a user's own is bounded (about 200,000 views).
LOCAL_MAX_MANIFEST_BYTES = 256 * MiB
