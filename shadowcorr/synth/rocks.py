"""Procedural rock meshes: noise-displaced, anisotropically scaled, facet-cut icospheres.

A rock starts as a subdivided icosahedron (uniform vertex density, no pole artefacts),
whose radius is modulated by band-limited noise on the sphere (random Fourier features
with a power-law spectrum: broad lumps plus smaller bumps, enough to make dents that
a convex hull does not have).  It is then stretched along random principal axes
(elongated and flattened rocks), partly cut by a few planes (the flat fracture faces
real rocks show), and finally scaled so that its largest extent equals the requested
diameter.  Everything is vectorised numpy and depends only on the generator passed in.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

# Golden-ratio construction of the regular icosahedron (12 vertices, 20 faces).
_PHI = (1.0 + 5.0**0.5) / 2.0
_ICO_VERTS = np.array(
    [
        [-1, _PHI, 0], [1, _PHI, 0], [-1, -_PHI, 0], [1, -_PHI, 0],
        [0, -1, _PHI], [0, 1, _PHI], [0, -1, -_PHI], [0, 1, -_PHI],
        [_PHI, 0, -1], [_PHI, 0, 1], [-_PHI, 0, -1], [-_PHI, 0, 1],
    ],
    dtype=np.float64,
)
_ICO_FACES = np.array(
    [
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
        [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
        [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
        [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
    ],
    dtype=np.int64,
)


@lru_cache(maxsize=8)
def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere with ``10 * 4**s + 2`` vertices and ``20 * 4**s`` outward-wound faces.

    Cached (and returned read-only) because every rock of a scene shares the same
    topology; only vertex positions differ.
    """
    verts = _ICO_VERTS / np.linalg.norm(_ICO_VERTS, axis=1, keepdims=True)
    faces = _ICO_FACES.copy()
    for _ in range(subdivisions):
        # Every edge gets one midpoint; shared edges must share it, so dedupe sorted pairs.
        edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        edges.sort(axis=1)
        uniq, inverse = np.unique(edges, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        mids = verts[uniq[:, 0]] + verts[uniq[:, 1]]
        mids /= np.linalg.norm(mids, axis=1, keepdims=True)
        n_f = len(faces)
        m01, m12, m20 = (len(verts) + inverse[k * n_f:(k + 1) * n_f] for k in range(3))
        a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
        faces = np.concatenate(
            [
                np.stack([a, m01, m20], 1),
                np.stack([b, m12, m01], 1),
                np.stack([c, m20, m12], 1),
                np.stack([m01, m12, m20], 1),
            ]
        )
        verts = np.concatenate([verts, mids])
    verts.setflags(write=False)
    faces.setflags(write=False)
    return verts, faces


@dataclass
class RockMesh:
    """A rock in its own body frame: centred on its centre of volume, units of the scene."""

    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int32, counter-clockwise seen from outside
    diameter: float  # largest extent (along the first principal axis)

    @property
    def volume(self) -> float:
        """Enclosed volume by the divergence theorem (mesh is closed and outward wound)."""
        v = self.vertices[self.faces]
        return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def _sphere_noise(rng: np.random.Generator, dirs: np.ndarray, n_waves: int, beta: float) -> np.ndarray:
    """Zero-mean, unit-std band-limited noise on unit directions.

    Sum of plane waves with random directions and between 0.6 and 5 cycles across the
    sphere's diameter, amplitude ``f**-beta``: low frequencies dominate (lumpy outline), higher
    ones add the surface bumps.  Evaluated for all vertices in one matrix product.
    """
    k = rng.normal(size=(n_waves, 3))
    k /= np.linalg.norm(k, axis=1, keepdims=True)
    freq = rng.uniform(0.6, 5.0, size=n_waves)
    phase = rng.uniform(0.0, 2.0 * np.pi, size=n_waves)
    amp = freq**-beta
    n = np.sin(np.pi * (dirs @ (k * freq[:, None]).T) + phase) @ amp
    n -= n.mean()
    return n / (n.std() + 1e-12)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly random rotation matrix (QR of a Gaussian matrix, sign-fixed)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def make_rock(
    rng: np.random.Generator,
    diameter: float,
    *,
    subdivisions: int = 4,
    roughness: float = 0.22,
    elongation: tuple[float, float] = (0.55, 1.0),
    flatness: tuple[float, float] = (0.35, 0.8),
    max_cuts: int = 3,
) -> RockMesh:
    """Make one irregular rock of the given diameter (largest extent), centred on its centroid.

    ``roughness`` is the std of the radial noise relative to the radius; 0.2–0.3 gives
    visible dents and lumps while keeping the surface star-shaped (no self-intersection:
    the radius stays positive because it is clipped at 0.45).  ``elongation`` and
    ``flatness`` are the ranges of the middle and smallest axis relative to the largest.
    """
    dirs, faces = icosphere(subdivisions)
    noise = _sphere_noise(rng, dirs, n_waves=24, beta=1.3)
    radius = np.clip(1.0 + roughness * noise, 0.45, None)
    v = dirs * radius[:, None]

    # Anisotropic stretch along a random frame: b/a in `elongation`, c/b in `flatness`.
    b = rng.uniform(*elongation)
    c = b * rng.uniform(*flatness)
    frame = _random_rotation(rng)
    v = ((v @ frame) * np.array([1.0, b, c])) @ frame.T

    # Fracture facets: vertices beyond a random plane are pulled back onto it.  Cutting
    # at 55–85 % of the support keeps each cut a facet rather than a slice.
    for _ in range(int(rng.integers(0, max_cuts + 1))):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        s = v @ n
        d = s.max() * rng.uniform(0.55, 0.85)
        over = s > d
        v[over] -= np.outer(s[over] - d, n)

    # Scale to the target diameter measured along the first principal axis (the way a
    # person would measure a rock's size), then centre on the volume centroid so that
    # the physics body frame and the mesh frame agree.
    centred = v - v.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    extent = np.ptp(centred @ vt[0])
    v = centred * (diameter / extent)
    v -= _volume_centroid(v, faces)
    return RockMesh(vertices=v, faces=np.ascontiguousarray(faces, dtype=np.int32), diameter=float(diameter))


def _volume_centroid(v: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Centre of volume of a closed mesh (signed tetrahedra against the origin)."""
    tri = v[faces]
    vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    cent = tri.sum(axis=1) / 4.0
    return (vol[:, None] * cent).sum(axis=0) / vol.sum()


def sample_diameters(rng: np.random.Generator, n: int, lo: float, hi: float) -> np.ndarray:
    """Rock diameters, log-uniform in [lo, hi]: many small rocks, a few large ones."""
    return np.exp(rng.uniform(np.log(lo), np.log(hi), size=n))
