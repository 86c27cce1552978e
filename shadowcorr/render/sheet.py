"""The contact sheet: every view image and both maps on one downscaled page, with a summary."""

from __future__ import annotations

from PIL import Image, ImageDraw

from ._draw import font, text_size
from .palette import RGB

GUTTER = 12
PAGE: RGB = (245, 245, 245)
INK: RGB = (20, 20, 20)


def _fit(image: Image.Image, width: int) -> Image.Image:
    """``image`` scaled to ``width`` pixels wide (never enlarged), aspect ratio kept."""
    if image.width <= width:
        return image
    height = max(1, round(image.height * width / image.width))
    return image.resize((width, height), Image.Resampling.LANCZOS)


def contact_sheet(sections: list[tuple[str, list[tuple[str, Image.Image]]]], maps: tuple[Image.Image, Image.Image] | None,
                  summary: list[str], *, tile_width: int = 480, columns: int = 4) -> Image.Image:
    """Tile ``sections`` (a heading and captioned images each, wrapped ``columns`` per row),
    then the top-down map beside the ``summary`` text and the side view."""
    n_max = max((len(items) for _, items in sections), default=1)
    cols = max(1, min(columns, max(n_max, 2)))
    width = cols * tile_width + (cols + 1) * GUTTER
    heading_font, caption_font, text_font = font(26), font(18), font(19)
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    caption_h = text_size(probe, "Ag", caption_font)[1] + 8
    heading_h = text_size(probe, "Ag", heading_font)[1] + 14

    blocks: list[tuple[int, int, Image.Image | str, object]] = []  # (x, y, image or text, font)
    y = GUTTER
    for heading, items in sections:
        if not items:
            continue
        blocks.append((GUTTER, y, heading, heading_font))
        y += heading_h
        for start in range(0, len(items), cols):  # one iteration per row of tiles
            row = [(c, _fit(im, tile_width)) for c, im in items[start:start + cols]]
            row_h = max(im.height for _, im in row)
            for i, (caption, im) in enumerate(row):
                x = GUTTER + i * (tile_width + GUTTER)
                blocks.append((x, y, caption, caption_font))
                blocks.append((x, y + caption_h, im, None))
            y += caption_h + row_h + GUTTER

    if maps is not None or summary:
        # Two columns: the top-down map on the left; the summary and, under it, the side
        # view on the right.  Both maps shrink by the same factor, so they keep one scale.
        column = (width - 3 * GUTTER) // 2 if maps is not None else width - 2 * GUTTER
        right_x = 2 * GUTTER + column if maps is not None else GUTTER
        y_right = y
        line_h = text_size(probe, "Ag", text_font)[1] + 9
        for line in summary:
            blocks.append((right_x, y_right, line, text_font))
            y_right += line_h
        y_left = y
        if maps is not None:
            top, side = maps
            factor = min(1.0, column / max(top.width, side.width))
            scaled = [im.resize((max(1, round(im.width * factor)), max(1, round(im.height * factor))),
                                Image.Resampling.LANCZOS) if factor < 1 else im for im in (top, side)]
            blocks.append((GUTTER, y_left, scaled[0], None))
            y_left += scaled[0].height + GUTTER
            y_right += GUTTER
            blocks.append((right_x, y_right, scaled[1], None))
            y_right += scaled[1].height + GUTTER
        y = max(y_left, y_right)

    sheet = Image.new("RGB", (width, y + GUTTER), PAGE)
    draw = ImageDraw.Draw(sheet)
    for x, by, item, fnt in blocks:
        if isinstance(item, str):
            draw.text((x, by), item, font=fnt, fill=INK)
        else:
            sheet.paste(item, (x, by))
    return sheet
