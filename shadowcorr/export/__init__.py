"""A result, in the formats robot stacks and viewers read: a ROS 2 bag, PLY files, a Rerun recording.

``export(result, bundle, to, out)`` writes one artefact from a result and the bundle it was
computed from (the bundle supplies the cameras and, for a result read from JSON, the
objects' fused points: :func:`shadowcorr.object_points`):

* ``bag``: a ROS 2 bag directory (MCAP storage, or sqlite3) with
  ``vision_msgs/msg/Detection3DArray`` on ``/shadowcorr/detections``,
  ``visualization_msgs/msg/MarkerArray`` on ``/shadowcorr/markers``,
  ``sensor_msgs/msg/PointCloud2`` on ``/shadowcorr/points`` and the camera frames on
  ``/tf_static``, in metres (REP 103), in ``frame_id``;
* ``ply``: a directory with one binary PLY per object (``object_<id>.ply``) and all objects
  coloured in ``objects.ply``, in the bundle's units;
* ``rrd``: a Rerun recording (needs ``pip install 'shadowcorr[viz]'``), in metres.

``docs/guide/exports.md`` describes every topic, field and entity.  One private module
per format; this package imports none of their libraries until it writes.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    from ..bundle import SceneBundle
    from ..result import Result

__all__ = ["FORMATS", "STORAGES", "export", "rerun_available"]

Format = Literal["bag", "ply", "rrd"]
FORMATS: tuple[str, ...] = ("bag", "ply", "rrd")
STORAGES: tuple[str, ...] = ("mcap", "sqlite3")


def rerun_available() -> bool:
    """Whether the Rerun SDK (the ``viz`` extra) is installed, so that ``rrd`` can be written."""
    from importlib.util import find_spec

    return find_spec("rerun") is not None


def export(result: "Result", bundle: "SceneBundle", to: Format, out: str | Path, *, frame_id: str = "map",
           storage: Literal["mcap", "sqlite3"] = "mcap") -> Path:
    """Write ``result`` (computed from ``bundle``) as a ``bag``, ``ply`` or ``rrd`` at ``out``; returns ``out``.

    ``out`` must not exist yet (``bag`` and ``ply`` write a directory, ``rrd`` a file).
    ``frame_id`` names the world frame of the bag's messages and transforms; ``storage``
    chooses the bag's storage plugin.  Raises ``ValueError`` for an unknown format or
    storage, a bundle that does not cut into the result's segments, or an existing ``out``;
    ``ImportError`` (naming the extra) for ``rrd`` without the Rerun SDK.
    """
    from ._scene import export_scene

    out = Path(out)
    if to not in FORMATS:
        raise ValueError(f"unknown export format {to!r}; expected one of {', '.join(FORMATS)}")
    if storage not in STORAGES:
        raise ValueError(f"unknown bag storage {storage!r}; expected one of {', '.join(STORAGES)}")
    if out.exists():
        raise ValueError(f"{out} exists already; exports never overwrite")
    if to == "rrd" and not rerun_available():
        raise ImportError("writing a Rerun recording needs the Rerun SDK: pip install 'shadowcorr[viz]'")
    scene = export_scene(result, bundle)
    if to == "bag":
        from ._bag import write_bag

        write_bag(scene, out, frame_id=frame_id, storage=storage)
    elif to == "ply":
        from ._ply import write_ply

        write_ply(scene, out)
    else:
        from ._rrd import write_rrd

        write_rrd(scene, out)
    return out
