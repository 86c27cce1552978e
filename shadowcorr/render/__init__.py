"""Pictures of a correspondence result: annotated views, top-down and side maps, a contact sheet.

``render_result(bundle, result, out_dir)`` writes them; ``shadowcorr render`` is its CLI.
"""

from .core import (
    STATUS_CORRECT,
    STATUS_SPLIT,
    STATUS_UNKNOWN,
    STATUS_WRONG,
    RenderConfig,
    render_result,
    segment_status,
)
from .palette import PALETTE, object_colour, object_colours

__all__ = [
    "PALETTE",
    "STATUS_CORRECT",
    "STATUS_SPLIT",
    "STATUS_UNKNOWN",
    "STATUS_WRONG",
    "RenderConfig",
    "object_colour",
    "object_colours",
    "render_result",
    "segment_status",
]
