"""``shadowcorr-client``: talk to a ShadowCorr server from the shell (see DESCRIPTION)."""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Sequence

from .client import DEFAULT_SERVER, AsyncShadowCorrClient, RetryEvent, ShadowCorrClient
from .dataset import LIBRARY_INSTALL, BagOptions, SceneSource, discover_scenes, parse_bag_camera
from .errors import BundleInputError, ConnectionFailed, ResponseError, ShadowCorrError
from .records import RecordWriter, UploadRecord, format_metrics, format_summary, read_records, summarize_records
from .retry import RetryPolicy
from .request_body import BundleUpload
from .bulk_upload import upload_scenes

__all__ = ["main", "build_parser"]

DESCRIPTION = """\
Talk to a ShadowCorr server: health, info, correspond (one scene), upload-dataset (many, resumable),
map (site maps that keep object ids across scans).

Connection options (--server, default $SHADOWCORR_SERVER or http://127.0.0.1:8000; --token,
default $SHADOWCORR_TOKEN; --timeout, --retries, ...) and -v / --log-level may come before or
after the command.

Exit status: 0 success; 1 a request or a scene failed (or the server is not ready);
2 bad usage or unusable local input; 130 interrupted.
"""
LOG_LEVELS = ("debug", "info", "warning", "error")


# The option types below follow the library's CLI (shadowcorr.cli) case for case, without
# importing it: tests/test_cli_parsing.py runs one table of cases against both.
def _cameras(text: str) -> list[int]:
    """At least one whole number >= 0, comma-separated; spaces and empty items are ignored."""
    try:
        cameras = [int(c) for c in text.split(",") if c.strip()]
    except ValueError:
        cameras = []
    if not cameras or min(cameras) < 0:
        raise argparse.ArgumentTypeError(f"expected comma-separated camera numbers (e.g. 0,2,4,6), got {text!r}")
    return cameras


def _number(text: str, kind: type, accept: Callable[[Any], bool], expected: str) -> Any:
    try:
        value = kind(text)
    except ValueError:
        value = None
    if value is None or not accept(value):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def _positive_int(text: str) -> int:
    return _number(text, int, lambda n: n >= 1, "a whole number >= 1")


def _seconds(text: str) -> float:
    return _number(text, float, lambda s: 0.0 <= s < float("inf"), "a number of seconds >= 0")


def _add_global_options(p: argparse.ArgumentParser, *, on_subcommand: bool) -> None:
    """Connection and logging options, on the main parser and (``on_subcommand``) on every command.

    On a command their default is ``SUPPRESS``, so `--server X health` and `health --server X`
    both work and an option left out after the command never overwrites one given before it.
    """
    def default(value: Any) -> dict[str, Any]:
        return {"default": argparse.SUPPRESS} if on_subcommand else {"default": value}

    g = p.add_argument_group("connection and logging (before or after the command)")
    g.add_argument("--server", **default(os.environ.get("SHADOWCORR_SERVER") or DEFAULT_SERVER),
                   help="server URL (env SHADOWCORR_SERVER; default http://127.0.0.1:8000)")
    g.add_argument("--token", **default(os.environ.get("SHADOWCORR_TOKEN") or None),
                   help="bearer token (prefer env SHADOWCORR_TOKEN: command lines are visible to other users)")
    g.add_argument("--timeout", type=float, **default(300.0),
                   help="seconds to wait for an answer to one request (default 300)")
    g.add_argument("--retries", type=int, **default(4),
                   help="retries after a connection failure, 502 or 503 (default 4; 0 = none)")
    g.add_argument("--backoff", type=float, **default(0.5),
                   help="seconds before the first retry, doubling each time (default 0.5)")
    g.add_argument("--max-retry-after", type=float, **default(60.0),
                   help="cap on the server's Retry-After, in seconds (default 60)")
    g.add_argument("-v", "--verbose", action="store_true", **default(False),
                   help="log retries (same as --log-level info)")
    g.add_argument("--log-level", choices=LOG_LEVELS, type=str.lower, **default(None),
                   help="least severe messages to log: debug, info, warning (default) or error")


