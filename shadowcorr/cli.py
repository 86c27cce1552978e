"""The ``shadowcorr`` command line: convert, correspond, export, eval, map, synth, train, render, serve.

Start-up is kept light: this module imports only the standard library, each command
imports what it needs when it runs, and the plugin subcommands (see pyproject's
``shadowcorr.commands`` entry points) register without loading torch, so ``--version``
and ``--help`` answer at once (``benchmarks/bench_cli.py``).
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Sequence

from ._version import __version__

if TYPE_CHECKING:  # for the annotation only: the CLI starts without pydantic
    from .config import ShadowCorrConfig

DESCRIPTION = """\
ShadowCorr: which 3D segments, seen from several calibrated camera views, are the same object.
Run `shadowcorr COMMAND --help` for the options of a command.

Global options (-v, --log-level) may come before or after the command.
"""

LOG_LEVELS = ("debug", "info", "warning", "error")


class CommandParser(argparse.ArgumentParser):
    """An argument parser whose arguments may be added on first use.

    ``populate`` (a callable taking the parser) runs the first time the parser parses
    or prints help.  Subcommands whose options come from a heavy module (``serve``
    builds its flags from the pydantic-settings model) use it, so that registering
    them -- and ``shadowcorr --help`` -- stays cheap.
    """

    def __init__(self, *args: Any, populate: Callable[[argparse.ArgumentParser], None] | None = None,
                 **kwargs: Any) -> None:
        if populate is not None:
            kwargs.setdefault("conflict_handler", "resolve")  # the command's own flags win over the global ones
        super().__init__(*args, **kwargs)
        self._populate = populate

    def _ensure_populated(self) -> None:
        if self._populate is not None:
            populate, self._populate = self._populate, None
            populate(self)

    def parse_known_args(self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None):
        self._ensure_populated()
        return super().parse_known_args(args, namespace)

    def format_help(self) -> str:
        self._ensure_populated()
        return super().format_help()


def add_global_options(parser: argparse.ArgumentParser, *, on_subcommand: bool) -> None:
    """-v and --log-level, on the main parser and (with ``on_subcommand``) on every subcommand.

    On a subcommand their default is ``SUPPRESS``: a value given before the command
    survives, one given after it wins, and an absent one never overwrites.
    """
    default: dict[str, Any] = {"default": argparse.SUPPRESS} if on_subcommand else {}
    existing = getattr(parser, "_option_string_actions", {})
    if "-v" not in existing and "--verbose" not in existing:
        parser.add_argument("-v", "--verbose", action="store_true", help="log progress (same as --log-level info)",
                            **default)
    if "--log-level" not in existing:
        parser.add_argument("--log-level", choices=LOG_LEVELS, type=str.lower,
                            help="least severe messages to log: debug, info, warning (default) or error",
                            **({"default": None} if not on_subcommand else default))


def configure_logging(args: argparse.Namespace) -> None:
    level = getattr(args, "log_level", None) or ("info" if getattr(args, "verbose", False) else "warning")
    logging.basicConfig(level=level.upper(), format="%(levelname)s %(name)s: %(message)s")


def parse_cameras(text: str) -> list[int]:
    """``--cameras 0,2,4,6`` -> [0, 2, 4, 6] (an argparse type): at least one whole number >= 0;
    spaces and empty items between the commas are ignored (``shadowcorr-client`` parses the same)."""
    try:
        cameras = [int(c) for c in text.split(",") if c.strip()]
    except ValueError:
        cameras = []
    if not cameras or min(cameras) < 0:
        raise argparse.ArgumentTypeError(f"expected comma-separated camera numbers (e.g. 0,2,4,6), got {text!r}")
    return cameras


def add_method_options(p: argparse.ArgumentParser, threads_default: int = 0) -> None:
    """The options that choose the method and its settings (shared by correspond, eval and batch).

    ``threads_default``: ``--threads`` when not given (0: every core; ``batch``, which runs
    scenes side by side, passes 1)."""
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
    p.add_argument("--device", default="cpu", type=_device,
                   help="torch device of the network: cpu (default), cuda, cuda:N or mps; the rest runs on the CPU")
    p.add_argument("--threads", type=_threads, default=threads_default,
                   help="threads for one scene: the stages' num_threads and torch's (0: every core; "
                   f"default {threads_default})")


def _device(text: str) -> str:
    from .config import DEVICE_PATTERN

    if re.match(DEVICE_PATTERN, text) is None:
        raise argparse.ArgumentTypeError(f"expected cpu, cuda or cuda:N (or mps), got {text!r}")
    return text


def _number(text: str, kind: type, accept: Callable[[Any], bool], expected: str) -> Any:
    """``kind(text)`` when it parses and ``accept`` takes it; otherwise argparse's error, ``expected ..., got ...``."""
    try:
        value = kind(text)
    except ValueError:
        value = None
    if value is None or not accept(value):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def _threads(text: str) -> int:
    return _number(text, int, lambda n: n >= 0, "a thread count (0: every core)")


