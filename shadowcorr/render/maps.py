"""Top-down map and side view of a scene: back-projected segment points coloured by object.

Both views are orthographic and share one scale (pixels per bundle unit) and the same
horizontal range, so a rock is as wide in the side view as on the map and the two line
up when placed one above the other.  "Up" is a world axis: the one closest to the
cameras' mean up direction (``-y`` of the OpenCV camera frame), unless the caller
names it.  Points are rasterised with a z-buffer (the highest point wins on the map,
the nearest to the viewer in the side view), so nothing depends on drawing order.

Cameras usually stand far outside the rock field (in the sample scene the cameras
span four times the rocks' extent), which would shrink the rocks to a few pixels.
When the cameras would blow the frame up by more than ``ZOOM_AREA_RATIO`` in area,
the maps frame the objects instead: cameras outside the frame are marked at its edge,
in their direction, and the top-down map gets an overview inset with the true camera
positions and the zoomed frame outlined.

The objects' frame is robust: an object whose centre lies far outside the others
(beyond Tukey's fences, 1.5 interquartile ranges past the quartiles of the centres, on
either map axis) does not stretch the map; it is labelled at the frame's edge, marked
"(beyond)", and shown in the overview inset.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw

from ..config import UpAxis
from ..poses import world_up
from ._draw import Label, draw_arrow, draw_labels, font, text_size, wrap
from ._raster import rasterise
from .palette import CAMERA, RGB, object_colour, object_colours

AXIS_NAMES = ("x", "y", "z")
BACKGROUND: RGB = (255, 255, 255)
GRID: RGB = (228, 228, 228)
FRAME: RGB = (60, 60, 60)
ZOOM_AREA_RATIO = 2.5
Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class MapFrame:
    """World axes of the drawings: ``right`` (page x), ``forward`` (map page y) and ``up``.

    ``right`` and ``forward`` are positive world axes, so tick labels are plain world
    coordinates; ``up`` may be negative (an OpenCV-style world has ``-y`` up), and
    ``right x forward == up`` keeps the map seen from above, not mirrored.
    """

    right: int  # world axis index
    forward: int
    up: int
    up_sign: float

    @property
    def up_name(self) -> str:
        return ("" if self.up_sign > 0 else "-") + AXIS_NAMES[self.up]


def choose_frame(poses: np.ndarray, up_axis: UpAxis = "auto") -> MapFrame:
    """The map frame for cameras with camera-to-world ``poses`` (V, 4, 4), OpenCV convention."""
    k, sign = world_up(poses, up_axis)
    a, b = (k + 1) % 3, (k + 2) % 3
    right, forward = (a, b) if sign > 0 else (b, a)  # e_a x e_b = e_k; swap for a downward-named axis
    return MapFrame(right=right, forward=forward, up=k, up_sign=sign)


def nice_step(span: float, target: int = 6) -> float:
    """A 1/2/5 x 10^n step that cuts ``span`` into about ``target`` intervals."""
    if not span > 0 or not math.isfinite(span):
        return 1.0
    raw = span / target
    power = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * power >= raw:
            return m * power
    return 10.0 * power


def nice_length(limit: float) -> float:
    """The largest 1/2/5 x 10^n not above ``limit`` (a scale bar length)."""
    if not limit > 0 or not math.isfinite(limit):
        return 1.0
    power = 10.0 ** math.floor(math.log10(limit))
    for m in (5.0, 2.0, 1.0):
        if m * power <= limit:
            return m * power
    return power


def _fmt(value: float) -> str:
    value = 0.0 if abs(value) < 1e-9 else value  # no "-0"
    return f"{value:g}" if abs(value) < 1e6 else f"{value:.3g}"


@dataclass
class Axes:
    """Orthographic page layout: world (h, v) -> pixel (x, y) at ``scale`` pixels per unit."""

    h0: float
    h1: float
    v0: float
    v1: float
    scale: float
    left: int = 96
    top: int = 86
    right_margin: int = 28
    bottom: int = 76

    @property
    def size(self) -> tuple[int, int]:
        return (int(math.ceil(self.left + (self.h1 - self.h0) * self.scale + self.right_margin)),
                int(math.ceil(self.top + (self.v1 - self.v0) * self.scale + self.bottom)))

    @property
    def plot_box(self) -> Box:
        return (float(self.left), float(self.top), self.left + (self.h1 - self.h0) * self.scale,
                self.top + (self.v1 - self.v0) * self.scale)

    def to_px(self, h: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.left + (np.asarray(h) - self.h0) * self.scale, self.top + (self.v1 - np.asarray(v)) * self.scale


@dataclass
class MapScene:
    """What the maps draw, in bundle units."""

    points: np.ndarray  # (N, 3) world points
    point_object: np.ndarray  # (N,) object id per point
    object_ids: np.ndarray  # (K,) objects to label
    object_centres: np.ndarray  # (K, 3) label anchors (world), NaN rows are not labelled
    camera_centres: np.ndarray  # (V, 3)
    camera_axes: np.ndarray  # (V, 3) unit optical axes
    camera_names: list[str]
    units: str
    point_spacing: float = 0.0  # typical distance between neighbouring points (world units)


def _shade(colour: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Darken colours by up to 45% where ``t`` (0-1) is low: gives the point clouds some relief."""
    return np.clip(colour.astype(np.float32) * (0.55 + 0.45 * np.clip(t, 0, 1))[:, None], 0, 255).astype(np.uint8)