def _options_parent() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("correspondence options (server defaults when omitted)")
    g.add_argument("--method", choices=["fused", "projection", "shadowcorr", "meanshift"],
                   help="the server's default is 'fused'; 'projection' and 'meanshift' run no network")
    g.add_argument("--bandwidth", type=float, help="MeanShift bandwidth")
    g.add_argument("--no-split-components", action="store_true",
                   help="keep disconnected blobs of one mask value together")
    g.add_argument("--min-blob-pixels", type=int, help="ignore blobs with fewer pixels")
    g.add_argument("--min-cluster-size", type=int, help="clusters with fewer voxels merge into a larger one")
    g.add_argument("--refine-poses", action=argparse.BooleanOptionalAction, default=None,
                   help="correct the views' poses from their depth first (the server's default: on)")
    g.add_argument("--metrics", action="store_true", help="ask for quality metrics (bundles with ground truth)")
    _add_scene_options(p, g)
    return p


def _add_scene_options(p: argparse.ArgumentParser, g: Any) -> None:
    """Which scenes of a folder are sent: Unreal cameras (in group ``g``) and ROS bag conversion."""
    g.add_argument("--cameras", type=_cameras,
                   help="cameras of Unreal-layout sets, e.g. 0,2,4,6 (default: every camera present)")
    b = p.add_argument_group("ROS bags (converted locally; the options of `shadowcorr convert rosbag`)")
    b.add_argument("--camera", action="append", type=_bag_camera, metavar="NAME=DEPTH_TOPIC,MASK_TOPIC[,INFO_TOPIC]",
                   help="a camera of the bags (repeat for more; default: found by the NS/depth/image_raw layout)")
    b.add_argument("--fixed-frame", default="map", help="world frame of the poses (default %(default)s)")
    b.add_argument("--sync-tolerance", type=_seconds, default=0.0, metavar="SECONDS",
                   help="largest depth/mask stamp difference (default 0: exact)")
    b.add_argument("--every", type=_positive_int, default=1, metavar="K", help="keep every K-th view of a camera")
    b.add_argument("--max-views", type=_positive_int, metavar="N", help="at most N views per camera")


