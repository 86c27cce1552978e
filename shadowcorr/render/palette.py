"""Fixed colours of the renderings: one categorical palette for objects, plus status colours.

Object ``k`` is always drawn in ``PALETTE[k % len(PALETTE)]``, so the same object id
has the same colour in every image of a result and across runs; nothing is random.

The palette is Sasha Trubetskoy's "20 simple, distinct colours" without its grey,
white and black (grey vanishes on the grey depth shading; white and black read as
"nothing" or "shadow"), extended with five well-separated colours from Glasbey-style
lists.  The most distinct, saturated colours come first, because small scenes only
use the first few entries.
"""

from __future__ import annotations

import numpy as np

RGB = tuple[int, int, int]

PALETTE: tuple[RGB, ...] = (
    (230, 25, 75),  # red
    (60, 180, 75),  # green
    (255, 225, 25),  # yellow
    (67, 99, 216),  # blue
    (245, 130, 49),  # orange
    (145, 30, 180),  # purple
    (66, 212, 244),  # cyan
    (240, 50, 230),  # magenta
    (191, 239, 69),  # lime
    (250, 190, 212),  # pink
    (70, 153, 144),  # teal
    (220, 190, 255),  # lavender
    (154, 99, 36),  # brown
    (255, 250, 200),  # beige
    (128, 0, 0),  # maroon
    (170, 255, 195),  # mint
    (128, 128, 0),  # olive
    (255, 216, 177),  # apricot
    (0, 0, 117),  # navy
    (140, 59, 255),  # violet
    (0, 253, 207),  # aquamarine
    (161, 117, 106),  # rosy brown
    (107, 0, 79),  # plum
    (0, 86, 89),  # dark teal
)

#: Colours of the ground-truth check images (green correct / red wrong, as the paper's Fig. 9).
CORRECT: RGB = (40, 200, 60)
WRONG: RGB = (235, 30, 30)
SPLIT: RGB = (255, 165, 0)  # correct object, but its rock is split over several objects
UNKNOWN: RGB = (150, 150, 150)  # no ground truth for this segment

#: Low-support outline: black/yellow hazard stripes, unlike any flat palette colour.
WARNING_STRIPES: tuple[RGB, RGB] = ((255, 215, 0), (0, 0, 0))

#: Cameras on the maps.
CAMERA: RGB = (20, 20, 20)


def object_colour(obj: int) -> RGB:
    """The fixed colour of object ``obj`` (negative ids, i.e. unlabelled, are grey)."""
    if obj < 0:
        return UNKNOWN
    return PALETTE[obj % len(PALETTE)]


def object_colours(objects: np.ndarray) -> np.ndarray:
    """Vectorised ``object_colour``: (N,) object ids -> (N, 3) uint8 colours."""
    table = np.asarray(PALETTE, dtype=np.uint8)
    objects = np.asarray(objects, dtype=np.int64)
    out = table[np.mod(objects, len(PALETTE))]
    out[objects < 0] = UNKNOWN
    return out