def _extent(values: np.ndarray) -> tuple[float, float]:
    return (float(values.min()), float(values.max())) if values.size else (0.0, 0.0)


def _padded(lo: float, hi: float, pad: float) -> tuple[float, float]:
    return lo - pad, hi + pad


def framed_points(points: np.ndarray, point_object: np.ndarray, axes: tuple[int, int]) -> np.ndarray:
    """Which points belong to objects inside Tukey's fences of the object centres on both map ``axes``.

    With fewer than four objects every point is framed (quartiles of so few say nothing).
    The fences are widened by the median object radius, so that rocks of a tight cluster
    are never cut off.
    """
    ids, inverse = np.unique(point_object, return_inverse=True)
    if ids.size < 4:
        return np.ones(len(points), dtype=bool)
    keep_object = np.ones(ids.size, dtype=bool)
    counts = np.bincount(inverse, minlength=ids.size)
    for axis in axes:
        coord = points[:, axis]
        centre = np.bincount(inverse, weights=coord, minlength=ids.size) / counts
        lo_obj = np.full(ids.size, np.inf)
        hi_obj = np.full(ids.size, -np.inf)
        np.minimum.at(lo_obj, inverse, coord)
        np.maximum.at(hi_obj, inverse, coord)
        radius = float(np.median(hi_obj - lo_obj)) / 2
        q1, q3 = np.percentile(centre, [25, 75])
        reach = 1.5 * (q3 - q1) + radius
        keep_object &= (centre >= q1 - reach) & (centre <= q3 + reach)
    return keep_object[inverse]


