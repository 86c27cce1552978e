"""``shadowcorr render BUNDLE RESULT.json --out DIR``: pictures of a result (see ``render_result``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..config import UP_AXES


def cmd_render(args: argparse.Namespace) -> int:
    """Load the bundle and the result, render, and list the files written."""
    from ..cli import iter_scenes
    from ..config import ShadowCorrConfig
    from ..result import Result
    from .core import RenderConfig, render_result

    (_, load), *rest = list(iter_scenes(Path(args.bundle), args.cameras))
    if rest:
        raise SystemExit(f"{args.bundle} holds {len(rest) + 1} scenes; `render` takes one")
    result_path = Path(args.result)
    if not result_path.is_file():
        raise FileNotFoundError(f"{result_path}: no such result file")
    result = Result.model_validate(json.loads(result_path.read_text()))
    # The segmentation settings come from the result; flags override them (results of older versions).
    engine: dict[str, object] = dict(result.config or {})
    if args.no_split_components:
        engine["split_components"] = False
    if args.min_blob_pixels is not None:
        engine["min_blob_pixels"] = args.min_blob_pixels
    config = RenderConfig(low_support=args.low_support, alpha=args.alpha, map_size=args.map_size,
                          up_axis=args.up_axis, engine=ShadowCorrConfig(**engine))
    files = render_result(load(), result, args.out, config=config)
    for f in files:
        print(f)
    return 0


def add_render_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``render`` on the ``shadowcorr`` command line."""
    from ..cli import parse_cameras  # the same parsing and message as `correspond --cameras`

    p = subparsers.add_parser("render", help="draw a result: annotated views, top-down/side maps, contact sheet")
    p.add_argument("bundle", help="the bundle the result was computed from (directory, .zip/.tar or Unreal layout)")
    p.add_argument("result", help="result JSON written by `shadowcorr correspond --out`")
    p.add_argument("--out", required=True, help="output directory for the PNGs")
    p.add_argument("--cameras", type=parse_cameras, help="cameras, for an Unreal-layout directory")
    p.add_argument("--low-support", type=float, default=0.6, help="outline segments with support below this (0-1)")
    p.add_argument("--alpha", type=float, default=0.5, help="opacity of the segment fills (0-1)")
    p.add_argument("--map-size", type=int, default=1000, help="map pixels across the scene's larger horizontal extent")
    p.add_argument("--up-axis", choices=UP_AXES, default="auto",
                   help="world axis pointing up for the maps (auto: nearest to the cameras' up)")
    p.add_argument("--no-split-components", action="store_true", help="as given to `correspond`")
    p.add_argument("--min-blob-pixels", type=int, help="as given to `correspond` (default 50)")
    p.set_defaults(func=cmd_render)
    return p
