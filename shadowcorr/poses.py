"""Camera poses: building camera-to-world matrices in the OpenCV optical convention."""

from __future__ import annotations

import numpy as np

from .config import UP_AXES  # the names live with the setting (config imports no numpy)


def look_at_pose(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV: x right, y down, z forward) at ``eye`` looking at ``target``.

    No roll: the camera's x axis is horizontal with respect to ``up``.  Looking straight
    along ``up`` leaves the roll free; then any axis orthogonal to the view is used.
    """
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    norm = np.linalg.norm(forward)
    forward = forward / norm if norm > 0 else -np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        right = np.cross(forward, np.eye(3)[np.argmin(np.abs(forward))])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def quaternion_to_matrix(q) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from unit quaternions (..., 4) in ROS order ``(x, y, z, w)``.

    The quaternion is normalised first: recorded ones are often off unit length by
    float rounding, and a rotation must stay a rotation.
    """
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def slerp(q0, q1, t: float) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions ``(x, y, z, w)`` at ``t`` in [0, 1].

    Takes the short way round (``q`` and ``-q`` are the same rotation) and falls back to
    normalised linear interpolation when the two are nearly equal.
    """
    a = np.asarray(q0, dtype=np.float64)
    b = np.asarray(q1, dtype=np.float64)
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    dot = float(np.dot(a, b))
    if dot < 0:
        b, dot = -b, -dot
    if dot > 0.9995:
        out = a + t * (b - a)
        return out / np.linalg.norm(out)
    theta = np.arccos(min(dot, 1.0))
    return (np.sin((1 - t) * theta) * a + np.sin(t * theta) * b) / np.sin(theta)



def world_up(poses: np.ndarray | None, up_axis: str = "auto") -> tuple[int, float]:
    """The world axis pointing up, as (axis index, sign), for camera-to-world ``poses`` (V, 4, 4), OpenCV.

    ``auto`` takes the axis nearest to the cameras' mean up direction (``-y`` of the
    OpenCV camera frame): cameras are mounted upright, whatever the world's convention.
    Without poses (None or none at all, e.g. a scene read back from a training cache) it is +z.
    """
    if up_axis == "auto":
        has_poses = poses is not None and len(poses) > 0
        camera_up = -np.asarray(poses)[:, :3, 1].mean(axis=0) if has_poses else np.array([0.0, 0.0, 1.0])
        if not np.any(np.abs(camera_up) > 1e-9):
            camera_up = np.array([0.0, 0.0, 1.0])
        k = int(np.argmax(np.abs(camera_up)))
        return k, (1.0 if camera_up[k] > 0 else -1.0)
    if up_axis not in UP_AXES:
        raise ValueError(f"up axis must be one of {', '.join(UP_AXES)}, got {up_axis!r}")
    return "xyz".index(up_axis[-1]), (-1.0 if up_axis.startswith("-") else 1.0)
