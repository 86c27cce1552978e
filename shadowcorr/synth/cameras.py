"""The camera rig: calibrated pinhole cameras on a ring around the rock field.

Defaults follow the rig of the reference lunar dataset: cameras ~750 units from the
scene centre at 329 units height, pitched 21–27° down towards the centre, 1920x1080
pixels with fx = fy ~ 1615 px and the principal point at the image centre.

Poses are camera-to-world in the OpenCV optical convention (x right, y down, z
forward): a pixel (u, v) with z-depth d is at ((u - cx) d / fx, (v - cy) d / fy, d) in
the camera frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..poses import look_at_pose


@dataclass
class Camera:
    """One pinhole camera: intrinsics in pixels, camera-to-world pose (OpenCV)."""

    name: str
    pose: np.ndarray  # (4, 4) camera-to-world, OpenCV convention
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) -> pixel coordinates (N, 2) and z-depth (N,)."""
        r, t = self.pose[:3, :3], self.pose[:3, 3]
        pc = (np.asarray(points, dtype=np.float64) - t) @ r  # world -> camera: R^T (p - t)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.fx * pc[:, 0] / z + self.cx, self.fy * pc[:, 1] / z + self.cy], axis=1)
        return uv, z


def ring_azimuths(n: int, arc_deg: float, start_deg: float) -> np.ndarray:
    """Azimuths (degrees) of ``n`` cameras spread over ``arc_deg``.

    A full circle spaces them 360/n apart (the first and last are neighbours); a
    partial arc puts the first and last camera at its two ends.
    """
    if n == 1:
        return np.array([start_deg])
    if arc_deg >= 360.0 - 1e-9:
        return start_deg + np.arange(n) * 360.0 / n
    return start_deg + np.linspace(0.0, arc_deg, n)


def make_rig(
    rng: np.random.Generator,
    *,
    n_cameras: int = 4,
    radius: float = 750.0,
    height: float = 329.0,
    arc_deg: float = 360.0,
    start_deg: float | None = None,
    azimuths_deg: Sequence[float] | None = None,
    pitch_deg: tuple[float, float] = (21.0, 27.0),
    radius_jitter: float = 0.05,
    width: int = 1920,
    height_px: int = 1080,
    focal_px: float = 1615.0,
    centre: np.ndarray | None = None,
) -> list[Camera]:
    """Cameras on a ring around ``centre``, each pitched down by a random angle in ``pitch_deg``.

    The yaw points every camera at the centre (like the real rig); the pitch is drawn
    in ``pitch_deg`` (the real rig's 21–27°) rather than aimed exactly at the centre,
    so the field sits a little above or below the image centre as in the real views.
    ``radius_jitter`` varies each camera's distance by up to ±5 % (the real ring is not
    a perfect circle).  ``start_deg`` None = random rotation of the whole ring.
    ``azimuths_deg`` (one per camera, relative to the start) places the cameras at
    uneven angles instead of spreading them evenly over ``arc_deg``.
    """
    centre = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
    start = rng.uniform(0.0, 360.0) if start_deg is None else start_deg
    if azimuths_deg is None:
        azimuths = ring_azimuths(n_cameras, arc_deg, start)
    elif len(azimuths_deg) != n_cameras:
        raise ValueError(f"azimuths_deg has {len(azimuths_deg)} entries for {n_cameras} cameras")
    else:
        azimuths = start + np.asarray(azimuths_deg, dtype=np.float64)
    cams = []
    for k, az in enumerate(np.deg2rad(azimuths)):
        r = radius * (1.0 + rng.uniform(-radius_jitter, radius_jitter))
        eye = centre + np.array([r * np.cos(az), r * np.sin(az), height])
        pitch = np.deg2rad(rng.uniform(*pitch_deg))
        # Target at the centre's horizontal direction, lowered to give the drawn pitch.
        target = eye + np.array([-np.cos(az), -np.sin(az), -np.tan(pitch)])
        cams.append(
            Camera(
                name=f"cam{k}", pose=look_at_pose(eye, target), fx=focal_px, fy=focal_px,
                cx=width / 2.0, cy=height_px / 2.0, width=width, height=height_px,
            )
        )
    return cams