def config_from_args(args: argparse.Namespace) -> "ShadowCorrConfig":
    """The ``ShadowCorrConfig`` that the options of :func:`add_method_options` describe."""
    from .config import ShadowCorrConfig

    options: dict[str, object] = {"method": args.method, "num_threads": args.threads}
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
    import torch

    from .nn import load_model
    from .ops import resolve_threads

    torch.set_num_threads(resolve_threads(args.threads))
    return load_model(args.model, device=args.device)


# --------------------------------------------------------------------------- scenes
def iter_scenes(source: Path, cameras: Sequence[int] | None = None) -> Iterator[tuple[str, Callable[[], Any]]]:
    """Yield (name, loader) for every scene under ``source``.

    ``source`` may be a bundle directory or archive, a directory of those, an
    Unreal-layout dataset directory (each set becomes a scene with ``cameras``), or a
    ROS bag (cameras found by their topic layout; ``convert rosbag`` takes explicit ones).
    The loader is called lazily so a long evaluation never holds every scene at once.
    ``cameras`` on anything but an Unreal-layout directory is an error, not ignored.
    """
    from .convert.rosbag import is_rosbag
    from .convert.ue import load_ue_scene, ue_sets
    from .io import load_bundle

    def no_cameras(what: str) -> None:
        if cameras:
            raise ValueError(f"--cameras selects cameras of an Unreal-layout dataset, but {str(source)!r} is {what}: "
                             "leave --cameras out (a bundle's views are all used; convert it again to choose others)")

    if is_rosbag(source):
        from .convert.rosbag import load_rosbag_scene

        no_cameras("a ROS bag")
        yield source.name, lambda: load_rosbag_scene(source)
        return
    if source.is_file() or (source / "manifest.json").exists():
        no_cameras("a bundle")
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
    children = [c for c in sorted(source.iterdir())
                if (c / "manifest.json").exists() or c.suffix in {".zip", ".tar"} or c.name.endswith(".tar.gz")]
    if not children:
        raise FileNotFoundError(f"{source}: holds no bundle, bundle archive or Unreal-layout set")
    no_cameras("a directory of bundles")
    for child in children:
        yield child.name, (lambda c=child: load_bundle(c))


# --------------------------------------------------------------------------- commands
def cmd_convert(args: argparse.Namespace) -> int:
    if args.kind == "ue":
        from .convert import convert_ue

        out = convert_ue(args.source, args.set, args.cameras, args.out, focal_px=args.focal_px)
    elif args.kind == "rosbag":
        from .convert.rosbag import convert_rosbag

        out = convert_rosbag(args.source, args.out, args.camera, fixed_frame=args.fixed_frame,
                             sync_tolerance=args.sync_tolerance, max_views=args.max_views, every=args.every,
                             ground_truth=args.ground_truth)
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
    result = correspond(load(), _model(args), config_from_args(args), metrics=not args.no_metrics)
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


def cmd_export(args: argparse.Namespace) -> int:
    from .export import export
    from .result import Result

    try:
        result = Result.model_validate_json(Path(args.result).read_bytes())
    except OSError as exc:
        raise FileNotFoundError(f"{args.result}: {exc.strerror}") from None
    except ValueError as exc:  # pydantic's ValidationError is a ValueError
        raise ValueError(f"{args.result} is not a result JSON: {exc}") from None
    (_, load), *rest = list(iter_scenes(Path(args.bundle), args.cameras))
    if rest:
        raise SystemExit(f"{args.bundle} holds {len(rest) + 1} scenes; `export` takes the one the result was computed from")
    try:
        out = export(result, load(), args.to, args.out, frame_id=args.frame_id, storage=args.storage)
    except ImportError as exc:
        raise SystemExit(f"error: {exc}") from None
    print(f"wrote {args.to} {out}")
    return 0


