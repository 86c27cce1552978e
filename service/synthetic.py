"""A tiny analytic scene (spheres seen by a ring of pinhole cameras) built in memory.

Used to warm up the worker processes and the network at start-up (the first call of
every stage is several times slower than the next: lazy imports, allocator and
kernel caches), and by the tests and the benchmark as a cheap, valid request.  It
needs no data files, so a container can always warm itself up.
"""

from __future__ import annotations

import numpy as np

from shadowcorr.bundle import Intrinsics, SceneBundle, View

__all__ = ["synthetic_bundle"]


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world pose (OpenCV: x right, y down, z forward) looking from eye at target."""
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def synthetic_bundle(
    n_rocks: int = 3,
    n_views: int = 3,
    width: int = 160,
    height: int = 120,
    *,
    seed: int = 0,
    name: str = "synthetic",
) -> SceneBundle:
    """Spheres (rocks, radius 30-50 cm) on a 3 m field, seen from ``n_views`` cameras 6 m away.

    Masks hold the rock id (1..n_rocks) in every view, so the bundle carries ground truth
    (``ground_truth = "instance"``).  Depth is exact z-depth in cm; background is 0 (invalid).
    """
    rng = np.random.default_rng(seed)
    # Rocks on a loose ring so they never overlap: spacing beats the largest diameter.
    angles = np.linspace(0.0, 2 * np.pi, n_rocks, endpoint=False) + rng.uniform(0, 0.3)
    radii = rng.uniform(30.0, 50.0, n_rocks)
    ring = 60.0 + 25.0 * n_rocks
    centres = np.stack([ring * np.cos(angles), ring * np.sin(angles), radii], axis=1)

    f = 0.9 * width
    intr = Intrinsics(fx=f, fy=f, cx=width / 2.0, cy=height / 2.0, width=width, height=height)
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    rays_cam = np.stack([(uu - intr.cx) / f, (vv - intr.cy) / f, np.ones_like(uu)], axis=-1)  # z = 1: t is z-depth

    views: list[View] = []
    for i in range(n_views):
        a = 2 * np.pi * i / n_views + 0.3
        eye = np.array([600.0 * np.cos(a), 600.0 * np.sin(a), 300.0])
        pose = _look_at(eye, np.array([0.0, 0.0, 20.0]))
        d = rays_cam @ pose[:3, :3].T  # world ray directions, (H, W, 3)
        depth = np.full((height, width), np.inf)
        mask = np.zeros((height, width), dtype=np.int32)
        for rock, (c, r) in enumerate(zip(centres, radii), start=1):
            oc = eye - c
            a2 = np.einsum("hwk,hwk->hw", d, d)
            b = np.einsum("hwk,k->hw", d, oc)
            disc = b * b - a2 * (oc @ oc - r * r)
            hit = disc > 0
            t = np.where(hit, (-b - np.sqrt(np.where(hit, disc, 0.0))) / a2, np.inf)
            closer = hit & (t > 0) & (t < depth)
            depth[closer] = t[closer]
            mask[closer] = rock
        depth[~np.isfinite(depth)] = 0.0
        views.append(View(name=f"cam{i}", pose=pose, intrinsics=intr, depth=depth.astype(np.float32), mask=mask))
    return SceneBundle(units="cm", views=views, name=name, ground_truth="instance")
