"""Rerun recording export (``rerun-sdk``, the ``viz`` extra), in metres.

Entity layout (all static, no timeline):

* ``world``: view coordinates of the world (its up axis, as ``ShadowCorrConfig.up_axis`` finds it);
* ``world/cameras/<view>``: the camera's pose (``Transform3D``, camera -> world) and
  ``Pinhole`` (intrinsics, image size, OpenCV axes: right, down, forward);
* ``world/cameras/<view>/depth``: its depth image (``DepthImage``, bundle units, with the
  factor to metres) and ``world/cameras/<view>/mask``: its instance mask (``SegmentationImage``);
* ``world/objects/<id>/points``: the object's fused points (``Points3D``, its picture colour);
* ``world/objects/<id>/box``: its oriented box (``Boxes3D``) labelled ``"<id> (<confidence>)"``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..bundle import UNIT_IN_METRES
from ..poses import world_up
from ._scene import ExportScene, entity_name

_WORLD_AXES = {(2, 1.0): "RIGHT_HAND_Z_UP", (2, -1.0): "RIGHT_HAND_Z_DOWN", (1, 1.0): "RIGHT_HAND_Y_UP",
               (1, -1.0): "RIGHT_HAND_Y_DOWN", (0, 1.0): "RIGHT_HAND_X_UP", (0, -1.0): "RIGHT_HAND_X_DOWN"}


def write_rrd(scene: ExportScene, out: Path) -> None:
    import rerun as rr

    rec = rr.RecordingStream("shadowcorr", recording_id=f"shadowcorr-{scene.result.scene}")
    rec.save(str(out))
    m = scene.metres
    config = scene.result.config or {}
    up = world_up(np.stack([v.pose for v in scene.views]), str(config.get("up_axis", "auto")))
    axes = getattr(rr.ViewCoordinates, _WORLD_AXES[up], None)
    if axes is not None:
        rec.log("world", axes, static=True)
    for view in scene.views:
        path = f"world/cameras/{entity_name(view.name)}"
        rec.log(path, rr.Transform3D(translation=view.pose[:3, 3] * m, mat3x3=view.pose[:3, :3]), static=True)
        if view.intrinsics is None:
            continue
        k = view.intrinsics
        rec.log(path, rr.Pinhole(focal_length=[k.fx, k.fy], principal_point=[k.cx, k.cy],
                                 resolution=[k.width, k.height], camera_xyz=rr.ViewCoordinates.RDF), static=True)
        if view.depth is not None:
            depth = np.asarray(view.depth, dtype=np.float32)
            rec.log(f"{path}/depth", rr.DepthImage(depth, meter=1.0 / UNIT_IN_METRES[scene.units]), static=True)
        if view.mask is not None:
            rec.log(f"{path}/mask", rr.SegmentationImage(np.asarray(view.mask, dtype=np.uint16)
                                                         if view.mask.max(initial=0) < 65536 else view.mask),
                    static=True)
    starts = np.searchsorted(scene.point_object, np.arange(len(scene.result.objects) + 1))
    box_row = {int(obj): k for k, obj in enumerate(scene.boxed.tolist())}
    for obj in range(len(scene.result.objects)):
        colour = scene.colours(np.array([obj]))[0]
        points = scene.points[starts[obj]:starts[obj + 1]] * m
        rec.log(f"world/objects/{obj}/points", rr.Points3D(points, colors=colour), static=True)
        k = box_row.get(obj)
        if k is not None:
            rec.log(f"world/objects/{obj}/box", rr.Boxes3D(
                centers=[scene.center[k] * m], half_sizes=[scene.size[k] * m / 2.0],
                quaternions=[rr.Quaternion(xyzw=scene.quaternion[k])], colors=[colour],
                labels=[f"{obj} ({scene.confidence[k]:.2f})"]), static=True)
    rec.flush()
    rec.disconnect()