#: Metric key -> column header of the `eval` table (each fits its 18-character column).
EVAL_COLUMNS = {"average_purity": "average purity", "rock_purity": "rock purity", "cluster_purity": "cluster purity",
                "voxel_ari": "voxel ARI", "perfect_one_to_one_share": "perfect 1:1 share", "coverage": "coverage %"}


def cmd_eval(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .evaluation import summarize
    from .pipeline import correspond

    model, config = _model(args), config_from_args(args)
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

    head = f"{'scene':<24}" + "".join(f"{label:>18}" for label in EVAL_COLUMNS.values())
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


def _map_options(args: argparse.Namespace) -> "ShadowCorrConfig | None":
    """The settings ``map add`` was given explicitly (None: the map's own, or the defaults for a new map)."""
    from .config import ShadowCorrConfig

    options: dict[str, object] = {"num_threads": args.threads}
    if args.refine_poses is not None:
        options["refine_poses"] = args.refine_poses
    if args.min_blob_pixels is not None:
        options["min_blob_pixels"] = args.min_blob_pixels
    return ShadowCorrConfig(**options)


def cmd_map_add(args: argparse.Namespace) -> int:
    from .sitemap import MapBusyError

    try:
        return _map_add(args)
    except MapBusyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3


def _map_add(args: argparse.Namespace) -> int:
    from .sitemap import SiteMap

    sources = [(name, load) for source in args.bundles for name, load in iter_scenes(Path(source), args.cameras)]
    model = _model(argparse.Namespace(method="fused", model=args.model, device=args.device, threads=args.threads))
    out = open(args.out, "w") if args.out else None  # noqa: SIM115 - written update by update, closed below
    try:
        with SiteMap(args.map, _map_options(args), model=model) as site:
            for name, load in sources:
                update = site.add(load(), name=name)
                text = update.model_dump_json(indent=None if len(sources) > 1 or not out else 1)
                counts = {k: sum(e.kind == k for e in update.events) for k in ("created", "observed", "merged", "split",
                                                                              "retired")}
                summary = (f"scan {update.scan} ({name}): {len(update.segments)} segments, linked to "
                           f"{len(update.linked_views)} stored views; " +
                           ", ".join(f"{n} {k}" for k, n in counts.items() if n) +
                           f"; {update.timings_ms['total']:.0f} ms")
                if out:
                    out.write(text + "\n")
                    out.flush()  # a later scan's failure leaves the earlier updates written
                    print(summary)
                else:
                    print(text)
                    print(summary, file=sys.stderr)
                for w in update.warnings:
                    print(f"warning: {w}", file=sys.stderr)
    finally:
        if out:
            out.close()
    if args.out:
        print(f"wrote {args.out}")
    return 0


def cmd_map_show(args: argparse.Namespace) -> int:
    from .sitemap import SiteMap

    if not Path(args.map).is_file():
        raise FileNotFoundError(f"{args.map}: no such map")
    with SiteMap(args.map, create=False) as site:
        state = site.state()
    text = state.model_dump_json(indent=1)
    if args.out:
        Path(args.out).write_text(text)
        print(f"{len(state.scans)} scans, {len(state.objects)} objects, {len(state.segments)} segments, "
              f"{len(state.events)} events; wrote {args.out}")
    else:
        print(text)
    return 0


def _add_map_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="a site map that grows scan by scan: stable object ids and their history",
                       description="A site map (one SQLite file): each scan added gets the ids of the objects it "
                                   "sees again, and every revision of an object is an event.")
    cmds = p.add_subparsers(dest="map_command", required=True, metavar="{add,show}")
    add = cmds.add_parser("add", help="add scans to a map (created when absent)",
                          description="Add each bundle as one scan (one update each, in order). With --out, one "
                                      "update JSON per scan (JSON lines when there are several); without, they are "
                                      "printed.")
    add.add_argument("map", help="the map file (created when absent)")
    add.add_argument("bundles", nargs="+", metavar="BUNDLE",
                     help="bundle directory or archive, a ROS bag, or an Unreal-layout directory (each scene is a scan)")
    add.add_argument("--cameras", type=parse_cameras, help="cameras to use from an Unreal-layout directory")
    add.add_argument("--out", help="write the update JSON here (JSON lines for several bundles)")
    add.add_argument("--model", help="model file (.safetensors or reference .pth); default: the packaged model")
    add.add_argument("--min-blob-pixels", type=int, help="a new map: ignore blobs with fewer pixels (default 50)")
    add.add_argument("--refine-poses", action=argparse.BooleanOptionalAction, default=None,
                     help="a new map: register each scan's depth with the map's views and correct its poses "
                          "(default on)")
    add.add_argument("--device", default="cpu", type=_device, help="torch device of the network (default cpu)")
    add.add_argument("--threads", type=_threads, default=0, help="threads (0: every core; default 0)")
    add.set_defaults(func=cmd_map_add)
    show = cmds.add_parser("show", help="print or write the whole map as JSON",
                           description="The map as JSON: scans, objects, every segment with its current object, "
                                       "and the events.")
    show.add_argument("map", help="the map file")
    show.add_argument("--out", help="write the map JSON here (default: print it)")
    show.set_defaults(func=cmd_map_show)


