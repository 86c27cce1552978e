"""``shadowcorr synth``: generate a synthetic dataset of scene bundles from the command line.

The main CLI calls ``add_synth_parser(subparsers)``; the parsed arguments go to
``run_synth(args)``.  Every ``SynthConfig`` knob that a user plausibly changes has a
flag; ``--config FILE`` loads a JSON config (flags given explicitly override it).
``--field`` draws every scene from a ``FieldDistribution`` instead (the defaults, or the
JSON of ``--field-config FILE``); the fixed-config flags do not apply then.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .config import SynthConfig
    from .field import FieldDistribution

# flag -> SynthConfig field, for the plain scalar knobs (dest defaults to None = not given).
_SCALARS: list[tuple[str, str, type, str]] = [
    ("--cameras", "cameras", int, "cameras on the ring (default 4)"),
    ("--radius", "radius", float, "ring radius around the scene centre (default 750)"),
    ("--camera-height", "camera_height", float, "camera height (default 329)"),
    ("--arc-deg", "arc_deg", float, "ring coverage in degrees: 360, 180, 90, ... (default 360)"),
    ("--start-deg", "start_deg", float, "azimuth of the first camera (default random per scene)"),
    ("--width", "width", int, "image width in pixels (default 1920)"),
    ("--height", "height", int, "image height in pixels (default 1080)"),
    ("--focal-px", "focal_px", float, "fx = fy in pixels (default 1615)"),
    ("--field-radius", "field_radius", float, "radius of the rock field (default 320)"),
    ("--sink-depth", "sink_depth", float, "how deep rocks sit in the ground (default 5)"),
    ("--subdivisions", "rock_subdivisions", int, "rock mesh detail, icosphere level (default 4)"),
    ("--renderer", "renderer", str, "auto | gl | raster (default auto)"),
    ("--background-depth", "background_depth", str, "terrain | invalid (default terrain)"),
    ("--max-depth", "max_depth", float, "depth beyond this is invalid (default none)"),
    ("--depth-format", "depth_format", str, "exr | npy | png (default exr)"),
    ("--mask-format", "mask_format", str, "png | npy (default png)"),
    ("--depth-noise", "depth_noise", float, "Gaussian depth noise sigma in units (default 0)"),
    ("--depth-quantum", "depth_quantum", float, "round depth to multiples of this (default 0 = off)"),
    ("--pose-noise-t", "pose_noise_translation", float, "camera position error sigma in units (default 0)"),
    ("--pose-noise-deg", "pose_noise_rotation_deg", float, "camera rotation error sigma in degrees (default 0)"),
    ("--mask-dilate", "mask_dilate_px", int, "grow (>0) or erode (<0) masks by this many pixels (default 0)"),
    ("--mask-boundary-noise", "mask_boundary_noise", float, "chance a boundary pixel flips id (default 0)"),
    ("--drop-view-prob", "drop_view_prob", float, "chance each view is left out (default 0)"),
]


def _pair(kind: type) -> Any:
    def parse(text: str) -> tuple:
        parts = text.replace(",", " ").split()
        if len(parts) != 2:
            raise argparse.ArgumentTypeError(f"expected two values 'LO,HI', got {text!r}")
        return tuple(kind(p) for p in parts)

    return parse


def add_synth_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``synth`` on the main CLI's subparsers."""
    p = subparsers.add_parser(
        "synth",
        help="generate synthetic rock-field scene bundles with ground truth",
        description="Procedural lunar rock fields settled by physics (MuJoCo) and rendered from a camera ring. "
        "Writes OUT/scene_00000 ... (bundles with ground truth) and OUT/dataset.json; --field draws each "
        "scene from the field-robot distribution.",
    )
    p.add_argument("--scenes", type=int, required=True, help="number of scenes")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=0, help="dataset seed; scene i uses a seed derived from (seed, i)")
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes (default 1)")
    p.add_argument("--config", help="JSON file with SynthConfig fields (flags override it)")
    p.add_argument("--rocks", type=_pair(int), help="rocks per scene as LO,HI (default 18,20)")
    p.add_argument("--diameter", type=_pair(float), help="rock diameter range LO,HI (default 36,157)")
    p.add_argument("--pitch-deg", type=_pair(float), help="camera pitch range LO,HI (default 21,27)")
    p.add_argument("--azimuths-deg", type=lambda t: tuple(float(a) for a in t.replace(",", " ").split()),
                   help="explicit camera azimuths relative to --start-deg, e.g. 0,40,110,170,250,300 "
                   "(one per camera: uneven rigs)")
    for flag, _, kind, text in _SCALARS:
        p.add_argument(flag, type=kind, default=None, help=text)
    p.add_argument("--field", action="store_true",
                   help="draw every scene's rig, rocks and perturbations from the field-robot distribution "
                   "(shadowcorr.synth.field.FieldDistribution); dataset.json records each scene's draw")
    p.add_argument("--field-config", metavar="FILE",
                   help="JSON file with FieldDistribution fields (implies --field)")
    p.add_argument("--resume", action="store_true", help="skip scenes that already have a manifest")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_synth)
    return p


