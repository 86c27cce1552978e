"""Per-view images: shaded depth, segment masks filled in a colour, outlines and id labels.

The pixels of a segment are found exactly as the engine cut them
(``shadowcorr.stages.find_blobs``: 8-connected blobs per instance value, largest
component first, blobs under ``min_blob_pixels`` ignored), so a result's
``(view, instance, component)`` names one blob of the mask and nothing else.
"""

from __future__ import annotations

import numpy as np
from PIL import Image
from scipy import ndimage

from ..bundle import View
from ..config import ShadowCorrConfig
from ..stages import find_blobs
from ._draw import CORNERS, Box, Label, banner, banner_box, draw_labels, font, hazard_stripes, label_box_size
from .palette import RGB, WARNING_STRIPES


def valid_depth(depth: np.ndarray, max_depth: float) -> np.ndarray:
    """Pixels whose depth the engine would back-project (finite, > 0, <= max_depth)."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth) & (depth > 0) & (depth <= max_depth)


def shade_depth(view: View, max_depth: float) -> np.ndarray:
    """(H, W, 3) uint8 grey picture of a depth map: inverse depth lit by surface normals.

    Inverse depth alone gives near = bright but flat blobs; Lambert shading from normals
    of the (smoothed) depth surface makes the rocks' shapes readable.  The depth is
    smoothed first because depth stored as half floats is quantised to about one unit,
    which would otherwise turn normals into stripes.  Invalid depth is drawn near-black.
    """
    depth = np.asarray(view.depth, dtype=np.float32)
    valid = valid_depth(depth, max_depth)
    height, width = depth.shape
    if not valid.any():
        return np.full((height, width, 3), 20, dtype=np.uint8)
    inv = np.zeros_like(depth)
    inv[valid] = 1.0 / depth[valid]
    lo, hi = np.percentile(inv[valid], [1.0, 99.0])
    near = np.clip((inv - lo) / max(hi - lo, 1e-12), 0.0, 1.0)

    # Normalised convolution: smooth only over valid pixels so holes do not bleed in as zeros.
    sigma = max(1.0, min(height, width) / 400.0)
    weight = ndimage.gaussian_filter(valid.astype(np.float32), sigma)
    smooth = ndimage.gaussian_filter(np.where(valid, depth, 0.0).astype(np.float32), sigma) / np.maximum(weight, 1e-6)
    # Normal of the surface d(u, v) of a pinhole camera, in closed form: with
    # P = d * ((u - cx) / fx, (v - cy) / fy, 1), the cross product dP/du x dP/dv is d times
    # (-fx d_u, -fy d_v, fx d_u xn + fy d_v yn + d) / (fx fy); flipped to face the camera.
    # Two 2-D gradients instead of 3-vector gradients and cross products: 5x faster.
    k = view.intrinsics
    d_v, d_u = np.gradient(smooth)
    xn = (np.arange(width, dtype=np.float32) - k.cx) / k.fx
    yn = (np.arange(height, dtype=np.float32)[:, None] - k.cy) / k.fy
    nx, ny = k.fx * d_u, k.fy * d_v
    nz = -(nx * xn + ny * yn + smooth)
    light = np.array([-0.35, -0.6, -1.0], dtype=np.float32)  # from above-left, behind the camera
    light /= np.linalg.norm(light)
    lambert = np.clip((nx * light[0] + ny * light[1] + nz * light[2]) / np.sqrt(nx * nx + ny * ny + nz * nz + 1e-12),
                      0.0, 1.0)

    grey = 35.0 + 120.0 * near + 90.0 * lambert
    grey = np.where(valid, grey, 18.0)
    return np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=-1)


def segment_index_image(view: View, lookup: dict[tuple[int, int], int], engine: ShadowCorrConfig) -> np.ndarray:
    """(H, W) int64 image of result segment indices (-1 = none) for one view.

    ``lookup`` maps ``(instance, component)`` of this view to the result's segment index;
    blobs the result does not list stay -1 (undrawn).
    """
    mask = np.asarray(view.mask)
    blobs = find_blobs(mask, engine.split_components, engine.min_blob_pixels)
    seg_of_blob = [lookup.get(key, -1) for key in zip(blobs.instance.tolist(), blobs.component.tolist())]  # per blob
    return blobs.label_image(np.asarray(seg_of_blob, dtype=np.int64))


def edge_band(seg_image: np.ndarray, width: int) -> np.ndarray:
    """Pixels of a segment within ``width`` pixels (Chebyshev) of a pixel that is not in it."""
    band = np.zeros(seg_image.shape, dtype=bool)
    on = seg_image >= 0
    rows, cols = np.flatnonzero(on.any(axis=1)), np.flatnonzero(on.any(axis=0))
    if width <= 0 or rows.size == 0:
        return band
    # Only the segments' bounding box (plus the band) can hold band pixels: filter just that.
    window = (slice(max(rows[0] - width, 0), rows[-1] + width + 1), slice(max(cols[0] - width, 0), cols[-1] + width + 1))
    sub = seg_image[window].astype(np.int32)
    size = 2 * width + 1
    # A window holding one label only has min == max; any other label (or -1) breaks that.
    lo = ndimage.minimum_filter(sub, size=size, mode="nearest")
    hi = ndimage.maximum_filter(sub, size=size, mode="nearest")
    band[window] = (sub >= 0) & (lo != hi)
    return band


def label_anchors(seg_image: np.ndarray, num_segments: int) -> dict[int, tuple[float, float, tuple[slice, slice]]]:
    """Per segment present in the image, its innermost pixel (x, y) and its bounding box (slices).

    The innermost pixel (largest distance to the segment's border) always lies inside
    the segment, unlike the centroid of a crescent-shaped or holed blob, so a label
    written there marks the right region.
    """
    anchors: dict[int, tuple[float, float, tuple[slice, slice]]] = {}
    windows = ndimage.find_objects(seg_image + 1, max_label=num_segments)
    for s, window in enumerate(windows):  # one iteration per segment
        if window is None:
            continue
        inside = np.pad(seg_image[window] == s, 1)  # pad: the window's edge counts as outside
        dist = ndimage.distance_transform_edt(inside)
        y, x = np.unravel_index(int(np.argmax(dist)), dist.shape)
        anchors[s] = (float(x - 1 + window[1].start), float(y - 1 + window[0].start), window)
    return anchors


def compose(base: np.ndarray, seg_image: np.ndarray, fill: np.ndarray, outline: np.ndarray, *, alpha: float,
            outline_px: int, hazard: np.ndarray | None = None, hazard_px: int = 0) -> np.ndarray:
    """Blend segment colours over ``base`` and draw their outlines.

    ``fill`` and ``outline`` are (S, 3) colours per segment; inside a segment a pixel is
    ``(1 - alpha) * base + alpha * fill`` (exactly ``fill`` with ``alpha == 1``); its
    border band of ``outline_px`` pixels is solid ``outline``.  Segments flagged in
    ``hazard`` get a wider band of black/yellow stripes instead.
    """
    out = base.astype(np.float32)
    on = seg_image >= 0
    idx = seg_image[on]
    out[on] = (1.0 - alpha) * out[on] + alpha * fill[idx].astype(np.float32)
    out = np.clip(np.rint(out), 0, 255).astype(np.uint8)
    band = edge_band(seg_image, outline_px)
    out[band] = outline[seg_image[band]]
    if hazard is not None and hazard.any() and hazard_px > 0:
        warn = edge_band(seg_image, hazard_px)
        warn &= hazard[np.maximum(seg_image, 0)]
        stripes = hazard_stripes(seg_image.shape, max(3, hazard_px * 2), WARNING_STRIPES)
        out[warn] = stripes[warn]
    return out


def view_picture(base: np.ndarray, seg_image: np.ndarray, fill: np.ndarray, outline: np.ndarray,
                 texts: dict[int, str], borders: np.ndarray, legend: list[tuple[str, RGB | None]], *, alpha: float,
                 outline_px: int, draw_text: bool, hazard: np.ndarray | None = None
                 ) -> tuple[Image.Image, Image.Image, list[Box]]:
    """One annotated view: fills, outlines, optional hazard outlines, labels and a legend panel.

    Returns the picture, the same picture without the legend panel (for thumbnails,
    which are cropped and would show a cut-off panel) and the boxes of the labels.
    """
    height = seg_image.shape[0]
    hazard_px = max(3, round(height / 220))
    pixels = compose(base, seg_image, fill, outline, alpha=alpha, outline_px=outline_px, hazard=hazard,
                     hazard_px=hazard_px)
    image = Image.fromarray(pixels, mode="RGB")
    if not draw_text:
        return image, image, []
    legend_font = font(max(11, round(height / 48)))
    corner = "top-left"
    if legend:
        # The corner where the legend hides the fewest segment pixels.
        def hidden(c: str) -> int:
            x0, y0, x1, y1 = (int(v) for v in banner_box(image, legend, legend_font, c))
            return int(np.count_nonzero(seg_image[y0:y1 + 1, x0:x1 + 1] >= 0))

        corner = min(CORNERS, key=hidden)
    avoid = [banner_box(image, legend, legend_font, corner)] if legend else []
    label_font = font(max(11, round(height / 34)))
    anchors = label_anchors(seg_image, fill.shape[0])
    # Larger segments first: their labels get the best spots, small ones get nudged.
    sizes = np.bincount(seg_image[seg_image >= 0], minlength=fill.shape[0])
    order = sorted(anchors, key=lambda s: -sizes[s])
    labels = []
    for s in (s for s in order if s in texts):
        x, y, window = anchors[s]
        colour = tuple(int(c) for c in borders[s])
        # A label that would hide most of its segment goes beside it (with a leader line).
        bw, bh, _ = label_box_size(texts[s], label_font)
        rows = slice(max(int(y - bh / 2), 0), int(y + bh / 2) + 1)
        cols = slice(max(int(x - bw / 2), 0), int(x + bw / 2) + 1)
        hidden = np.count_nonzero(seg_image[rows, cols] == s) / max(sizes[s], 1)
        clear = (window[1].start, window[0].start, window[1].stop, window[0].stop) if hidden > 0.5 else None
        labels.append(Label((x, y), texts[s], colour, label_font, clear=clear))
    boxes = draw_labels(image, labels, avoid=avoid)
    plain = image.copy()
    if legend:
        banner(image, legend, legend_font, corner)
    return image, plain, boxes


def crop_box(seg_image: np.ndarray, boxes: list[Box] = (), *, margin: float = 0.08,
             min_fraction: float = 0.4) -> tuple[int, int, int, int]:
    """(left, top, right, bottom) around all segments and ``boxes`` (labels), for thumbnails.

    Rocks often fill a fifth of a view; a thumbnail of the whole view shrinks them to
    specks.  The box keeps the view's aspect ratio (tiles stay uniform), adds
    ``margin`` of its size on each side, is at least ``min_fraction`` of the view wide
    (no absurd magnification of a single small rock) and stays inside the view.
    """
    height, width = seg_image.shape
    rows = np.flatnonzero((seg_image >= 0).any(axis=1))
    cols = np.flatnonzero((seg_image >= 0).any(axis=0))
    if rows.size == 0:
        return (0, 0, width, height)
    top, bottom, left, right = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    for x0, y0, x1, y1 in boxes:
        left, top, right, bottom = min(left, x0), min(top, y0), max(right, x1), max(bottom, y1)
    box_w = (right - left) * (1 + 2 * margin)
    box_h = (bottom - top) * (1 + 2 * margin)
    aspect = width / height
    box_w = min(max(box_w, box_h * aspect, min_fraction * width), width)
    box_h = box_w / aspect
    cx = min(max((left + right) / 2, box_w / 2), width - box_w / 2)
    cy = min(max((top + bottom) / 2, box_h / 2), height - box_h / 2)
    return (int(round(cx - box_w / 2)), int(round(cy - box_h / 2)), int(round(cx + box_w / 2)), int(round(cy + box_h / 2)))
