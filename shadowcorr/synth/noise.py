"""Realism knobs: sensor and calibration errors applied to exact renderings.

All of them are off by default.  They model what separates the exact synthetic
ground truth from what a robot actually gets: noisy and quantised depth, imperfect
extrinsic calibration, instance masks from a 2D segmenter that bleed into or stop
short of the object boundary, and views that are missing.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def noisy_depth(rng: np.random.Generator, depth: np.ndarray, sigma: float | np.ndarray, quantum: float) -> np.ndarray:
    """Add N(0, sigma) to valid depth, then round to ``quantum``; invalid pixels stay 0.

    ``sigma`` is one value or one per pixel (e.g. growing with depth)."""
    valid = depth > 0
    out = depth.astype(np.float64)
    if np.any(np.asarray(sigma) > 0):
        out = out + rng.normal(scale=sigma, size=out.shape)
    if quantum > 0:
        out = np.round(out / quantum) * quantum
    # Noise must not turn a hit into an invalid pixel nor invent depth where none is.
    return np.where(valid, np.maximum(out, 1e-3), 0.0).astype(np.float32)


def rotation_from_vector(rv: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (axis * angle in radians) -> 3x3 matrix."""
    angle = float(np.linalg.norm(rv))
    if angle < 1e-15:
        return np.eye(3)
    k = rv / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def noisy_pose(rng: np.random.Generator, pose: np.ndarray, sigma_t: float, sigma_rot_deg: float) -> np.ndarray:
    """A miscalibrated camera-to-world pose: small random rotation about the camera
    centre (isotropic rotation vector, ``sigma_rot_deg`` per axis) and a position error
    of ``sigma_t`` per axis.  The image stays rendered from the true pose."""
    out = pose.copy()
    if sigma_rot_deg > 0:
        out[:3, :3] = rotation_from_vector(rng.normal(scale=np.deg2rad(sigma_rot_deg), size=3)) @ pose[:3, :3]
    if sigma_t > 0:
        out[:3, 3] = pose[:3, 3] + rng.normal(scale=sigma_t, size=3)
    return out


def perturbed_pose(rng: np.random.Generator, pose: np.ndarray, rotation_deg: float, translation: float) -> np.ndarray:
    """A pose off by exactly ``rotation_deg`` (about a random axis through the camera centre)
    and ``translation`` (in a random direction): the worst case of a pose error bound."""
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    out = pose.copy()
    out[:3, :3] = rotation_from_vector(axis / np.linalg.norm(axis) * np.deg2rad(rotation_deg)) @ pose[:3, :3]
    out[:3, 3] = pose[:3, 3] + direction / np.linalg.norm(direction) * translation
    return out


def morph_mask(ids: np.ndarray, px: int) -> np.ndarray:
    """Grow (``px`` > 0) every instance into the background, or erode it (``px`` < 0).

    Growing only takes background pixels (a segmenter's masks bleed into the ground, not
    into each other; where two rocks compete the larger id wins, which is arbitrary but
    deterministic).  Eroding removes every pixel whose (2|px|+1)^2 neighbourhood is not
    all of its own id, so shared boundaries between rocks recede on both sides.
    """
    if px == 0:
        return ids
    size = 2 * abs(px) + 1
    if px > 0:
        grown = ndimage.maximum_filter(ids, size=size, mode="nearest")
        return np.where(ids > 0, ids, grown).astype(ids.dtype)
    lo = ndimage.minimum_filter(ids, size=size, mode="nearest")
    hi = ndimage.maximum_filter(ids, size=size, mode="nearest")
    return np.where((lo == hi) & (ids > 0), ids, 0).astype(ids.dtype)


def boundary_noise(rng: np.random.Generator, ids: np.ndarray, prob: float) -> np.ndarray:
    """Jagged mask boundaries: each pixel whose 3x3 neighbourhood holds another id takes
    one of the neighbourhood's extreme ids (min or max, at random) with probability ``prob``."""
    if prob <= 0:
        return ids
    lo = ndimage.minimum_filter(ids, size=3, mode="nearest")
    hi = ndimage.maximum_filter(ids, size=3, mode="nearest")
    flip = (lo != hi) & (rng.random(ids.shape) < prob)
    pick = np.where(rng.random(ids.shape) < 0.5, lo, hi)
    return np.where(flip, pick, ids).astype(ids.dtype)
