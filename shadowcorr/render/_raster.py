"""Point splatting with a z-buffer: many coloured points -> one image, the highest priority per pixel wins.

Vectorised: one sort of (pixel, -priority) pairs picks each pixel's winner, so the result
does not depend on the order the points come in.
"""

from __future__ import annotations

import numpy as np

from .palette import RGB


MAX_SPLATS = 12_000_000  # points x splat pixels; beyond it the splat shrinks (memory, time)


def rasterise(x: np.ndarray, y: np.ndarray, priority: np.ndarray, colour: np.ndarray, size: tuple[int, int],
              background: RGB = (255, 255, 255), radius: int = 0) -> np.ndarray:
    """(H, W, 3) uint8 image of points at pixel (x, y); where several fall in one pixel the highest ``priority`` wins.

    Each point covers a (2 radius + 1)^2 pixel square, so samples spaced more widely
    than a pixel (a low-resolution view, a zoomed map) still draw closed surfaces.

    A z-buffer by sorting: points sorted by (pixel, -priority), the first of each pixel
    is kept.  Empty pixels with at least 4 filled neighbours take the colour of their
    highest-priority neighbour: that closes the sub-pixel gaps between samples without
    growing silhouettes.
    """
    width, height = size
    image = np.empty((height, width, 3), dtype=np.uint8)
    image[:] = background
    xi, yi = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    while radius > 0 and xi.size * (2 * radius + 1) ** 2 > MAX_SPLATS:
        radius -= 1
    if radius > 0:
        offsets = np.arange(-radius, radius + 1)
        ox, oy = (a.ravel() for a in np.meshgrid(offsets, offsets))
        xi = (xi[:, None] + ox).ravel()
        yi = (yi[:, None] + oy).ravel()
        copies = ox.size
        priority, colour = np.repeat(priority, copies), np.repeat(colour, copies, axis=0)
    inside = (xi >= 0) & (xi < width) & (yi >= 0) & (yi < height)
    xi, yi, priority, colour = xi[inside], yi[inside], priority[inside], colour[inside]
    if xi.size == 0:
        return image
    pixel = yi * width + xi
    order = np.lexsort((-priority, pixel))
    _, first = np.unique(pixel[order], return_index=True)
    win = order[first]
    best = np.full((height, width), -np.inf)
    best.reshape(-1)[pixel[win]] = priority[win]
    image.reshape(-1, 3)[pixel[win]] = colour[win]

    # Work on the points' bounding box only (plus the one-pixel ring the fill may reach),
    # and carry source indices through the 8 shifts instead of colour arrays.
    ys0, ys1 = max(int(yi.min()) - 1, 0), min(int(yi.max()) + 2, height)
    xs0, xs1 = max(int(xi.min()) - 1, 0), min(int(xi.max()) + 2, width)
    sub = best[ys0:ys1, xs0:xs1]
    sh, sw = sub.shape
    padded = np.pad(sub, 1, constant_values=-np.inf)
    source = np.arange(padded.size).reshape(padded.shape)
    fill_p = np.full((sh, sw), -np.inf)
    fill_src = np.zeros((sh, sw), dtype=np.int64)
    neighbours = np.zeros((sh, sw), dtype=np.int8)
    for dy in (-1, 0, 1):  # 8 shifted views, each vectorised over the box
        for dx in (-1, 0, 1):
            if dx == 0 and dy == 0:
                continue
            window = (slice(1 + dy, 1 + dy + sh), slice(1 + dx, 1 + dx + sw))
            p = padded[window]
            neighbours += np.isfinite(p)
            better = p > fill_p
            fill_p = np.where(better, p, fill_p)
            fill_src = np.where(better, source[window], fill_src)
    gap = ~np.isfinite(sub) & (neighbours >= 4)
    padded_c = np.pad(image[ys0:ys1, xs0:xs1], ((1, 1), (1, 1), (0, 0))).reshape(-1, 3)
    image[ys0:ys1, xs0:xs1][gap] = padded_c[fill_src[gap]]
    return image
