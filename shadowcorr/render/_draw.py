"""Small Pillow drawing helpers shared by the view images, the maps and the contact sheet."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from .palette import RGB

Font = ImageFont.FreeTypeFont | ImageFont.ImageFont
Box = tuple[float, float, float, float]

LABEL_FILL: RGB = (25, 25, 25)
LABEL_TEXT: RGB = (255, 255, 255)


@lru_cache(maxsize=32)
def font(size: int) -> Font:
    """Pillow's bundled font at ``size`` pixels.

    Pillow >= 10.1 ships a scalable FreeType font; older versions only have a fixed
    ~11 px bitmap font, which is still readable, so fall back to it rather than
    depending on fonts installed on the machine.  The bundled font is ASCII-only
    (no arrows, no dashes): callers keep their text ASCII.
    """
    try:
        return ImageFont.load_default(size=max(int(size), 6))
    except TypeError:  # Pillow < 10.1
        return ImageFont.load_default()


def text_size(draw: ImageDraw.ImageDraw, text: str, fnt: Font) -> tuple[int, int]:
    """Width and height of ``text`` as drawn (multi-line aware)."""
    left, top, right, bottom = draw.multiline_textbbox((0, 0), text, font=fnt)
    return int(right - left), int(bottom - top)


@dataclass
class Label:
    """A boxed text label to place near ``anchor`` (x, y in pixels)."""

    anchor: tuple[float, float]
    text: str
    border: RGB
    font: Font
    fill: RGB = LABEL_FILL
    text_fill: RGB = LABEL_TEXT
    clear: Box | None = None  # keep the label off this box (a region the label would hide)


def label_box_size(text: str, fnt: Font) -> tuple[int, int, int]:
    """Width, height and padding of the box ``draw_labels`` draws around ``text``."""
    w, h = text_size(ImageDraw.Draw(Image.new("RGB", (1, 1))), text, fnt)
    pad = max(2, h // 4)
    return w + 2 * pad, h + 2 * pad, pad


def _overlaps(box: Box, placed: list[Box]) -> bool:
    x0, y0, x1, y1 = box
    return any(x0 < b[2] and b[0] < x1 and y0 < b[3] and b[1] < y1 for b in placed)


def draw_labels(image: Image.Image, labels: list[Label], *, avoid: list[Box] | None = None,
                leader: RGB | None = (255, 255, 255), bounds: Box | None = None) -> list[Box]:
    """Draw boxed labels centred on their anchors, nudging them apart where they would overlap.

    Placement is greedy in list order (callers put the most important labels first):
    each label takes the first candidate position, spiralling outwards from its anchor,
    whose box overlaps no label placed before (nor an ``avoid`` box), covers no other
    label's anchor (a small region next to a big one stays visible) and stays inside
    ``bounds`` (default: the image).  A moved label gets a thin ``leader`` line back to
    its anchor so it still points at its region (``None``: no line).
    """
    draw = ImageDraw.Draw(image)
    bx0, by0, bx1, by1 = bounds or (0.0, 0.0, float(image.width), float(image.height))
    placed: list[Box] = list(avoid or [])
    start = len(placed)
    anchors = np.array([lb.anchor for lb in labels], dtype=float).reshape(-1, 2)
    for i, label in enumerate(labels):
        bw, bh, pad = label_box_size(label.text, label.font)
        ax, ay = label.anchor
        best = None
        # Candidate offsets in rings of growing radius (in box heights), 8 directions each.
        others = np.delete(anchors, i, axis=0)
        keep_off = [label.clear] if label.clear is not None else []
        for ring in range(0, 10):
            steps = [(0.0, 0.0)] if ring == 0 else [
                (dx * ring * (bw + 2) * 0.6, dy * ring * (bh + 2)) for dy in (-1, 1, 0) for dx in (0, -1, 1)
                if (dx, dy) != (0, 0)
            ]
            for dx, dy in steps:
                cx = min(max(ax + dx, bx0 + bw / 2), bx1 - bw / 2)
                cy = min(max(ay + dy, by0 + bh / 2), by1 - bh / 2)
                box = (cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2)
                covers = np.any((others[:, 0] > box[0]) & (others[:, 0] < box[2]) &
                                (others[:, 1] > box[1]) & (others[:, 1] < box[3]))
                if not covers and not _overlaps(box, placed) and not _overlaps(box, keep_off):
                    best = box
                    break
            if best is not None:
                break
        if best is None:  # crowded: accept the overlap rather than drop the label
            cx = min(max(ax, bx0 + bw / 2), bx1 - bw / 2)
            cy = min(max(ay, by0 + bh / 2), by1 - bh / 2)
            best = (cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2)
        placed.append(best)
        x0, y0, x1, y1 = best
        if leader is not None and not (x0 <= ax <= x1 and y0 <= ay <= y1):
            near = (min(max(ax, x0), x1), min(max(ay, y0), y1))
            draw.line([near, (ax, ay)], fill=(0, 0, 0), width=3)
            draw.line([near, (ax, ay)], fill=leader, width=1)
        border = max(1, bh // 10)
        draw.rounded_rectangle(best, radius=max(2, bh // 5), fill=label.fill, outline=label.border, width=border)
        draw.multiline_text(((x0 + x1) / 2, (y0 + y1) / 2), label.text, font=label.font, fill=label.text_fill,
                            anchor="mm", align="center")
    return placed[start:]


def draw_arrow(draw: ImageDraw.ImageDraw, start: tuple[float, float], end: tuple[float, float], colour: RGB,
               width: int = 3, head: float = 14.0) -> None:
    """A straight arrow from ``start`` to ``end`` with a filled triangular head."""
    p0, p1 = np.asarray(start, float), np.asarray(end, float)
    d = p1 - p0
    length = float(np.hypot(*d))
    if length < 1e-6:
        return
    u = d / length
    n = np.array([-u[1], u[0]])
    head = min(head, 0.6 * length)
    base = p1 - u * head
    draw.line([tuple(p0), tuple(base)], fill=colour, width=width)
    draw.polygon([tuple(p1), tuple(base + n * head * 0.45), tuple(base - n * head * 0.45)], fill=colour)


CORNERS = ("top-left", "top-right", "bottom-left", "bottom-right")


def _banner_layout(lines: list[tuple[str, RGB | None]], fnt: Font, size: tuple[int, int],
                   corner: str = "top-left") -> tuple[Box, int, int]:
    """Box, line height and padding of a ``banner`` in a corner of an image of ``size``."""
    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    sizes = [text_size(draw, t, fnt) for t, _ in lines]
    line_h = max((h for _, h in sizes), default=0) + max(3, getattr(fnt, "size", 12) // 4)
    pad = max(4, line_h // 3)
    swatch = line_h - 4
    w = max((tw + (swatch + pad if c is not None else 0) for (tw, _), (_, c) in zip(sizes, lines)), default=0) + 2 * pad
    h = line_h * len(lines) + 2 * pad
    x0 = pad if corner.endswith("left") else max(size[0] - pad - w, 0)
    y0 = pad if corner.startswith("top") else max(size[1] - pad - h, 0)
    return (x0, y0, min(x0 + w, size[0] - 1), min(y0 + h, size[1] - 1)), line_h, pad


def banner_box(image: Image.Image, lines: list[tuple[str, RGB | None]], fnt: Font, corner: str = "top-left") -> Box:
    """Where ``banner`` will draw (so labels can keep clear of it before it is drawn)."""
    return _banner_layout(lines, fnt, image.size, corner)[0]


def banner(image: Image.Image, lines: list[tuple[str, RGB | None]], fnt: Font, corner: str = "top-left") -> Box:
    """A dark, semi-opaque text panel in a ``corner``; ``(text, swatch colour or None)`` per line.

    Returns the panel's box.
    """
    box, line_h, pad = _banner_layout(lines, fnt, image.size, corner)
    x0, y0, x1, y1 = box
    overlay = Image.new("RGBA", image.size, (0, 0, 0, 0))
    ImageDraw.Draw(overlay).rounded_rectangle(box, radius=pad, fill=(0, 0, 0, 170))
    image.paste(Image.alpha_composite(image.convert("RGBA"), overlay).convert("RGB"))
    draw = ImageDraw.Draw(image)
    swatch = line_h - 4
    y = y0 + pad
    for text, colour in lines:
        x = x0 + pad
        if colour is not None:
            draw.rectangle((x, y + 2, x + swatch, y + 2 + swatch), fill=colour, outline=(255, 255, 255))
            x += swatch + pad
        draw.text((x, y + line_h / 2), text, font=fnt, fill=(255, 255, 255), anchor="lm")
        y += line_h
    return box


def hazard_stripes(shape: tuple[int, int], period: int, colours: tuple[RGB, RGB]) -> np.ndarray:
    """(H, W, 3) uint8 diagonal stripes alternating between two colours every ``period`` pixels."""
    v, u = np.indices(shape, sparse=True)
    phase = ((u + v) // max(period, 1)) % 2
    return np.where(phase[..., None] == 0, np.asarray(colours[0], np.uint8), np.asarray(colours[1], np.uint8))


def wrap(draw: ImageDraw.ImageDraw, text: str, fnt: Font, width: float) -> list[str]:
    """Greedy word wrap of ``text`` into lines no wider than ``width`` pixels (long words stay whole)."""
    lines: list[str] = []
    for word in text.split(" "):
        if lines and text_size(draw, lines[-1] + " " + word, fnt)[0] <= width:
            lines[-1] += " " + word
        else:
            lines.append(word)
    return lines
