"""ROS 2 bag export (rosbags' writer; MCAP or sqlite3 storage).

Topics, all stamped ``stamp_ns`` (0: tools take the latest transform) in ``frame_id``,
lengths in metres (REP 103):

* ``/tf_static`` (``tf2_msgs/msg/TFMessage``, transient local): ``frame_id`` ->
  ``<view>_optical_frame`` for every camera, the OpenCV optical axes being ROS's optical frame;
* ``/shadowcorr/detections`` (``vision_msgs/msg/Detection3DArray``): one ``Detection3D`` per
  object with an oriented box; ``id`` is the object id as a string, ``bbox`` the box,
  ``results[0].hypothesis`` class ``rock`` with the object's ``confidence`` as ``score``;
* ``/shadowcorr/markers`` (``visualization_msgs/msg/MarkerArray``): per object a ``CUBE``
  (namespace ``boxes``, half transparent) and a ``TEXT_VIEW_FACING`` label ``"<id> (<confidence>)"``
  above it (namespace ``labels``), both with the object id as marker id and its picture colour;
* ``/shadowcorr/points`` (``sensor_msgs/msg/PointCloud2``): the fused points, fields ``x, y, z``
  (float32), ``rgb`` (float32 holding the packed colour, as RViz reads it) and ``object`` (uint32).

vision_msgs is not in rosbags' built-in type stores: its definitions (ROS 2 Humble and later)
are registered here from their ``.msg`` text.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ._scene import ExportScene, frame_name

TOPIC_TF = "/tf_static"
TOPIC_DETECTIONS = "/shadowcorr/detections"
TOPIC_MARKERS = "/shadowcorr/markers"
TOPIC_POINTS = "/shadowcorr/points"

#: vision_msgs (ROS 2 Humble and later), as .msg text for rosbags' type system.
VISION_MSGS = {
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"),
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
        "vision_msgs/BoundingBox3D bbox\nstring id\n"),
    "vision_msgs/msg/Detection3DArray": "std_msgs/Header header\nvision_msgs/Detection3D[] detections\n",
}

_FLOAT32, _UINT32 = 7, 6  # sensor_msgs/msg/PointField datatypes
_LABEL_HEIGHT_M = 0.1


def typestore():
    """ROS 2 Humble's message types plus vision_msgs."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    for name, text in VISION_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def write_bag(scene: ExportScene, out: Path, *, frame_id: str = "map", storage: str = "mcap",
              stamp_ns: int = 0) -> None:
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    messages = _Messages(store, frame_id, stamp_ns)
    latched = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, QosTime(0, 0),
                  QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(out, version=9, storage_plugin=plugin) as writer:
        for topic, msgtype, msg, qos in (
            (TOPIC_TF, "tf2_msgs/msg/TFMessage", messages.camera_frames(scene), [latched]),
            (TOPIC_DETECTIONS, "vision_msgs/msg/Detection3DArray", messages.detections(scene), []),
            (TOPIC_MARKERS, "visualization_msgs/msg/MarkerArray", messages.markers(scene), []),
            (TOPIC_POINTS, "sensor_msgs/msg/PointCloud2", messages.points(scene), []),
        ):
            connection = writer.add_connection(topic, msgtype, typestore=store, offered_qos_profiles=qos)
            writer.write(connection, stamp_ns, store.serialize_cdr(msg, msgtype))


