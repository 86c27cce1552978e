"""Pictures of a correspondence result: annotated views, top-down and side maps, a contact sheet.

``render_result(bundle, result, out_dir)`` writes them; ``shadowcorr render`` is its CLI.
"""

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

_EXPORTS = {
    "STATUS_CORRECT": "core",
    "STATUS_SPLIT": "core",
    "STATUS_UNKNOWN": "core",
    "STATUS_WRONG": "core",
    "RenderConfig": "core",
    "render_result": "core",
    "segment_status": "core",
    "PALETTE": "palette",
    "object_colour": "palette",
    "object_colours": "palette",
}

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
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
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
