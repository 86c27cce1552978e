"""Camera poses: building camera-to-world matrices in the OpenCV optical convention."""

from __future__ import annotations

import numpy as np


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
