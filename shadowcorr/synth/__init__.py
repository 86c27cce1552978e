"""Synthetic lunar rock fields as scene bundles with ground truth (``shadowcorr synth``).

Procedural irregular rocks are settled onto uneven ground by a physics engine
(MuJoCo), photographed by a calibrated camera ring, and written as bundles whose mask
ids are rock ids in every view (``ground_truth: "instance"``).

Importing this package does not import MuJoCo; generating does (``pip install
'shadowcorr[synth]'``).  Rendering uses MuJoCo's headless OpenGL when available and a
pure-numpy rasteriser otherwise (identical images; see ``render``).
"""

from .config import SynthConfig
from .generate import SynthScene, generate_dataset, generate_scene, scene_seed, synthesize, write_scene

__all__ = [
    "SynthConfig",
    "SynthScene",
    "generate_dataset",
    "generate_scene",
    "scene_seed",
    "synthesize",
    "write_scene",
]
