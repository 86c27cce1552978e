"""What every export reads: the result's objects, their fused points and the cameras, in one place."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ..bundle import UNIT_IN_METRES, SceneBundle, View
from ..pipeline import object_points, with_pose_corrections
from ..render.palette import object_colours
from ..result import Result


@dataclass
class ExportScene:
    """A result and its bundle, reduced to arrays (bundle units; ``metres`` converts)."""

    result: Result
    views: list[View]  # poses with the result's corrections applied
    points: np.ndarray  # (N, 3) fused points of every object, sorted by object
    point_object: np.ndarray  # (N,) int64
    boxed: np.ndarray  # (B,) ids of the objects with an oriented box, ascending
    center: np.ndarray  # (B, 3)
    size: np.ndarray  # (B, 3)
    quaternion: np.ndarray  # (B, 4) [x, y, z, w]
    confidence: np.ndarray  # (B,)
    metres: float  # metres per bundle unit

    @property
    def units(self) -> str:
        return self.result.units

    def colours(self, objects: np.ndarray) -> np.ndarray:
        """(N, 3) uint8 colours of objects, as in the rendered pictures (shadowcorr.render.palette)."""
        return object_colours(objects)


def export_scene(result: Result, bundle: SceneBundle) -> ExportScene:
    if bundle.units != result.units:
        raise ValueError(f"the bundle is in {bundle.units!r}, the result in {result.units!r}: not the result's bundle")
    cloud = object_points(bundle, result)
    boxed = [o for o in result.objects if o.oriented_box is not None]
    return ExportScene(
        result=result,
        views=with_pose_corrections(bundle, result).views,
        points=cloud.points,
        point_object=cloud.object,
        boxed=np.array([o.object for o in boxed], dtype=np.int64),
        center=np.array([o.oriented_box.center for o in boxed], dtype=np.float64).reshape(-1, 3),
        size=np.array([o.oriented_box.size for o in boxed], dtype=np.float64).reshape(-1, 3),
        quaternion=np.array([o.oriented_box.quaternion for o in boxed], dtype=np.float64).reshape(-1, 4),
        confidence=np.array([o.confidence if o.confidence is not None else 0.0 for o in boxed], dtype=np.float64),
        metres=UNIT_IN_METRES[result.units],
    )


def frame_name(view: str) -> str:
    """The TF frame of a view's camera (OpenCV optical axes, as ROS optical frames): ``<view>_optical_frame``."""
    return re.sub(r"[^A-Za-z0-9_]", "_", view) + "_optical_frame"


def entity_name(view: str) -> str:
    """A view name as one Rerun entity path part."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", view)
