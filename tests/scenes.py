"""Small analytic test scenes: spheres on a circle of cameras, ray-cast exactly with numpy."""

from __future__ import annotations

import numpy as np

from shadowcorr.bundle import SceneBundle, View
from shadowcorr.bundle import Intrinsics


def look_at(position: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose in the OpenCV convention (x right, y down, z forward)."""
    f = np.asarray(target, float) - np.asarray(position, float)
    f /= np.linalg.norm(f)
    x = np.cross(f, up)
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, f], axis=1)
    pose[:3, 3] = position
    return pose


def ring_cameras(n: int, radius: float, height: float, target=(0.0, 0.0, 0.0), start_deg: float = 0.0,
                 arc_deg: float = 360.0) -> list[np.ndarray]:
    step = arc_deg / n if arc_deg >= 360 else arc_deg / max(n - 1, 1)
    angles = np.deg2rad(start_deg + step * np.arange(n))
    return [look_at(np.array([radius * np.cos(a), radius * np.sin(a), height]) + np.asarray(target), target)
            for a in angles]


def render_spheres(centres: np.ndarray, radii: np.ndarray, pose: np.ndarray, k: Intrinsics,
                   ids: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Exact z-depth and instance mask of spheres seen by one pinhole camera."""
    ids = np.arange(1, len(radii) + 1) if ids is None else ids
    v, u = np.mgrid[0:k.height, 0:k.width].astype(np.float64)
    rays_cam = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1)
    r, o = pose[:3, :3], pose[:3, 3]
    rays = rays_cam @ r.T  # world directions, z-component along the optical axis is 1
    best = np.full(u.shape, np.inf)
    mask = np.zeros(u.shape, dtype=np.int32)
    for c, rad, i in zip(centres, radii, ids):  # per sphere, vectorised over pixels
        oc = o - c
        a = np.einsum("hwk,hwk->hw", rays, rays)
        b = 2 * np.einsum("hwk,k->hw", rays, oc)
        disc = b * b - 4 * a * (oc @ oc - rad * rad)
        t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
        t = np.where(t > 0, t, np.inf)
        closer = t < best
        best = np.where(closer, t, best)
        mask = np.where(closer, i, mask)
    depth = np.where(np.isfinite(best), best, 0.0).astype(np.float32)  # t is z-depth since ray z = 1
    return depth, mask


def sphere_scene(centres, radii, *, cameras: int = 4, radius: float = 750.0, height: float = 300.0,
                 width: int = 320, height_px: int = 180, fov_scale: float = 1615.0 / 1920.0,
                 units: str = "cm", arc_deg: float = 360.0, start_deg: float = 45.0) -> SceneBundle:
    """A bundle of spheres (ground truth: instance id = sphere index + 1)."""
    centres = np.asarray(centres, float)
    radii = np.asarray(radii, float)
    f = fov_scale * width
    k = Intrinsics(fx=f, fy=f, cx=width / 2, cy=height_px / 2, width=width, height=height_px)
    target = centres.mean(axis=0)
    views = []
    for i, pose in enumerate(ring_cameras(cameras, radius, height, target=target, start_deg=start_deg, arc_deg=arc_deg)):
        depth, mask = render_spheres(centres, radii, pose, k)
        views.append(View(name=f"cam{i}", pose=pose, intrinsics=k, depth=depth, mask=mask))
    return SceneBundle(units=units, views=views, name="spheres", ground_truth="instance")
