"""The ``shadowcorr`` command line: convert, correspond, eval, synth, train, render, serve."""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
from pathlib import Path
from typing import Iterator, Sequence

from ._version import __version__


def _cameras(text: str) -> list[int]:
    try:
        return [int(c) for c in text.split(",") if c.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"cameras must be comma-separated integers, got {text!r}") from None


def _add_method_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", help="model file (.safetensors or reference .pth); default: the packaged model")
    p.add_argument("--method", choices=["fused", "projection", "shadowcorr", "meanshift"], default="fused",
                   help="fused (default): cross-view surface evidence and the network's volumetric evidence; "
                   "projection: the training-free cross-view check; shadowcorr: the paper's volumetric consensus; "
                   "meanshift: the paper's no-network baseline")
    p.add_argument("--bandwidth", type=float, help="MeanShift bandwidth of shadowcorr and meanshift (default 0.7; baseline 0.2)")
    p.add_argument("--no-split-components", action="store_true", help="keep disconnected blobs of one mask value together")
    p.add_argument("--min-blob-pixels", type=int, help="ignore blobs with fewer pixels (default 50)")
    p.add_argument("--refine-poses", action=argparse.BooleanOptionalAction, default=None,
                   help="register the views' depth to each other and correct their poses first (default: the configuration's)")


def _config(args: argparse.Namespace):
    from .config import ShadowCorrConfig

    options: dict[str, object] = {"method": args.method}
    if args.bandwidth is not None:
        options["baseline_bandwidth" if args.method == "meanshift" else "bandwidth"] = args.bandwidth
    if args.no_split_components:
        options["split_components"] = False
    if args.min_blob_pixels is not None:
        options["min_blob_pixels"] = args.min_blob_pixels
    if args.refine_poses is not None:
        options["refine_poses"] = args.refine_poses
    return ShadowCorrConfig(**options)


def _model(args: argparse.Namespace):
    if args.method in ("meanshift", "projection"):  # the methods without a network
        return None
    from .nn import load_model

    return load_model(args.model)


# --------------------------------------------------------------------------- scenes
_UE_DEPTH = re.compile(r"^Set(\d+)_Depth_(\d+)\.exr$")


def ue_sets(directory: Path) -> dict[str, list[int]]:
    """Sets (id -> cameras present) of an Unreal-layout dataset directory."""
    sets: dict[str, list[int]] = {}
    for f in directory.iterdir():
        m = _UE_DEPTH.match(f.name)
        if m and (directory / f"Set{m.group(1)}_Segment_{m.group(2)}.png").exists():
            sets.setdefault(m.group(1), []).append(int(m.group(2)))
    return {k: sorted(v) for k, v in sorted(sets.items())}


def iter_scenes(source: Path, cameras: Sequence[int] | None = None) -> Iterator[tuple[str, object]]:
    """Yield (name, loader) for every scene under ``source``.

    ``source`` may be a bundle directory or archive, a directory of those, or an
    Unreal-layout dataset directory (each set becomes a scene with ``cameras``).
    The loader is called lazily so a long evaluation never holds every scene at once.
    """
    from .convert import load_ue_scene
    from .io import load_bundle

    if source.is_file() or (source / "manifest.json").exists():
        yield source.name, lambda: load_bundle(source)
        return
    if not source.is_dir():
        raise FileNotFoundError(f"{source}: no such bundle or directory")
    sets = ue_sets(source)
    if sets:
        for set_id, present in sets.items():
            cams = list(cameras) if cameras else present
            yield f"Set{set_id}", (lambda s=set_id, c=cams: load_ue_scene(source, s, c))
        return
    found = False
    for child in sorted(source.iterdir()):
        if (child / "manifest.json").exists() or child.suffix in {".zip", ".tar"} or child.name.endswith(".tar.gz"):
            found = True
            yield child.name, (lambda c=child: load_bundle(c))
    if not found:
        raise FileNotFoundError(f"{source}: holds no bundle, bundle archive or Unreal-layout set")


# --------------------------------------------------------------------------- commands
def cmd_convert(args: argparse.Namespace) -> int:
    if args.kind == "ue":
        from .convert import convert_ue

        out = convert_ue(args.source, args.set, args.cameras, args.out, focal_px=args.focal_px)
    else:
        from .convert import convert_reference_npz

        out = convert_reference_npz(args.source, args.out)
    print(f"wrote bundle {out}")
    return 0


