"""Uneven regolith ground as a regular heightfield.

Fractal (power-law spectrum) relief plus a few small craters, sampled on a square grid
centred on the scene origin.  A heightfield, not a mesh, because MuJoCo collides meshes
as their convex hulls: a hull of a bumpy ground would be a flat slab, while a heightfield
collides cell by cell with the true relief.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Terrain:
    """Heights ``z[r, c]`` at ``x = -half + c * step``, ``y = -half + r * step``."""

    heights: np.ndarray  # (n, n) float64, scene units
    half_size: float

    @property
    def n(self) -> int:
        return self.heights.shape[0]

    @property
    def step(self) -> float:
        return 2.0 * self.half_size / (self.n - 1)

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear ground height at world (x, y) (clamped to the grid edge outside it)."""
        fx = np.clip((np.asarray(x, dtype=np.float64) + self.half_size) / self.step, 0, self.n - 1 - 1e-9)
        fy = np.clip((np.asarray(y, dtype=np.float64) + self.half_size) / self.step, 0, self.n - 1 - 1e-9)
        c0 = np.floor(fx).astype(int)
        r0 = np.floor(fy).astype(int)
        tx, ty = fx - c0, fy - r0
        h = self.heights
        return (
            h[r0, c0] * (1 - tx) * (1 - ty)
            + h[r0, c0 + 1] * tx * (1 - ty)
            + h[r0 + 1, c0] * (1 - tx) * ty
            + h[r0 + 1, c0 + 1] * tx * ty
        )

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Triangle mesh of the heightfield (two triangles per cell, normals up)."""
        n = self.n
        g = np.linspace(-self.half_size, self.half_size, n)
        xx, yy = np.meshgrid(g, g)
        verts = np.stack([xx.ravel(), yy.ravel(), self.heights.ravel()], axis=1)
        idx = np.arange(n * n).reshape(n, n)
        a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]).astype(np.int32)
        return verts, faces


def fractal_noise(rng: np.random.Generator, n: int, beta: float = 2.2) -> np.ndarray:
    """Zero-mean, unit-std 2D noise with power spectrum ``~ f**-beta`` (FFT synthesis)."""
    white = rng.normal(size=(n, n))
    f = np.sqrt(np.fft.fftfreq(n)[:, None] ** 2 + np.fft.rfftfreq(n)[None, :] ** 2)
    f[0, 0] = np.inf  # no DC term: the mean height is set by the caller
    field = np.fft.irfft2(np.fft.rfft2(white) * f ** (-beta / 2.0), s=(n, n))
    field -= field.mean()
    return field / (field.std() + 1e-12)


def make_terrain(
    rng: np.random.Generator,
    *,
    half_size: float = 1500.0,
    resolution: int = 256,
    relief: float = 12.0,
    n_craters: int = 4,
    crater_radius: tuple[float, float] = (60.0, 250.0),
) -> Terrain:
    """Random ground: fractal relief of RMS ``relief`` plus ``n_craters`` bowl craters.

    The relief is a gentle undulation (RMS ~12 units over hundreds of units): enough
    that rocks settle at varied heights and tilts, not so steep that they roll away.
    Craters are parabolic bowls (depth ~12 % of the radius) with a raised rim, the
    typical small lunar crater profile.
    """
    h = relief * fractal_noise(rng, resolution)
    g = np.linspace(-half_size, half_size, resolution)
    xx, yy = np.meshgrid(g, g)
    for _ in range(n_craters):
        r = rng.uniform(*crater_radius)
        cx, cy = rng.uniform(-0.6 * half_size, 0.6 * half_size, size=2)
        rho = np.hypot(xx - cx, yy - cy) / r
        depth = 0.12 * r
        bowl = np.where(rho < 1.0, depth * (rho**2 - 1.0), 0.0)
        rim = 0.25 * depth * np.exp(-((rho - 1.0) / 0.25) ** 2)
        h += bowl + rim
    # The scene centre sits at height ~0 so that camera heights mean what they say.
    h -= np.median(h[np.hypot(xx, yy) < 300.0]) if half_size > 300.0 else h.mean()
    return Terrain(heights=h, half_size=half_size)
