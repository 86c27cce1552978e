"""``shadowcorr-client``: talk to a ShadowCorr server from the shell.

Commands::

    shadowcorr-client health
    shadowcorr-client info
    shadowcorr-client correspond BUNDLE [--out RESULT.json] [--metrics] [options]
    shadowcorr-client upload-dataset DIR --out results.jsonl [--cameras 0,2,4,6] [--concurrency 4] [--metrics]

Every command takes ``--server`` (default ``$SHADOWCORR_SERVER`` or
http://127.0.0.1:8000) and ``--token`` (default ``$SHADOWCORR_TOKEN``).

Exit status: 0 success; 1 a request or a scene failed (or the server is not ready);
2 bad usage or unusable local input; 130 interrupted.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

from .client import DEFAULT_SERVER, AsyncShadowCorrClient, RetryEvent, ShadowCorrClient
from .dataset import SceneSource, discover_scenes
from .errors import BundleInputError, ResponseError, ShadowCorrError
from .records import RecordWriter, UploadRecord, format_summary, read_records, summarize_records
from .retry import RetryPolicy
from .upload import BundleUpload
from .uploader import upload_scenes

__all__ = ["main", "build_parser"]


def _cameras(text: str) -> list[int]:
    try:
        cams = [int(c) for c in text.split(",") if c.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"cameras must be comma-separated integers, got {text!r}") from None
    if not cams:
        raise argparse.ArgumentTypeError("give at least one camera")
    return cams


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _connection_parent() -> argparse.ArgumentParser:
    # Attached to every subcommand so options can follow the command (`correspond X --server ...`).
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("connection")
    g.add_argument("--server", default=os.environ.get("SHADOWCORR_SERVER") or DEFAULT_SERVER,
                   help="server URL (env SHADOWCORR_SERVER; default %(default)s)")
    g.add_argument("--token", default=os.environ.get("SHADOWCORR_TOKEN") or None,
                   help="bearer token (prefer env SHADOWCORR_TOKEN: command lines are visible to other users)")
    g.add_argument("--timeout", type=float, default=300.0,
                   help="seconds to wait for an answer to one request (default %(default)s)")
    g.add_argument("--retries", type=int, default=4,
                   help="retries after a connection failure, 502 or 503 (default %(default)s; 0 = none)")
    g.add_argument("--backoff", type=float, default=0.5,
                   help="seconds before the first retry, doubling each time (default %(default)s)")
    g.add_argument("--max-retry-after", type=float, default=60.0,
                   help="cap on the server's Retry-After, in seconds (default %(default)s)")
    return p


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
    g.add_argument("--metrics", action="store_true", help="ask for quality metrics (bundles with ground truth)")
    g.add_argument("--cameras", type=_cameras,
                   help="cameras of Unreal-layout sets, e.g. 0,2,4,6 (default: every camera present)")
    return p


def _request_options(args: argparse.Namespace) -> dict[str, Any]:
    return {
        "method": args.method,
        "bandwidth": args.bandwidth,
        "split_components": False if args.no_split_components else None,
        "min_blob_pixels": args.min_blob_pixels,
        "min_cluster_size": args.min_cluster_size,
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
            _print_json(client.health())
        except ResponseError as exc:  # 503 while starting: say so, and fail the probe
            print(f"not ready: {exc}", file=sys.stderr)
            return 1
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    with ShadowCorrClient(args.server, **_client_kwargs(args)) as client:
        _print_json(client.info())
    return 0


def _single_scene(path: str, cameras: Sequence[int] | None) -> SceneSource:
    scenes = discover_scenes(path, cameras)
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
        raise BundleInputError(f"--render needs shadowcorr.render, which this installation lacks ({exc})") from None
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
    scene = _single_scene(args.bundle, args.cameras)
    bundle = None
    if args.render and scene.kind == "unreal":
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
        m = result.metrics
        print("  " + "  ".join(f"{k.replace('_', ' ')} {m[k]:.2f}" for k in
                               ("average_purity", "rock_purity", "cluster_purity") if k in m))
    for warning in result.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    return 0


def _progress(total: int, disable: bool):
    from tqdm import tqdm

    # tqdm's rate and ETA come from its own smoothed timing: scenes/s and time left.
    return tqdm(total=total, unit="scene", desc="upload", dynamic_ncols=True, disable=disable, file=sys.stderr)


def cmd_upload_dataset(args: argparse.Namespace) -> int:
    scenes = discover_scenes(args.dir, args.cameras)
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


# --------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="shadowcorr-client", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true", help="log retries")
    sub = parser.add_subparsers(dest="command", required=True)
    conn, opts = _connection_parent(), _options_parent()

    p = sub.add_parser("health", parents=[conn], help="is the server up and ready? (exit 1 if not)")
    p.set_defaults(func=cmd_health)

    p = sub.add_parser("info", parents=[conn], help="model, version and limits of the server")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("correspond", parents=[conn, opts], help="label every segment of one scene")
    p.add_argument("bundle", help="bundle directory or archive (or an Unreal-layout folder with one set)")
    p.add_argument("--out", help="write the result JSON here (default: print it)")
    p.add_argument("--render", metavar="DIR",
                   help="also draw the result over the views into DIR (needs shadowcorr.render; decodes the scene locally)")
    p.set_defaults(func=cmd_correspond)

    p = sub.add_parser("upload-dataset", parents=[conn, opts],
                       help="send every scene of a directory; results as JSON lines, resumable")
    p.add_argument("dir", help="directory of bundle directories / archives / Unreal-layout sets (any depth)")
    p.add_argument("--out", required=True, help="results file (JSON lines); scenes already 'ok' in it are skipped")
    p.add_argument("--concurrency", type=_positive_int, default=4, help="scenes in flight at once (default %(default)s)")
    p.add_argument("--limit", type=_positive_int, help="send at most this many scenes in this run")
    p.add_argument("--abort-after", type=int, default=5, metavar="N",
                   help="stop starting scenes after N in a row failed to reach the server (default %(default)s; 0 = never)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_upload_dataset)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.verbose:
        import logging

        logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
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