def render_maps(scene: MapScene, frame: MapFrame, map_size: int = 1000) -> tuple[Image.Image, Image.Image]:
    """The top-down map and the side view (see the module docstring)."""
    r, f = frame.right, frame.forward
    pts, cams = scene.points, scene.camera_centres
    height = lambda p: frame.up_sign * p[..., frame.up]  # noqa: E731
    # No point at all: frame the cameras.  Otherwise the objects, less far outliers (labelled at the edge).
    objects = pts[framed_points(pts, scene.point_object, (r, f))] if pts.size else cams
    everything = np.concatenate([pts, cams])
    ob_r, ob_f, ob_h = _extent(objects[:, r]), _extent(objects[:, f]), _extent(height(objects))
    al_r, al_f, al_h = _extent(everything[:, r]), _extent(everything[:, f]), _extent(height(everything))
    area = lambda a, b: max(a[1] - a[0], 1e-9) * max(b[1] - b[0], 1e-9)  # noqa: E731
    zoom = area(al_r, al_f) > ZOOM_AREA_RATIO * area(ob_r, ob_f) and pts.size > 0
    span_r, span_f = (ob_r, ob_f) if zoom else (al_r, al_f)
    span = max(span_r[1] - span_r[0], span_f[1] - span_f[0])
    span = span if span > 1e-9 else 1.0  # a single camera and no point: any scale will do
    pad = (0.06 if zoom else 0.12) * span  # unzoomed: room for the camera arrows
    range_r, range_f = _padded(*span_r, pad), _padded(*span_f, pad)
    scale = map_size / max(range_r[1] - range_r[0], range_f[1] - range_f[0])
    arrow_px = 0.08 * map_size

    colours = object_colours(scene.point_object)
    hts = height(pts)
    t_height = (hts - ob_h[0]) / max(ob_h[1] - ob_h[0], 1e-9)
    names = AXIS_NAMES
    top_axes = Axes(*range_r, *range_f, scale)
    if zoom:
        # The overview goes in a column right of the plot, where it hides nothing.
        margin = 0.1 * max(al_r[1] - al_r[0], al_f[1] - al_f[0])
        full_r, full_f = _padded(*al_r, margin), _padded(*al_f, margin)
        inset_scale = 0.3 * map_size / max(full_r[1] - full_r[0], full_f[1] - full_f[0])
        inset_axes = Axes(*full_r, *full_f, inset_scale, left=4, top=24, right_margin=4, bottom=4)
        top_axes.right_margin += inset_axes.size[0] + 8
    note = "colour = object id; ring + arrow = camera and its optical axis"
    note += "; square = camera beyond the frame, at its nearest edge point" if zoom else ""
    top, taken = _draw_map(
        scene, top_axes, pts[:, r], pts[:, f], hts, _shade(colours, 0.3 + 0.7 * t_height),
        cams[:, r], cams[:, f], scene.camera_axes[:, r], scene.camera_axes[:, f], arrow_px, names[r], names[f],
        f"Top-down map (looking down {frame.up_name})", note,
    )
    if zoom:
        _inset(top, top_axes, inset_axes, scene, frame)
    _label_objects_at(top, top_axes, scene, scene.object_centres[:, r], scene.object_centres[:, f], taken)

    # Side view: the viewer stands at -forward looking along +forward, so the smallest
    # forward coordinate is nearest and wins the z-buffer; nearer points are brighter.
    near = -pts[:, f]
    t_near = (near - near.min()) / max(float(np.ptp(near)), 1e-9) if near.size else near
    v_lo, v_hi = ob_h if zoom else al_h
    lane_px = text_size(ImageDraw.Draw(top), "0", font(17))[1] + 14
    lanes = _lanes(scene, top_axes, scene.object_centres[:, r], lane_px)
    v_pad = 0.08 * max(v_hi - v_lo, 1e-9) + 6 / scale
    # Above the tallest rock: the label lanes, then a band for cameras beyond the frame.
    room = ((lanes.max(initial=-1) + 1) * lane_px + 16 + (48 if zoom else 0)) / scale
    side_axes = Axes(*range_r, v_lo - v_pad, v_hi + v_pad + room, scale)
    side, taken = _draw_map(
        scene, side_axes, pts[:, r], hts, near, _shade(colours, 0.3 + 0.7 * t_near),
        cams[:, r], height(cams), scene.camera_axes[:, r], height(scene.camera_axes), arrow_px, names[r],
        frame.up_name, f"Side view (looking along +{names[f]})",
        "nearer points brighter; " + note,
    )
    _label_objects_in_lanes(side, side_axes, scene, scene.object_centres[:, r], hts, lanes, lane_px, v_hi + v_pad,
                            taken)
    return top, side


def _draw_map(scene: MapScene, axes: Axes, h: np.ndarray, v: np.ndarray, priority: np.ndarray, colours: np.ndarray,
              cam_h: np.ndarray, cam_v: np.ndarray, axis_h: np.ndarray, axis_v: np.ndarray, arrow_px: float,
              h_name: str, v_name: str, title: str, subtitle: str) -> tuple[Image.Image, list[Box]]:
    """Points, grid, ticks, scale bar and cameras of one orthographic view.

    Returns the image and the boxes already drawn in the plot (for labels to avoid).
    """
    size = axes.size
    px, py = axes.to_px(h, v)
    # Splat each point over about the spacing between neighbouring samples.
    radius = int(min(6, scene.point_spacing * axes.scale / 2))
    pixels = rasterise(px, py, priority, colours, size, radius=radius)
    on_points = np.any(pixels != np.asarray(BACKGROUND, np.uint8), axis=-1)
    image = Image.new("RGB", size, BACKGROUND)
    _draw_grid(image, axes, h_name, v_name, scene.units, title, subtitle)
    # Points go over the grid lines: paste them on top of the finished frame.
    canvas = np.asarray(image).copy()
    x0, y0, x1, y1 = (int(round(c)) for c in axes.plot_box)
    inner = np.zeros(on_points.shape, dtype=bool)
    inner[y0 + 2:y1 - 1, x0 + 2:x1 - 1] = True
    canvas[on_points & inner] = pixels[on_points & inner]
    image = Image.fromarray(canvas, mode="RGB")
    taken = [_draw_scale_bar(image, axes, scene.units)]
    taken += _draw_cameras(image, axes, scene.camera_names, cam_h, cam_v, axis_h, axis_v, arrow_px, avoid=taken)
    return image, taken