def _bag_camera(text: str) -> str:
    try:
        return parse_bag_camera(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _bag_options(args: argparse.Namespace) -> BagOptions:
    return BagOptions(cameras=tuple(args.camera or ()), fixed_frame=args.fixed_frame,
                      sync_tolerance=args.sync_tolerance, max_views=args.max_views, every=args.every)


def _request_options(args: argparse.Namespace) -> dict[str, Any]:
    return {
        "method": args.method,
        "bandwidth": args.bandwidth,
        "split_components": False if args.no_split_components else None,
        "min_blob_pixels": args.min_blob_pixels,
        "min_cluster_size": args.min_cluster_size,
        "refine_poses": args.refine_poses,
        "metrics": True if args.metrics else None,
    }


def _policy(args: argparse.Namespace) -> RetryPolicy:
    return RetryPolicy(max_attempts=max(args.retries, 0) + 1, backoff_base=args.backoff,
                       backoff_max=max(30.0, args.backoff), retry_after_max=args.max_retry_after)


def _client_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    import httpx

    timeout = httpx.Timeout(connect=min(10.0, args.timeout), read=args.timeout, write=args.timeout, pool=None)
    return {"token": args.token, "timeout": timeout, "retry": _policy(args)}


def _print_json(data: Any) -> None:
    print(json.dumps(data, indent=1))


# --------------------------------------------------------------------------- commands
def cmd_health(args: argparse.Namespace) -> int:
    with ShadowCorrClient(args.server, **_client_kwargs(args)) as client:
        try:
            _print_json(client.wait_until_ready(args.wait) if args.wait > 0 else client.health())
        except ResponseError as exc:  # 503 while starting: the server's own code and message, and fail the probe
            print(f"not ready: {exc.error}: {exc.message}", file=sys.stderr)
            return 1
        except ConnectionFailed as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    with ShadowCorrClient(args.server, **_client_kwargs(args)) as client:
        _print_json(client.info())
    return 0


def _discover(path: str, args: argparse.Namespace) -> list[SceneSource]:
    """The scenes under ``path``; --cameras where nothing has Unreal cameras is an error, not ignored."""
    scenes = discover_scenes(path, args.cameras, bag=_bag_options(args))
    if args.cameras and not any(s.kind == "unreal" for s in scenes):
        raise BundleInputError(f"--cameras selects cameras of Unreal-layout sets, and {path} holds none: leave "
                               "--cameras out (a bundle's views are all sent; bags take --camera NAME=...)")
    if args.camera and not any(s.kind == "rosbag" for s in scenes):
        raise BundleInputError(f"--camera selects the cameras of ROS bags, and {path} holds none")
    return scenes


def _single_scene(path: str, args: argparse.Namespace) -> SceneSource:
    scenes = _discover(path, args)
    if len(scenes) > 1:
        names = ", ".join(s.name for s in scenes[:5])
        raise BundleInputError(f"{path} holds {len(scenes)} scenes ({names}...); `correspond` takes one, "
                               "use `upload-dataset` for many")
    return scenes[0]


def _render(scene: SceneSource, bundle: Any, result: Any, args: argparse.Namespace) -> None:
    """Draw the result over the scene with the library's renderer (``shadowcorr.render``)."""
    try:
        from shadowcorr.config import ShadowCorrConfig
        from shadowcorr.render import RenderConfig, render_result
    except ModuleNotFoundError as exc:
        raise BundleInputError(f"--render draws with the ShadowCorr library, which is not installed "
                               f"(no module {exc.name!r}): {LIBRARY_INSTALL}") from None
    # The renderer re-cuts the masks into segments: it must use the options the server used.
    engine: dict[str, Any] = dict(result.config or {})
    if args.no_split_components:
        engine["split_components"] = False
    if args.min_blob_pixels is not None:
        engine["min_blob_pixels"] = args.min_blob_pixels
    files = render_result(bundle if bundle is not None else scene.load_bundle(), result, args.render,
                          config=RenderConfig(engine=ShadowCorrConfig(**engine)))
    print(f"rendered {len(files)} picture(s) into {args.render}", file=sys.stderr)


def cmd_correspond(args: argparse.Namespace) -> int:
    scene = _single_scene(args.bundle, args)
    bundle = None
    if args.render and scene.needs_conversion:
        # Convert once, and draw over exactly what was sent.
        bundle = scene.load_bundle()
        upload = BundleUpload.from_bundle(bundle, name=scene.name)
    else:
        upload = scene.load()
    with ShadowCorrClient(args.server, **_client_kwargs(args)) as client:
        start = time.perf_counter()
        result = client.correspond(upload, **_request_options(args))
        elapsed_ms = (time.perf_counter() - start) * 1e3
    text = result.model_dump_json(indent=1)
    if args.render:
        _render(scene, bundle, result, args)
    if not args.out:
        print(text)
        return 0
    Path(args.out).write_text(text + "\n")
    print(f"{scene.name}: {len(result.segments)} segments -> {len(result.objects)} objects "
          f"in {elapsed_ms:.0f} ms; wrote {args.out}")
    if result.metrics:
        print("  " + format_metrics(result.metrics))
    for warning in result.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    return 0


def _progress(total: int, disable: bool):
    from tqdm import tqdm

    # tqdm's rate and ETA come from its own smoothed timing: scenes/s and time left.
    return tqdm(total=total, unit="scene", desc="upload", dynamic_ncols=True, disable=disable, file=sys.stderr)


def cmd_upload_dataset(args: argparse.Namespace) -> int:
    scenes = _discover(args.dir, args)
    latest, bad_lines = read_records(args.out)
    if bad_lines:
        print(f"note: skipped {bad_lines} unreadable line(s) in {args.out} (an interrupted write)", file=sys.stderr)
    done = {name for name, rec in latest.items() if rec.ok}
    todo = [s for s in scenes if s.name not in done]
    skipped = len(scenes) - len(todo)
    if args.limit is not None:
        todo = todo[: args.limit]
    print(f"{len(scenes)} scenes in {args.dir}: {skipped} already done, sending {len(todo)} "
          f"to {args.server} with concurrency {args.concurrency}", file=sys.stderr)

    run_records: list[UploadRecord] = []
    retries = 0
    unreachable_streak = 0  # consecutive scenes lost to connection failures
    bar = _progress(len(todo), args.no_progress)

    def on_retry(_: RetryEvent) -> None:
        nonlocal retries
        retries += 1

    def on_record(record: UploadRecord) -> None:
        nonlocal unreachable_streak
        writer.write(record)  # first, so the line is on disk even if the display fails
        run_records.append(record)
        lost = not record.ok and (record.error or {}).get("type") == "ConnectionFailed"
        unreachable_streak = unreachable_streak + 1 if lost else 0
        latest[record.scene] = record
        failed = sum(not r.ok for r in run_records)
        bar.set_postfix(failed=failed, retries=retries, refresh=False)
        bar.update(1)
        if not record.ok and not args.no_progress:  # live news under the bar; the summary lists them all again
            bar.write(f"failed {record.scene}: {(record.error or {}).get('message')}", file=sys.stderr)

    def server_gone() -> bool:
        # Every scene already waits through its own retries; once several in a row found
        # no server, the rest would only pile up identical failures: stop, keep them for a rerun.
        return bool(args.abort_after) and unreachable_streak >= args.abort_after

    async def run() -> None:
        async with AsyncShadowCorrClient(args.server, on_retry=on_retry, max_connections=args.concurrency,
                                         **_client_kwargs(args)) as client:
            try:
                await client.health(retry=client.retry)  # fail fast on a wrong address, before reading any scene
            except ResponseError:
                pass  # e.g. 503 while the server warms up: the retries of each request cover that
            await upload_scenes(client, todo, concurrency=args.concurrency, options=_request_options(args),
                                on_record=on_record, should_stop=server_gone)

    start = time.perf_counter()
    interrupted = False
    with RecordWriter(args.out) as writer:
        try:
            asyncio.run(run())
        except KeyboardInterrupt:
            interrupted = True
        finally:
            bar.close()
    summary = summarize_records([s.name for s in scenes], skipped, run_records, latest, time.perf_counter() - start)
    print(format_summary(summary))
    for scene, message in summary.failures:
        print(f"failed {scene}: {message}", file=sys.stderr)
    if interrupted:
        print(f"interrupted: finished scenes are in {args.out}; run the same command again to resume",
              file=sys.stderr)
        return 130
    if server_gone():
        print(f"stopped after {unreachable_streak} scenes in a row could not reach {args.server}; "
              f"{summary.pending} scene(s) not sent: run the same command again to resume", file=sys.stderr)
    return 1 if summary.failed else 0


def cmd_map_create(args: argparse.Namespace) -> int:
    with ShadowCorrClient(args.server, **_client_kwargs(args)) as client:
        _print_json({"map": client.create_map()})
    return 0


def cmd_map_add(args: argparse.Namespace) -> int:
    scenes = [scene for path in args.bundles for scene in _discover(path, args)]
    out = open(args.out, "w") if args.out else None  # noqa: SIM115 - written scan by scan, closed below
    try:
        with ShadowCorrClient(args.server, **_client_kwargs(args)) as client:
            for scene in scenes:
                update = client.add_scan(args.map, scene.load(), name=scene.name)
                kinds = [e["kind"] for e in update["events"]]
                summary = (f"scan {update['scan']} ({scene.name}): {len(update['segments'])} segments; " + ", ".join(
                    f"{kinds.count(k)} {k}" for k in ("created", "observed", "merged", "split", "retired")
                    if kinds.count(k)))
                if out:
                    out.write(json.dumps(update) + "\n")
                    out.flush()  # a later scan's failure leaves the earlier updates written
                    print(summary)
                else:
                    print(json.dumps(update, indent=None if len(scenes) > 1 else 1))
                    print(summary, file=sys.stderr)
    finally:
        if out:
            out.close()
    return 0


def cmd_map_show(args: argparse.Namespace) -> int:
    with ShadowCorrClient(args.server, **_client_kwargs(args)) as client:
        state = client.get_map(args.map)
    if args.out:
        Path(args.out).write_text(json.dumps(state, indent=1) + "\n")
        print(f"{len(state['scans'])} scans, {len(state['objects'])} objects, {len(state['segments'])} segments, "
              f"{len(state['events'])} events; wrote {args.out}")
    else:
        _print_json(state)
    return 0


def cmd_map_events(args: argparse.Namespace) -> int:
    with ShadowCorrClient(args.server, **_client_kwargs(args)) as client:
        _print_json(client.map_events(args.map, since=args.since))
    return 0


def cmd_map_delete(args: argparse.Namespace) -> int:
    with ShadowCorrClient(args.server, **_client_kwargs(args)) as client:
        client.delete_map(args.map)
    print(f"deleted map {args.map}", file=sys.stderr)
    return 0


def _add_map_commands(sub: Any) -> None:
    """``map create|add|show|events|delete``: site maps kept by the server."""
    p = sub.add_parser("map", help="site maps kept by the server: stable object ids across scans",
                       description="Site maps kept by the server: each scan added gets the ids of the objects it "
                                   "sees again; every revision of an object is an event.")
    _add_global_options(p, on_subcommand=True)
    maps = p.add_subparsers(dest="map_command", required=True, metavar="{create,add,show,events,delete}")

    def command(name: str, help_text: str) -> argparse.ArgumentParser:
        c = maps.add_parser(name, help=help_text, description=help_text[0].upper() + help_text[1:])
        _add_global_options(c, on_subcommand=True)
        return c

    command("create", "create an empty map; prints its id").set_defaults(func=cmd_map_create)
    c = command("add", "add scans to a map, one per scene, in order (the update JSON of each)")
    c.add_argument("map", help="the map's id")
    c.add_argument("bundles", nargs="+", metavar="BUNDLE",
                   help="bundle directory or archive, a ROS bag, or an Unreal-layout folder (each scene is a scan)")
    c.add_argument("--out", help="write the updates here as JSON lines (default: print them)")
    _add_scene_options(c, c.add_argument_group("scenes"))
    c.set_defaults(func=cmd_map_add)
    c = command("show", "the whole map: scans, objects, every segment with its object, the events")
    c.add_argument("map", help="the map's id")
    c.add_argument("--out", help="write the map JSON here (default: print it)")
    c.set_defaults(func=cmd_map_show)
    c = command("events", "the map's history")
    c.add_argument("map", help="the map's id")
    c.add_argument("--since", type=int, default=0, metavar="N", help="only events after event N (default 0: all)")
    c.set_defaults(func=cmd_map_events)
    c = command("delete", "delete a map")
    c.add_argument("map", help="the map's id")
    c.set_defaults(func=cmd_map_delete)


# --------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="shadowcorr-client", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_global_options(parser, on_subcommand=False)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    opts = _options_parent()

    def command(name: str, help_text: str, *parents: argparse.ArgumentParser) -> argparse.ArgumentParser:
        p = sub.add_parser(name, parents=list(parents), help=help_text, description=help_text[0].upper() + help_text[1:])
        _add_global_options(p, on_subcommand=True)
        return p

    p = command("health", "is the server up and ready? (exit 1 if not)")
    p.add_argument("--wait", type=float, default=0.0, metavar="SECONDS",
                   help="poll until the server is ready or SECONDS pass (default 0: answer at once)")
    p.set_defaults(func=cmd_health)

    p = command("info", "model, version and limits of the server")
    p.set_defaults(func=cmd_info)

    p = command("correspond", "label every segment of one scene", opts)
    p.add_argument("bundle", help="bundle directory or archive, a ROS bag, or an Unreal-layout folder with one set")
    p.add_argument("--out", help="write the result JSON here (default: print it)")
    p.add_argument("--render", metavar="DIR",
                   help="also draw the result over the views into DIR (needs the library; decodes the scene locally)")
    p.set_defaults(func=cmd_correspond)

    p = command("upload-dataset", "send every scene of a directory; results as JSON lines, resumable", opts)
    p.add_argument("dir", help="directory of bundle directories / archives / Unreal-layout sets / ROS bags (any depth)")
    p.add_argument("--out", required=True, help="results file (JSON lines); scenes already 'ok' in it are skipped")
    p.add_argument("--concurrency", type=_positive_int, default=4, help="scenes in flight at once (default %(default)s)")
    p.add_argument("--limit", type=_positive_int, help="send at most this many scenes in this run")
    p.add_argument("--abort-after", type=int, default=5, metavar="N",
                   help="stop starting scenes after N in a row failed to reach the server (default %(default)s; 0 = never)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_upload_dataset)

    _add_map_commands(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    level = args.log_level or ("info" if args.verbose else None)
    if level:
        import logging

        logging.basicConfig(level=level.upper(), format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # Output piped into `head` and closed early: not an error of ours; silence the
        # interpreter's own complaint when it flushes stdout at exit.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (BundleInputError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ShadowCorrError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except ValueError as exc:  # e.g. the library's BundleError while converting an Unreal set locally
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
