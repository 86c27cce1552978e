"""Analytic sphere scenes: exact depth and masks by ray-sphere intersection, pure numpy.

A cheap, exactly known scene for warm-ups, tests and demos (no physics, no renderer):
spheres seen by a ring of pinhole cameras looking at their centre.  Masks hold sphere
index + 1, so the bundle carries ground truth (``ground_truth = "instance"``).
"""

from __future__ import annotations

import numpy as np

from ..bundle import Intrinsics, SceneBundle, View
from ..poses import look_at_pose
from .cameras import ring_azimuths


def render_spheres(centres: np.ndarray, radii: np.ndarray, pose: np.ndarray, intrinsics: Intrinsics,
                   ids: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Exact z-depth (0 = no hit) and instance mask of spheres seen by one pinhole camera."""
    k = intrinsics
    ids = np.arange(1, len(radii) + 1) if ids is None else np.asarray(ids)
    v, u = np.mgrid[0:k.height, 0:k.width].astype(np.float64)
    # Rays with unit z in the camera frame: the hit parameter t is the z-depth itself.
    rays = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1) @ pose[:3, :3].T
    origin = pose[:3, 3]
    a = np.einsum("hwk,hwk->hw", rays, rays)
    best = np.full(u.shape, np.inf)
    mask = np.zeros(u.shape, dtype=np.int32)
    for c, r, i in zip(np.asarray(centres, float), np.asarray(radii, float), ids):  # per sphere, vectorised over pixels
        oc = origin - c
        b = np.einsum("hwk,k->hw", rays, oc)
        disc = b * b - a * (oc @ oc - r * r)
        t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0.0))) / a, np.inf)
        closer = (t > 0) & (t < best)
        best = np.where(closer, t, best)
        mask = np.where(closer, i, mask)
    return np.where(np.isfinite(best), best, 0.0).astype(np.float32), mask


def sphere_scene(centres, radii, *, cameras: int = 4, radius: float = 750.0, height: float = 300.0,
                 width: int = 320, height_px: int = 180, focal_px: float | None = None,
                 units: str = "cm", arc_deg: float = 360.0, start_deg: float = 45.0,
                 target=None, name: str = "spheres") -> SceneBundle:
    """A bundle of spheres seen by ``cameras`` cameras on a ring around ``target``.

    Cameras sit ``radius`` from the target (default: the spheres' mean centre),
    ``height`` above it, spread over ``arc_deg`` starting at ``start_deg``.  The focal
    length defaults to the real rig's field of view (1615 px at 1920 px width).
    """
    centres = np.asarray(centres, float)
    radii = np.asarray(radii, float)
    f = focal_px if focal_px is not None else 1615.0 / 1920.0 * width
    k = Intrinsics(fx=f, fy=f, cx=width / 2, cy=height_px / 2, width=width, height=height_px)
    target = centres.mean(axis=0) if target is None else np.asarray(target, float)
    views = []
    for i, az in enumerate(np.deg2rad(ring_azimuths(cameras, arc_deg, start_deg))):
        eye = target + np.array([radius * np.cos(az), radius * np.sin(az), height])
        pose = look_at_pose(eye, target)
        depth, mask = render_spheres(centres, radii, pose, k)
        views.append(View(name=f"cam{i}", pose=pose, intrinsics=k, depth=depth, mask=mask))
    return SceneBundle(units=units, views=views, name=name, ground_truth="instance")