def cmd_correspond(args: argparse.Namespace) -> int:
    from .pipeline import correspond

    (name, load), *rest = list(iter_scenes(Path(args.bundle), args.cameras))
    if rest:
        raise SystemExit(f"{args.bundle} holds {len(rest) + 1} scenes; `correspond` takes one (use `eval` for many)")
    result = correspond(load(), _model(args), _config(args), metrics=not args.no_metrics)
    text = json.dumps(result.model_dump(mode="json"), indent=1)
    if args.out:
        Path(args.out).write_text(text)
        n_obj = len(result.objects)
        print(f"{len(result.segments)} segments -> {n_obj} objects in {result.timings_ms['total']:.0f} ms; wrote {args.out}")
        if result.metrics:
            m = result.metrics
            print(f"average purity {m['average_purity']:.2f}  rock {m['rock_purity']:.2f}  cluster {m['cluster_purity']:.2f}  "
                  f"voxel ARI {m.get('voxel_ari', float('nan')):.4f}  coverage {m['coverage']:.1f}%")
        for w in result.warnings:
            print(f"warning: {w}", file=sys.stderr)
    else:
        print(text)
    return 0


EVAL_COLUMNS = ("average_purity", "rock_purity", "cluster_purity", "voxel_ari", "perfect_one_to_one_share", "coverage")


def cmd_eval(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .metrics import summarize
    from .pipeline import correspond

    model, config = _model(args), _config(args)
    scenes = list(iter_scenes(Path(args.source), args.cameras))
    rows, failures = [], []
    for name, load in tqdm(scenes, desc="eval", unit="scene", disable=len(scenes) < 2 or args.quiet):
        try:
            result = correspond(load(), model, config, metrics=True)
        except Exception as exc:  # one bad scene must not hide the others' figures
            failures.append((name, f"{type(exc).__name__}: {exc}"))
            continue
        if result.metrics is None:
            failures.append((name, "no ground truth in this scene"))
            continue
        rows.append({"scene": name, **result.metrics, "total_ms": result.timings_ms["total"]})

    head = f"{'scene':<24}" + "".join(f"{c.replace('_', ' ')[:16]:>18}" for c in EVAL_COLUMNS)
    print(head)
    for r in rows:
        print(f"{r['scene'][:24]:<24}" + "".join(f"{r.get(c, float('nan')):>18.4f}" for c in EVAL_COLUMNS))
    if rows:
        summary = summarize(rows)
        print(f"{'mean ± std (n=' + str(len(rows)) + ')':<24}" + "".join(
            f"{summary[c]['mean']:>10.4f} ± {summary[c]['std']:<5.3f}" if c in summary else f"{'-':>18}" for c in EVAL_COLUMNS))
    for name, err in failures:
        print(f"failed {name}: {err}", file=sys.stderr)
    if args.json:
        Path(args.json).write_text(json.dumps({"scenes": rows, "failures": failures,
                                               "summary": summarize(rows) if rows else {}}, indent=1))
    return 1 if failures or not rows else 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="shadowcorr", description=__doc__)
    parser.add_argument("--version", action="version", version=f"shadowcorr {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("convert", help="convert a dataset into a scene bundle")
    conv = p.add_subparsers(dest="kind", required=True)
    ue = conv.add_parser("ue", help="the authors' Unreal lunar rock dataset layout")
    ue.add_argument("source", help="dataset directory holding SetNNNN_Depth_C.exr and SetNNNN_Segment_C.png")
    ue.add_argument("--set", required=True, help="set id, e.g. 2001")
    ue.add_argument("--cameras", type=_cameras, default=[0, 2, 4, 6])
    ue.add_argument("--focal-px", type=float, default=1615.0, help="focal length (the documented 960 is wrong)")
    ue.add_argument("--out", required=True)
    ref = conv.add_parser("reference-npz", help="the reference code's stacked-segment .npz (pickled: trusted local files only)")
    ref.add_argument("source")
    ref.add_argument("--out", required=True)
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser("correspond", help="label every segment of one scene")
    p.add_argument("bundle", help="bundle directory or .zip/.tar (or an Unreal-layout directory with one set)")
    p.add_argument("--cameras", type=_cameras, help="cameras to use from an Unreal-layout directory")
    p.add_argument("--out", help="write the result JSON here (default: print it)")
    p.add_argument("--no-metrics", action="store_true", help="skip ground-truth metrics")
    _add_method_options(p)
    p.set_defaults(func=cmd_correspond)

    p = sub.add_parser("eval", help="metrics over one scene or a directory of scenes (mean ± std)")
    p.add_argument("source", help="bundle, directory of bundles, or Unreal-layout dataset directory")
    p.add_argument("--cameras", type=_cameras, help="cameras to use from an Unreal-layout directory")
    p.add_argument("--json", help="also write per-scene rows and the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_method_options(p)
    p.set_defaults(func=cmd_eval)

    for command in _plugin_commands():
        command.load()(sub)
    return parser


def _plugin_commands():
    """Subcommands registered in the ``shadowcorr.commands`` entry-point group (see pyproject.toml).

    The service registers ``serve`` this way, so the library's CLI does not depend on it.
    """
    from importlib.metadata import entry_points

    return sorted(entry_points(group="shadowcorr.commands"), key=lambda ep: ep.name)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s")
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