class _Messages:
    """The bag's messages, built with the type store's classes."""

    def __init__(self, store, frame_id: str, stamp_ns: int) -> None:
        self.t = store.types
        time = self.t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        self.time, self.frame_id = time, frame_id

    def header(self, frame_id: str | None = None):
        return self.t["std_msgs/msg/Header"](stamp=self.time, frame_id=frame_id or self.frame_id)

    def pose(self, position: np.ndarray, quaternion: np.ndarray):
        x, y, z = (float(v) for v in position)
        qx, qy, qz, qw = (float(v) for v in quaternion)
        return self.t["geometry_msgs/msg/Pose"](position=self.t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                                                orientation=self.t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))

    def vector(self, v: np.ndarray):
        return self.t["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def camera_frames(self, scene: ExportScene):
        transforms = []
        for view in scene.views:
            q = Rotation.from_matrix(view.pose[:3, :3]).as_quat()
            t = view.pose[:3, 3] * scene.metres
            transforms.append(self.t["geometry_msgs/msg/TransformStamped"](
                header=self.header(), child_frame_id=frame_name(view.name),
                transform=self.t["geometry_msgs/msg/Transform"](
                    translation=self.vector(t),
                    rotation=self.t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))))
        return self.t["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def detections(self, scene: ExportScene):
        t = self.t
        out = []
        for k, obj in enumerate(scene.boxed.tolist()):
            pose = self.pose(scene.center[k] * scene.metres, scene.quaternion[k])
            hypothesis = t["vision_msgs/msg/ObjectHypothesisWithPose"](
                hypothesis=t["vision_msgs/msg/ObjectHypothesis"](class_id="rock", score=float(scene.confidence[k])),
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)))
            out.append(t["vision_msgs/msg/Detection3D"](
                header=self.header(), results=[hypothesis],
                bbox=t["vision_msgs/msg/BoundingBox3D"](center=pose, size=self.vector(scene.size[k] * scene.metres)),
                id=str(obj)))
        return t["vision_msgs/msg/Detection3DArray"](header=self.header(), detections=out)

    def markers(self, scene: ExportScene):
        t = self.t
        marker = t["visualization_msgs/msg/Marker"]
        colours = scene.colours(scene.boxed) / 255.0
        up = Rotation.from_quat(scene.quaternion).apply([0.0, 0.0, 1.0]) if len(scene.boxed) else np.zeros((0, 3))
        forever = t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0)
        out = []
        for k, obj in enumerate(scene.boxed.tolist()):
            r, g, b = (float(c) for c in colours[k])
            centre = scene.center[k] * scene.metres
            size = scene.size[k] * scene.metres
            common = {"header": self.header(), "id": obj, "action": 0, "lifetime": forever, "frame_locked": False,
                      "points": [], "colors": [], "texture_resource": "", "texture": t["sensor_msgs/msg/CompressedImage"](
                          header=self.header(), format="", data=np.zeros(0, np.uint8)),
                      "uv_coordinates": [], "mesh_resource": "", "mesh_file": t["visualization_msgs/msg/MeshFile"](
                          filename="", data=np.zeros(0, np.uint8)), "mesh_use_embedded_materials": False}
            out.append(marker(ns="boxes", type=1, pose=self.pose(centre, scene.quaternion[k]), scale=self.vector(size),
                              color=t["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=0.5), text="", **common))
            above = centre + up[k] * (size[2] / 2 + _LABEL_HEIGHT_M)
            out.append(marker(ns="labels", type=9, pose=self.pose(above, [0.0, 0.0, 0.0, 1.0]),
                              scale=self.vector([0.0, 0.0, _LABEL_HEIGHT_M]),
                              color=t["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=1.0),
                              text=f"{obj} ({scene.confidence[k]:.2f})", **common))
        return t["visualization_msgs/msg/MarkerArray"](markers=out)

    def points(self, scene: ExportScene):
        t = self.t
        n = scene.points.shape[0]
        rgb = scene.colours(scene.point_object).astype(np.uint32)
        record = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4"), ("object", "<u4")])
        xyz = scene.points * scene.metres
        record["x"], record["y"], record["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        record["rgb"] = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]  # RViz reads these bits as float32
        record["object"] = scene.point_object
        field = t["sensor_msgs/msg/PointField"]
        fields = [field(name=name, offset=offset, datatype=kind, count=1)
                  for name, offset, kind in (("x", 0, _FLOAT32), ("y", 4, _FLOAT32), ("z", 8, _FLOAT32),
                                             ("rgb", 12, _FLOAT32), ("object", 16, _UINT32))]
        return t["sensor_msgs/msg/PointCloud2"](
            header=self.header(), height=1, width=n, fields=fields, is_bigendian=False, point_step=20,
            row_step=20 * n, data=record.view(np.uint8), is_dense=True)