def _draw_grid(image: Image.Image, axes: Axes, h_name: str, v_name: str, units: str, title: str, subtitle: str) -> None:
    """Grid, ticks, tick labels, axis names and title around the plot area."""
    draw = ImageDraw.Draw(image)
    x0, y0, x1, y1 = axes.plot_box
    tick_font, name_font, title_font = font(15), font(17), font(19)
    step = nice_step(max(axes.h1 - axes.h0, axes.v1 - axes.v0))  # one step for both axes: squares stay square
    for t in np.arange(math.ceil(axes.h0 / step) * step, axes.h1 + 1e-9 * step, step):
        px = float(axes.to_px(t, 0.0)[0])
        draw.line([(px, y0), (px, y1)], fill=GRID, width=1)
        draw.line([(px, y1), (px, y1 + 6)], fill=FRAME, width=2)
        draw.text((px, y1 + 9), _fmt(t), font=tick_font, fill=FRAME, anchor="mt")
    for t in np.arange(math.ceil(axes.v0 / step) * step, axes.v1 + 1e-9 * step, step):
        py = float(axes.to_px(0.0, t)[1])
        draw.line([(x0, py), (x1, py)], fill=GRID, width=1)
        draw.line([(x0 - 6, py), (x0, py)], fill=FRAME, width=2)
        draw.text((x0 - 9, py), _fmt(t), font=tick_font, fill=FRAME, anchor="rm")
    draw.rectangle((x0, y0, x1, y1), outline=FRAME, width=2)
    draw.text(((x0 + x1) / 2, y1 + 34), f"{h_name} ({units})", font=name_font, fill=FRAME, anchor="mt")
    draw.text((24, (y0 + y1) / 2), f"{v_name}\n({units})", font=name_font, fill=FRAME, anchor="mm", align="center")
    draw.text((x0, 14), title, font=title_font, fill=(0, 0, 0), anchor="lt")
    for i, line in enumerate(wrap(draw, subtitle, tick_font, x1 - x0)[:2]):
        draw.text((x0, 40 + 19 * i), line, font=tick_font, fill=FRAME, anchor="lt")


def _draw_scale_bar(image: Image.Image, axes: Axes, units: str, fnt_size: int = 15) -> Box:
    """A bar of a round length in the plot's lower-left corner, on a white box; returns the box."""
    draw = ImageDraw.Draw(image)
    x0, _, _, y1 = axes.plot_box
    length = nice_length(0.25 * (axes.h1 - axes.h0))
    px = length * axes.scale
    fnt = font(fnt_size)
    text = f"{_fmt(length)} {units}"
    tw, th = text_size(draw, text, fnt)
    bx, by = x0 + 12, y1 - 12
    box = (bx - 6, by - th - 20, bx + max(px, tw) + 6, by + 6)
    draw.rectangle(box, fill=(255, 255, 255), outline=FRAME)
    draw.rectangle((bx, by - 5, bx + px, by), fill=(0, 0, 0))
    for end in (bx, bx + px):
        draw.line([(end, by - 10), (end, by)], fill=(0, 0, 0), width=2)
    draw.text((bx + px / 2, by - 12), text, font=fnt, fill=(0, 0, 0), anchor="mb")
    return box


