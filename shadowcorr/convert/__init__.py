"""Converters from third-party data to ShadowCorr bundles.

``ue``: the authors' Unreal Engine lunar-rock dataset (depth EXR + colour masks).
``rosbag``: ROS 1 / ROS 2 bags of depth + instance-mask images, camera info and tf
(``shadowcorr.convert.rosbag``; imported on use, it needs the ``rosbags`` package).
``reference_npz``: the reference implementation's pickled segment ``.npz`` -- the one
place that unpickles, as a local, explicit action on a trusted file.
"""

from .reference_npz import convert_reference_npz, read_reference_npz
from .ue import (
    UE_CAMERAS,
    UE_CLASS_COLOURS,
    UE_DEPTH_MAX,
    UE_FOCAL_PX,
    UE_PAPER_CAMERAS,
    UE_UNITS,
    UECamera,
    convert_ue,
    load_ue_scene,
    ue_file_names,
    ue_pose_opencv,
    ue_sets,
)

__all__ = [
    "UE_CAMERAS",
    "UE_CLASS_COLOURS",
    "UE_DEPTH_MAX",
    "UE_FOCAL_PX",
    "UE_PAPER_CAMERAS",
    "UE_UNITS",
    "UECamera",
    "convert_ue",
    "load_ue_scene",
    "ue_file_names",
    "ue_pose_opencv",
    "ue_sets",
    "convert_reference_npz",
    "read_reference_npz",
]