def positive_int(text: str) -> int:
    """An argparse type: a whole number >= 1."""
    return _number(text, int, lambda n: n >= 1, "a whole number >= 1")


def seconds(text: str) -> float:
    """An argparse type: a finite number of seconds >= 0."""
    return _number(text, float, lambda s: 0.0 <= s < float("inf"), "a number of seconds >= 0")


def _bag_camera(text: str):
    from .convert.rosbag import BagCamera

    try:
        return BagCamera.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _add_convert_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("convert", help="convert a dataset into a scene bundle",
                       description="Convert a dataset into a scene bundle directory.")
    conv = p.add_subparsers(dest="kind", required=True, metavar="{ue,rosbag,reference-npz}")
    ue = conv.add_parser("ue", help="the authors' Unreal lunar rock dataset layout",
                         description="One set of the Unreal lunar rock dataset (SetNNNN_Depth_C.exr + "
                                     "SetNNNN_Segment_C.png per camera) -> bundle in cm with instance ground truth.")
    ue.add_argument("source", help="dataset directory holding SetNNNN_Depth_C.exr and SetNNNN_Segment_C.png")
    ue.add_argument("--set", required=True, help="set id, e.g. 2001")
    ue.add_argument("--cameras", type=parse_cameras, default=[0, 2, 4, 6], help="cameras to use (default 0,2,4,6)")
    ue.add_argument("--focal-px", type=float, default=1615.0, help="focal length (the documented 960 is wrong)")
    ue.add_argument("--out", required=True, help="bundle directory to write")
    bag = conv.add_parser(
        "rosbag", help="a ROS 1 or ROS 2 (sqlite3, MCAP) bag of depth + instance-mask images",
        description="A bag's depth images (32FC1 metres or 16UC1 millimetres), instance masks (mono8, mono16, "
                    "16UC1, 32SC1), CameraInfo and /tf + /tf_static -> bundle in metres. Depth and mask are paired by "
                    "header.stamp; each pair is one view, posed by the transform from --fixed-frame to the image's "
                    "optical frame at that stamp. Without --camera, cameras laid out as NS/depth/image_raw + "
                    "NS/depth/camera_info + NS/instances/image_raw are found. Distorted images are refused "
                    "(record rectified ones).")
    bag.add_argument("source", help="ROS 2 bag directory (metadata.yaml + .db3/.mcap), or a ROS 1 .bag file")
    bag.add_argument("--out", required=True, help="bundle directory to write")
    bag.add_argument("--camera", action="append", type=_bag_camera, metavar="NAME=DEPTH_TOPIC,MASK_TOPIC[,INFO_TOPIC]",
                     help="one camera (repeat for more); INFO_TOPIC defaults to the camera_info beside DEPTH_TOPIC")
    bag.add_argument("--fixed-frame", default="map", help="world frame of the poses (default %(default)s)")
    bag.add_argument("--sync-tolerance", type=seconds, default=0.0, metavar="SECONDS",
                     help="largest stamp difference between a depth image and its mask, and the furthest a "
                          "transform is extrapolated (default 0: exact stamps)")
    bag.add_argument("--every", type=positive_int, default=1, metavar="K",
                     help="keep every K-th depth+mask pair of each camera (default 1)")
    bag.add_argument("--max-views", type=positive_int, metavar="N",
                     help="at most N views per camera, evenly spread over the recording")
    bag.add_argument("--ground-truth", choices=["none", "instance"], default="none",
                     help="'instance': mask ids are object identities in every view (enables metrics)")
    ref = conv.add_parser("reference-npz", help="the reference code's stacked-segment .npz (pickled: trusted local files only)",
                          description="The reference implementation's segment .npz -> bundle. It is a pickle: "
                                      "convert only files you trust.")
    ref.add_argument("source", help="the .npz file")
    ref.add_argument("--out", required=True, help="bundle directory to write")
    p.set_defaults(func=cmd_convert)


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(prog="shadowcorr", description=DESCRIPTION,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"shadowcorr {__version__}")
    add_global_options(parser, on_subcommand=False)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=CommandParser)

    _add_convert_parser(sub)

    p = sub.add_parser("correspond", help="label every segment of one scene",
                       description="Label every segment of one scene with its object; print or write the result JSON.")
    p.add_argument("bundle", help="bundle directory or .zip/.tar, a ROS bag, or an Unreal-layout directory with one set")
    p.add_argument("--cameras", type=parse_cameras, help="cameras to use from an Unreal-layout directory")
    p.add_argument("--out", help="write the result JSON here (default: print it)")
    p.add_argument("--no-metrics", action="store_true", help="skip ground-truth metrics")
    add_method_options(p)
    p.set_defaults(func=cmd_correspond)

    p = sub.add_parser("export", help="a result as a ROS 2 bag, PLY files or a Rerun recording",
                       description="Write a result JSON and the bundle it was computed from as a ROS 2 bag (vision_msgs "
                       "detections, markers, the labelled point cloud, camera frames; metres), PLY files (one per "
                       "object and one coloured with all) or a Rerun recording (pip install 'shadowcorr[viz]'). "
                       "See docs/guide/exports.md.")
    p.add_argument("result", help="result JSON (shadowcorr correspond --out, or the service's answer)")
    p.add_argument("bundle", help="the bundle the result was computed from (as for correspond)")
    p.add_argument("out", help="bag or PLY directory, or .rrd file, to create (never overwritten)")
    p.add_argument("--to", required=True, choices=["bag", "ply", "rrd"], help="the format to write")
    p.add_argument("--cameras", type=parse_cameras, help="cameras of an Unreal-layout directory (as for correspond)")
    p.add_argument("--frame-id", default="map", help="world frame of the bag's messages (default %(default)s)")
    p.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap", help="the bag's storage (default %(default)s)")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("eval", help="metrics over one scene or a directory of scenes (mean ± std)",
                       description="Quality metrics against ground truth, per scene and as mean ± std.")
    p.add_argument("source", help="bundle, directory of bundles, or Unreal-layout dataset directory")
    p.add_argument("--cameras", type=parse_cameras, help="cameras to use from an Unreal-layout directory")
    p.add_argument("--json", help="also write per-scene rows and the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_method_options(p)
    p.set_defaults(func=cmd_eval)

    _add_map_parser(sub)

    for command in _plugin_commands():
        command.load()(sub)
    for subparser in _all_subparsers(sub):
        add_global_options(subparser, on_subcommand=True)
    return parser


def _all_subparsers(sub: argparse._SubParsersAction) -> list[argparse.ArgumentParser]:
    """Every (nested) subcommand parser, so that global options are accepted after any command."""
    out: list[argparse.ArgumentParser] = []
    for parser in dict.fromkeys(sub.choices.values()):
        out.append(parser)
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                out += _all_subparsers(action)
    return out


def _plugin_commands():
    """Subcommands registered in the ``shadowcorr.commands`` entry-point group (see pyproject.toml).

    The service registers ``serve`` this way, so the library's CLI does not depend on it.
    """
    from importlib.metadata import entry_points

    return sorted(entry_points(group="shadowcorr.commands"), key=lambda ep: ep.name)


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv == ["--version"]:  # answered before the plugin commands are looked up (importlib.metadata is slow)
        print(f"shadowcorr {__version__}")
        return 0
    args = build_parser().parse_args(argv)
    configure_logging(args)
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