def config_from_args(args: argparse.Namespace) -> "SynthConfig":
    """SynthConfig from ``--config`` plus the flags that were given (validated)."""
    from .config import SynthConfig  # pydantic: loaded when the command runs, not when it is registered

    fields: dict[str, Any] = {}
    if getattr(args, "config", None):
        fields.update(json.loads(Path(args.config).read_text()))
    for flag, name, _, _ in _SCALARS:
        value = getattr(args, flag.lstrip("-").replace("-", "_"))
        if value is not None:
            fields[name] = value
    for attr, name in (("rocks", "n_rocks"), ("diameter", "rock_diameter"), ("pitch_deg", "pitch_deg"),
                       ("azimuths_deg", "azimuths_deg")):
        if getattr(args, attr, None) is not None:
            fields[name] = getattr(args, attr)
    return SynthConfig.model_validate(fields)


def _fixed_flags_given(args: argparse.Namespace) -> list[str]:
    """The fixed-config options given on the command line (they conflict with ``--field``)."""
    given = [flag for flag, _, _, _ in _SCALARS if getattr(args, flag.lstrip("-").replace("-", "_")) is not None]
    given += [f"--{a.replace('_', '-')}" for a in ("config", "rocks", "diameter", "pitch_deg", "azimuths_deg")
              if getattr(args, a, None) is not None]
    return given


def field_from_args(args: argparse.Namespace) -> "FieldDistribution | None":
    """The ``FieldDistribution`` of ``--field`` / ``--field-config`` (validated), or None."""
    from .field import FieldDistribution

    if not (getattr(args, "field", False) or getattr(args, "field_config", None)):
        return None
    conflicting = _fixed_flags_given(args)
    if conflicting:
        raise ValueError(f"--field draws each scene's config; drop {', '.join(conflicting)} "
                         "(put ranges in a --field-config file instead)")
    fields = json.loads(Path(args.field_config).read_text()) if args.field_config else {}
    return FieldDistribution.model_validate(fields)


def run_synth(args: argparse.Namespace) -> int:
    """Generate the dataset; prints one summary line.  Raises ValueError on bad options."""
    from pydantic import ValidationError

    from .generate import generate_dataset

    try:
        field = field_from_args(args)
        config = None if field is not None else config_from_args(args)
    except ValidationError as e:
        raise ValueError(f"invalid synth options: {e}") from None
    if args.scenes < 0 or args.workers < 1:
        raise ValueError("--scenes must be >= 0 and --workers >= 1")
    paths = generate_dataset(
        config, args.scenes, args.out, seed=args.seed, workers=args.workers,
        progress=not args.quiet, resume=args.resume, field=field,
    )
    recorded = "each scene's draw" if field is not None else "the config"
    print(f"wrote {len(paths)} scene(s) to {args.out} (dataset.json records {recorded} and the seed)")
    return 0
