"""Scene bundles: the one input format of ShadowCorr.

A bundle is a directory (or a ``.zip`` / ``.tar`` of one) holding ``manifest.json``
and per-view files.  The manifest declares the length ``units`` of every depth value
and pose translation, and for each view:

* ``depth``: file + format (``exr`` float32/half z-depth, ``png`` 16-bit with a
  ``scale`` in units per stored count, or ``npy``), and whether values are z-depth
  along the optical axis (``"z"``, default) or distance along the ray (``"range"``);
* ``mask``: file + format (``png`` 8/16-bit single channel instance ids with
  0 = background, ``png_rgb`` colour-coded with a ``palette`` of ``{id: [r, g, b]}``,
  or ``npy`` integer ids);
* ``intrinsics``: ``fx, fy, cx, cy`` in pixels and ``width, height``;
* ``pose``: the 4x4 camera-to-world matrix and its ``convention``: ``opencv``
  (x right, y down, z forward; the default) or ``opengl`` (x right, y up, z backward).

A second flavour carries segments as 3D points instead of depth + mask
(``segments``: an ``.npz`` without object arrays holding ``points`` (P, 3), ``lengths``
(S,), ``view`` (S,), ``instance`` (S,) and optionally ``object`` (S,) ground truth);
its views then need only a pose.

Ground truth is optional: ``"ground_truth": "instance"`` says that mask instance ids
are object identities across views (as in the Unreal lunar dataset), ``"mapped"``
says each view's ``instance_objects`` maps its instance ids to object ids.
Ground truth is only ever used for metrics, never for features.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

Units = Literal["m", "cm", "mm"]
UNIT_IN_METRES: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}


#: Largest pose translation, in metres, a manifest may declare (1,000 km).  Coordinates
#: beyond it are either a mistake or lose their centimetres in float32 arithmetic
#: downstream, and far beyond it products and squares overflow.
MAX_TRANSLATION_M = 1e6
#: Largest focal length and principal-point coordinate, in pixels: a 4096-pixel image
#: with a 1e6-pixel focal length sees 0.2 degrees; larger values are not a camera.
MAX_INTRINSICS_PX = 1e6


def unit_scale(from_units: str, to_units: str) -> float:
    """Factor that converts a length in ``from_units`` to ``to_units``."""
    return UNIT_IN_METRES[from_units] / UNIT_IN_METRES[to_units]


# --------------------------------------------------------------------------- manifest
class _Strict(BaseModel):
    # Unknown keys are typos until proven otherwise; NaN/inf are never valid in a
    # manifest (intrinsics, scales, poses) and JSON parsers accept them, so refuse here.
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class DepthSpec(_Strict):
    file: str
    format: Literal["exr", "png", "npy"]
    scale: float = Field(
        1.0, ge=1e-9, le=1e9,
        description="units per stored value; applied to every format, usually != 1 only for 16-bit PNG",
    )
    kind: Literal["z", "range"] = "z"
    channel: str | None = Field(
        None, description="exr only: channel to read; default the first of Z, Y, R, depth, or the only channel"
    )


class MaskSpec(_Strict):
    file: str
    format: Literal["png", "png_rgb", "npy"]
    palette: dict[int, tuple[int, int, int]] | None = Field(
        None, description="instance id -> RGB colour; required for png_rgb, id 0 is background"
    )

    @model_validator(mode="after")
    def _palette_for_rgb(self) -> "MaskSpec":
        if self.format == "png_rgb" and not self.palette:
            raise ValueError("format 'png_rgb' needs a 'palette' of {id: [r, g, b]}")
        if self.palette:
            bad_ids = [i for i in self.palette if i < 0 or i > 2**31 - 1]
            if bad_ids:
                raise ValueError(f"palette ids must be in 0..2^31-1, got {bad_ids[:5]}")
            bad = [i for i, rgb in self.palette.items() if any(c < 0 or c > 255 for c in rgb)]
            if bad:
                raise ValueError(f"palette colours must be 0..255 per channel (ids {bad[:5]})")
            seen: dict[tuple[int, int, int], int] = {}
            for i, rgb in self.palette.items():
                if tuple(rgb) in seen and seen[tuple(rgb)] != i:
                    raise ValueError(f"palette colour {list(rgb)} is used by ids {seen[tuple(rgb)]} and {i}")
                seen[tuple(rgb)] = i
        return self


class Intrinsics(_Strict):
    fx: float = Field(gt=0, le=MAX_INTRINSICS_PX)
    fy: float = Field(gt=0, le=MAX_INTRINSICS_PX)
    cx: float = Field(ge=-MAX_INTRINSICS_PX, le=MAX_INTRINSICS_PX)
    cy: float = Field(ge=-MAX_INTRINSICS_PX, le=MAX_INTRINSICS_PX)
    width: int = Field(gt=0)
    height: int = Field(gt=0)


class PoseSpec(_Strict):
    matrix: list[list[float]]
    convention: Literal["opencv", "opengl"] = "opencv"

    @field_validator("matrix")
    @classmethod
    def _rigid(cls, m: list[list[float]]) -> list[list[float]]:
        a = np.asarray(m, dtype=np.float64)
        if a.shape != (4, 4):
            raise ValueError(f"pose matrix must be 4x4, got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError("pose matrix has non-finite values")
        if not np.allclose(a[3], [0, 0, 0, 1], atol=1e-6):
            raise ValueError("pose matrix last row must be [0, 0, 0, 1]")
        r = a[:3, :3]
        if not np.allclose(r.T @ r, np.eye(3), atol=1e-3) or np.linalg.det(r) < 0:
            raise ValueError("pose rotation is not a proper rotation (R^T R != I or det(R) < 0)")
        return m


class ViewSpec(_Strict):
    name: str = Field(min_length=1, max_length=256)
    pose: PoseSpec
    intrinsics: Intrinsics | None = None
    depth: DepthSpec | None = None
    mask: MaskSpec | None = None
    instance_objects: dict[int, int] | None = Field(
        None, description="ground truth: instance id -> object id (with ground_truth='mapped')"
    )


class SegmentsSpec(_Strict):
    file: str


class Manifest(_Strict):
    format: Literal["shadowcorr-bundle"] = "shadowcorr-bundle"
    version: Literal[1] = 1
    name: str = "scene"
    units: Units
    ground_truth: Literal["none", "instance", "mapped"] = "none"
    views: list[ViewSpec] = Field(min_length=1)
    segments: SegmentsSpec | None = None

    @model_validator(mode="after")
    def _consistent(self) -> "Manifest":
        names = [v.name for v in self.views]
        if len(set(names)) != len(names):
            raise ValueError("view names must be unique")
        max_translation = MAX_TRANSLATION_M / UNIT_IN_METRES[self.units]
        for i, v in enumerate(self.views):
            t = np.asarray(v.pose.matrix, dtype=np.float64)[:3, 3]
            if np.abs(t).max() > max_translation:
                raise ValueError(f"views[{i}] ({v.name}): pose translation {np.abs(t).max():.3g} {self.units} is farther "
                                 f"than {max_translation:.3g} {self.units} ({MAX_TRANSLATION_M:.0e} m) from the origin; "
                                 "express the poses in a local frame")
            if self.segments is None:
                missing = [k for k in ("intrinsics", "depth", "mask") if getattr(v, k) is None]
                if missing:
                    raise ValueError(f"views[{i}] ({v.name}): missing {', '.join(missing)} (needed without 'segments')")
            if self.ground_truth == "mapped" and v.instance_objects is None and self.segments is None:
                raise ValueError(f"views[{i}] ({v.name}): ground_truth 'mapped' needs 'instance_objects'")
        return self


# --------------------------------------------------------------------------- in memory
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class View:
    """One decoded camera view. ``pose`` is camera-to-world in the OpenCV optical frame."""

    name: str
    pose: np.ndarray  # (4, 4) float64, camera-to-world, OpenCV convention
    intrinsics: Intrinsics | None = None
    # (H, W) z-depth in bundle units, float32 or float16 (half-float EXRs load as stored); <= 0 or non-finite = invalid
    depth: np.ndarray | None = None
    mask: np.ndarray | None = None  # (H, W) integer instance ids (loaders: uint8/uint16 as stored, else int32), 0 = background
    instance_objects: dict[int, int] | None = None  # ground truth only

    @property
    def camera_center(self) -> np.ndarray:
        return self.pose[:3, 3]

    @property
    def optical_axis(self) -> np.ndarray:
        return self.pose[:3, 2]


@dataclass
class PointSegments:
    """Segments given directly as points (ragged: concatenated with explicit lengths)."""

    points: np.ndarray  # (P, 3) float, bundle units, world frame
    lengths: np.ndarray  # (S,) int
    view: np.ndarray  # (S,) int index into SceneBundle.views
    instance: np.ndarray  # (S,) int
    object: np.ndarray | None = None  # (S,) int ground truth, metrics only


@dataclass
class SceneBundle:
    """A decoded scene: everything the engine needs, in plain arrays."""

    units: str
    views: list[View]
    name: str = "scene"
    ground_truth: str = "none"  # "none" | "instance" | "mapped"
    point_segments: PointSegments | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def has_ground_truth(self) -> bool:
        return self.ground_truth != "none"


def pose_to_opencv(matrix: np.ndarray, convention: str) -> np.ndarray:
    """Camera-to-world pose in the given convention -> camera-to-world in OpenCV convention."""
    m = np.asarray(matrix, dtype=np.float64)
    if convention == "opencv":
        return m
    if convention == "opengl":
        return m @ OPENGL_TO_OPENCV
    raise ValueError(f"unknown pose convention {convention!r}")