def _draw_cameras(image: Image.Image, axes: Axes, names: list[str], cam_h: np.ndarray, cam_v: np.ndarray,
                  axis_h: np.ndarray, axis_v: np.ndarray, arrow_px: float, small: bool = False,
                  avoid: list[Box] | None = None) -> list[Box]:
    """Cameras as a ring at the position and an arrow along the optical axis projected on the page.

    The arrow is foreshortened like the axis itself (a camera looking straight down
    has no arrow on the map).  A camera outside the plot is drawn at the nearest point
    of the plot's edge (clamped per axis) as a hollow square instead of the ring, with
    its true optical axis.  Returns the boxes of the markers and names.
    """
    draw = ImageDraw.Draw(image)
    x0, y0, x1, y1 = axes.plot_box
    cx, cy = axes.to_px(cam_h, cam_v)
    ring = 4 if small else 7
    inner_box = (x0 + 3 * ring, y0 + 3 * ring, x1 - 3 * ring, y1 - 3 * ring)
    labels: list[Label] = []
    markers: list[Box] = []
    for i, name in enumerate(names):  # one per camera
        x, y = float(cx[i]), float(cy[i])
        outside = not (x0 <= x <= x1 and y0 <= y <= y1)
        if outside:
            x = min(max(x, inner_box[0]), inner_box[2])
            y = min(max(y, inner_box[1]), inner_box[3])
        # Page y grows downwards: the page direction of a world axis flips its vertical part.
        tip = (x + axis_h[i] * arrow_px, y - axis_v[i] * arrow_px)
        draw_arrow(draw, (x, y), tip, CAMERA, width=2 if small else 3, head=8 if small else 14)
        if outside:
            draw.rectangle((x - ring, y - ring, x + ring, y + ring), fill=(255, 255, 255), outline=CAMERA, width=2)
        else:
            draw.ellipse((x - ring, y - ring, x + ring, y + ring), fill=(255, 255, 255), outline=CAMERA, width=2 if small else 3)
        markers.append((x - ring, y - ring, x + ring, y + ring))
        # The arrow as a chain of small boxes, so names and ids keep off it too.
        for t in np.linspace(0.2, 1.0, 5):
            ax, ay = x + (tip[0] - x) * t, y + (tip[1] - y) * t
            markers.append((ax - 4, ay - 4, ax + 4, ay + 4))
        if not small:
            # Name just beyond the marker on the side away from the arrow, so it never covers the arrow.
            text = name + (" (beyond)" if outside else "")
            tw, th = text_size(draw, text, font(15))
            d = np.array([tip[0] - x, tip[1] - y])
            d = d / max(float(np.hypot(*d)), 1e-9)
            reach = min((tw / 2 + 8) / max(abs(d[0]), 1e-9), (th / 2 + 8) / max(abs(d[1]), 1e-9)) + ring
            labels.append(Label((x - d[0] * reach, y - d[1] * reach), text, CAMERA, font(15), fill=(255, 255, 255),
                                text_fill=CAMERA))
    names_at = draw_labels(image, labels, avoid=markers + list(avoid or []), leader=None,
                           bounds=(x0 + 2, y0 + 2, x1 - 2, y1 - 2))
    return markers + names_at


def _label_objects_at(image: Image.Image, axes: Axes, scene: MapScene, h: np.ndarray, v: np.ndarray,
                      avoid: list[Box]) -> None:
    """Object ids on the map at the objects' centres (nudged apart where they would overlap)."""
    lx, ly = axes.to_px(h, v)
    fnt = font(17)
    x0, y0, x1, y1 = axes.plot_box
    labels = []
    for i, o in enumerate(scene.object_ids.tolist()):  # one per object
        if not (np.isfinite(lx[i]) and np.isfinite(ly[i])):
            continue
        x, y = float(lx[i]), float(ly[i])
        beyond = not (x0 <= x <= x1 and y0 <= y <= y1)  # an outlier left out of the frame: at its edge
        x, y = min(max(x, x0 + 24), x1 - 24), min(max(y, y0 + 12), y1 - 12)
        labels.append(Label((x, y), f"{o} (beyond)" if beyond else str(o), object_colour(o), fnt))
    draw_labels(image, labels, avoid=avoid, leader=(90, 90, 90))


