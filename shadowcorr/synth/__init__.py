"""Synthetic lunar rock fields as scene bundles with ground truth (``shadowcorr synth``).

Procedural irregular rocks are settled onto uneven ground by a physics engine
(MuJoCo), photographed by a calibrated camera ring, and written as bundles whose mask
ids are rock ids in every view (``ground_truth: "instance"``).

Importing this package does not import MuJoCo; generating does (``pip install
'shadowcorr[synth]'``).  Rendering uses MuJoCo's headless OpenGL when available and a
pure-numpy rasteriser otherwise (identical images; see ``render``).

``FieldDistribution`` / ``generate_field_scene`` (module ``field``) draw each scene's rig,
rocks and sensor/segmenter errors from ranges instead of one fixed config.
"""

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

_EXPORTS = {
    "FieldDistribution": "field",
    "SynthConfig": "config",
    "SynthScene": "generate",
    "generate_dataset": "generate",
    "generate_field_scene": "field",
    "generate_scene": "generate",
    "scene_seed": "generate",
    "synthesize": "generate",
    "write_scene": "generate",
}

__all__ = [
    "FieldDistribution",
    "SynthConfig",
    "SynthScene",
    "generate_dataset",
    "generate_field_scene",
    "generate_scene",
    "scene_seed",
    "synthesize",
    "write_scene",
]
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from .config import SynthConfig
    from .field import FieldDistribution, generate_field_scene
    from .generate import SynthScene, generate_dataset, generate_scene, scene_seed, synthesize, write_scene
