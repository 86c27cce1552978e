"""A tiny analytic scene (spheres seen by a ring of pinhole cameras) built in memory.

Used to warm up the worker processes and the network at start-up (the first call of
every stage is several times slower than the next: lazy imports, allocator and
kernel caches), and by the tests and the benchmark as a cheap, valid request.  It
needs no data files, so a container can always warm itself up.
"""

from __future__ import annotations

import numpy as np

from shadowcorr.bundle import SceneBundle
from shadowcorr.synth.spheres import sphere_scene

__all__ = ["synthetic_bundle"]


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
    return sphere_scene(centres, radii, cameras=n_views, radius=600.0, height=280.0, width=width, height_px=height,
                        focal_px=0.9 * width, start_deg=float(np.rad2deg(0.3)), target=[0.0, 0.0, 20.0], name=name)