def _lanes(scene: MapScene, axes: Axes, h: np.ndarray, lane_px: int) -> np.ndarray:
    """Lane (row) of each object's side-view label: labels sorted by x take the lowest free lane."""
    lanes = np.full(scene.object_ids.size, -1, dtype=np.int64)
    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    fnt = font(17)
    x = axes.to_px(h, 0.0)[0]
    right_edges: list[float] = []
    for i in np.argsort(np.where(np.isfinite(x), x, np.inf), kind="stable"):  # one per object
        if not np.isfinite(x[i]):
            continue
        half = (text_size(draw, str(scene.object_ids[i]), fnt)[0] + 12) / 2
        lane = next((k for k, edge in enumerate(right_edges) if edge + 4 < x[i] - half), len(right_edges))
        if lane == len(right_edges):
            right_edges.append(0.0)
        right_edges[lane] = x[i] + half
        lanes[i] = lane
    return lanes


def _label_objects_in_lanes(image: Image.Image, axes: Axes, scene: MapScene, h: np.ndarray, heights: np.ndarray,
                            lanes: np.ndarray, lane_px: int, base_height: float, avoid: list[Box]) -> None:
    """Side-view ids in rows above the rocks, each with a leader line down to its rock's top."""
    draw = ImageDraw.Draw(image)
    fnt = font(17)
    tops = np.full(scene.object_ids.size, np.nan)
    if heights.size:
        uniq, inverse = np.unique(scene.point_object, return_inverse=True)
        best = np.full(uniq.size, -np.inf)
        np.maximum.at(best, inverse, heights)
        pos = np.minimum(np.searchsorted(uniq, scene.object_ids), uniq.size - 1)
        found = uniq[pos] == scene.object_ids
        tops[found] = best[pos[found]]
    x = axes.to_px(h, 0.0)[0]
    y_base = float(axes.to_px(0.0, base_height)[1]) - 8
    for i, obj in enumerate(scene.object_ids.tolist()):  # one per object
        if lanes[i] < 0 or not np.isfinite(x[i]):
            continue
        y_label = y_base - lanes[i] * lane_px - lane_px / 2
        y_top = float(axes.to_px(0.0, tops[i])[1]) if np.isfinite(tops[i]) else y_label
        draw.line([(x[i], y_label), (x[i], y_top)], fill=object_colour(obj), width=2)
    draw_labels(image, [Label((float(x[i]), y_base - lanes[i] * lane_px - lane_px / 2), str(o), object_colour(o), fnt)
                        for i, o in enumerate(scene.object_ids.tolist()) if lanes[i] >= 0 and np.isfinite(x[i])],
                avoid=avoid)


def _inset(image: Image.Image, main: Axes, axes: Axes, scene: MapScene, frame: MapFrame) -> None:
    """Overview of the whole scene, cameras at their true positions, right of the main plot."""
    r, f = frame.right, frame.forward
    pts = scene.points
    px, py = axes.to_px(pts[:, r], pts[:, f])
    radius = int(min(3, scene.point_spacing * axes.scale / 2))
    inset = Image.fromarray(rasterise(px, py, np.zeros(len(pts)), object_colours(scene.point_object), axes.size,
                                      radius=radius), mode="RGB")
    draw = ImageDraw.Draw(inset)
    _, _, ix1, iy1 = axes.plot_box
    draw.rectangle((0, 0, inset.width - 1, inset.height - 1), outline=FRAME, width=2)
    draw.text((6, 5), "overview (red: the map's frame)", font=font(14), fill=FRAME, anchor="lt")
    zx0, zy1 = axes.to_px(main.h0, main.v0)
    zx1, zy0 = axes.to_px(main.h1, main.v1)
    draw.rectangle((float(zx0), float(zy0), float(zx1), float(zy1)), outline=(200, 0, 0), width=2)
    side = max(inset.size)
    _draw_cameras(inset, axes, scene.camera_names, scene.camera_centres[:, r], scene.camera_centres[:, f],
                  scene.camera_axes[:, r], scene.camera_axes[:, f], 0.12 * side, small=True)
    length = nice_length(0.3 * (axes.h1 - axes.h0))
    bar = length * axes.scale
    draw.rectangle((ix1 - bar - 6, iy1 - 10, ix1 - 6, iy1 - 7), fill=(0, 0, 0))
    draw.text((ix1 - 6 - bar / 2, iy1 - 12), f"{_fmt(length)} {scene.units}", font=font(12), fill=(0, 0, 0), anchor="mb")
    _, y0, x1, _ = main.plot_box
    image.paste(inset, (int(x1) + 16, int(y0)))
