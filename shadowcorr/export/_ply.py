"""PLY export: one binary little-endian PLY per object and all objects coloured in one.

``object_<id>.ply`` holds the object's fused points (``x, y, z`` float32);
``objects.ply`` holds every object's points with ``red, green, blue`` (uchar, the object's
picture colour) and ``object`` (int32).  Coordinates are in the bundle's units, which a
``comment units <units>`` line in each header names (PLY itself has no units).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._scene import ExportScene

COMBINED = "objects.ply"


def object_file(obj: int) -> str:
    return f"object_{obj}.ply"


def write_ply(scene: ExportScene, out: Path) -> None:
    out.mkdir(parents=True)
    starts = np.searchsorted(scene.point_object, np.arange(len(scene.result.objects) + 1))
    xyz = scene.points.astype("<f4")
    for obj in range(len(scene.result.objects)):
        part = xyz[starts[obj]:starts[obj + 1]]
        record = np.zeros(part.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
        record["x"], record["y"], record["z"] = part[:, 0], part[:, 1], part[:, 2]
        _write(out / object_file(obj), record, scene.units, f"object {obj} of scene {scene.result.scene}")
    record = np.zeros(xyz.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                                           ("blue", "u1"), ("object", "<i4")])
    record["x"], record["y"], record["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    colours = scene.colours(scene.point_object)
    record["red"], record["green"], record["blue"] = colours[:, 0], colours[:, 1], colours[:, 2]
    record["object"] = scene.point_object
    _write(out / COMBINED, record, scene.units, f"every object of scene {scene.result.scene}")


_PLY_TYPES = {"<f4": "float", "u1": "uchar", "<i4": "int", "|u1": "uchar"}


def _write(path: Path, record: np.ndarray, units: str, what: str) -> None:
    properties = "".join(f"property {_PLY_TYPES[record.dtype[name].str]} {name}\n" for name in record.dtype.names)
    header = (f"ply\nformat binary_little_endian 1.0\ncomment {what}\ncomment units {units}\n"
              f"element vertex {record.shape[0]}\n{properties}end_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(record.tobytes())
