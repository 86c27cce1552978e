"""Fault benchmark: hostile and broken clients against a real server on 127.0.0.1.

Starts ``python -m shadowcorr_service`` (default settings except ``--workers`` and a 2 s
shutdown grace) and reproduces, printing what the server held:

1. **stalled uploads**: 32 connections declare 1 MB and send 100 bytes; latency of
   valid requests while they are open (and without them), how long until each stalled
   upload is answered; a slow-loris connection (one header byte a second): when it is
   closed, and with what;
2. **cheap uploads that cost a lot**: a 1,900-blob mask (every blob ~60 pixels with
   depth) in one view; the status, the time to answer, and the error code, at the
   default limits (``max_segments`` 500) and at the former default ``max_segments`` 2000;
3. (run last) **shutdown**: SIGTERM while a long request runs; what its client gets and when;
4. **memory**: eight concurrent 120 MiB uploads; resident memory of the main process
   (psutil, sampled every 20 ms) before, at peak and after;
5. **archives**: a valid bundle zipped with a 400 MiB member the manifest does not name;
   the status, and the peak resident memory of the worker processes meanwhile;
6. **small uploads that would exhaust memory**: a checkerboard mask of one id (a million
   one-pixel runs), a point-segment npz declaring 20 M points, 16 nearly empty 4096 x 4096
   views; then corrupt deflate data and numbers that overflow (``fx = 1e308``, ``depth.scale
   = 1e-30``, a pose 1e300 away): each one's status, error code, time to answer and the
   worker's growth in peak resident memory.

    .venv/bin/python benchmarks/bench_faults.py
    .venv/bin/python benchmarks/bench_faults.py --workers 2 --skip memory

Figures depend on the machine and on what else runs on it (wall-clock latencies
especially); memory figures do not.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import socket
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests import hostile  # noqa: E402
from tests.harness import ServerProcess, add_zeros_member, zip_files, zipped_bundle  # noqa: E402

MiB = 1024 * 1024
SAMPLE_DIR = ROOT / "examples" / "ue_sample"


# --------------------------------------------------------------------------- helpers
def tiny_scene() -> tuple[bytes, dict, dict[str, bytes]]:
    from shadowcorr_service.synthetic import synthetic_bundle

    return zipped_bundle(synthetic_bundle(n_rocks=3, n_views=3))


def read_status(sock: socket.socket) -> tuple[int | None, str]:
    """(status, error code) of the response on ``sock``, read until the server closes it."""
    data = b""
    try:
        while chunk := sock.recv(65536):
            data += chunk
    except OSError:
        pass
    if not data:
        return None, "(closed without an answer)"
    head, _, body = data.partition(b"\r\n\r\n")
    try:
        code = json.loads(body).get("error", "?")
    except ValueError:
        code = f"(not JSON: {body[:40]!r})"
    return int(head.split()[1]), code


def stalled_upload(port: int, declared: int = 1_000_000, sent: int = 100) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=120)
    sock.sendall(b"POST /correspond HTTP/1.1\r\nHost: x\r\nContent-Type: application/zip\r\n"
                 b"Content-Length: %d\r\n\r\n" % declared + b"x" * sent)
    return sock


def latencies(url: str, body: bytes, n: int) -> tuple[list[float], list[int]]:
    times, statuses = [], []
    with httpx.Client(timeout=300) as c:
        for _ in range(n):
            t0 = time.perf_counter()
            r = c.post(url + "/correspond", files={"bundle": ("s.zip", body)})
            times.append(time.perf_counter() - t0)
            statuses.append(r.status_code)
    return times, statuses


def fmt_ms(times: list[float]) -> str:
    return f"p50 {statistics.median(times) * 1e3:.0f} ms, max {max(times) * 1e3:.0f} ms"


class RssSampler:
    """Peak resident memory of some processes, sampled in a thread."""

    def __init__(self, processes: Callable[[], list[Any]], period_s: float = 0.02) -> None:
        self.processes, self.period_s = processes, period_s
        self.peak = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        import psutil

        while not self._stop.is_set():
            total = 0
            for p in self.processes():
                try:
                    total += p.memory_info().rss
                except psutil.Error:
                    pass
            self.peak = max(self.peak, total)
            time.sleep(self.period_s)

    def __enter__(self) -> "RssSampler":
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def rss(pid: int) -> int:
    import psutil

    return psutil.Process(pid).memory_info().rss


# --------------------------------------------------------------------------- the five items
def bench_stalled(server: ServerProcess, body: bytes, n: int) -> None:
    print("\n[1] 32 stalled uploads (declare 1 MB, send 100 bytes)")
    base, _ = latencies(server.url, body, n)
    print(f"  valid requests, nothing else open:        {fmt_ms(base)}")
    t_open = time.monotonic()
    stalled = [stalled_upload(server.port) for _ in range(32)]
    during, statuses = latencies(server.url, body, n)
    print(f"  valid requests, 32 stalled uploads open:  {fmt_ms(during)}, statuses {sorted(set(statuses))}")
    answers = [read_status(s) for s in stalled]
    closed_after = time.monotonic() - t_open
    for s in stalled:
        s.close()
    kinds = sorted({f"{st} {code}" for st, code in answers})
    print(f"  stalled uploads answered {kinds} within {closed_after:.1f} s of opening")

    t0 = time.monotonic()
    sock = socket.create_connection(("127.0.0.1", server.port), timeout=60)
    request = b"GET /health HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"z" * 60
    try:
        for byte in request:
            sock.sendall(bytes([byte]))
            time.sleep(1.0)
            sock.setblocking(False)
            try:
                if sock.recv(1, socket.MSG_PEEK):
                    break
            except BlockingIOError:
                pass
            finally:
                sock.setblocking(True)
    except OSError:
        pass
    status, code = read_status(sock)
    sock.close()
    print(f"  slow loris (1 header byte/s): answered {status} {code}, closed after {time.monotonic() - t0:.1f} s")


def confetti_scene(n_blobs: int = 1900) -> bytes:
    """One view whose mask holds ``n_blobs`` separate ~60-pixel blobs, all with valid depth."""
    from shadowcorr_service.synthetic import synthetic_bundle

    bundle = synthetic_bundle(n_rocks=3, n_views=3, width=640, height=480)
    view = bundle.views[0]
    mask = np.zeros(view.mask.shape, np.int32)
    side = 8  # 8 x 8 squares on a 10-pixel grid: 64 pixels each
    cols = view.mask.shape[1] // 10
    for i in range(n_blobs):
        r, c = divmod(i, cols)
        mask[r * 10:r * 10 + side, c * 10:c * 10 + side] = i + 1
    depth = np.where(mask > 0, 500.0, view.depth).astype(np.float32)
    bundle.views[0] = dataclasses.replace(view, mask=mask, depth=depth)
    return zipped_bundle(bundle)[0]


def bench_costly(server: ServerProcess, other_limit_server: ServerProcess | None) -> None:
    print("\n[2] a cheap upload that costs a lot: 1,900 blobs of 64 pixels in one view")
    body = confetti_scene()
    print(f"  upload size {len(body) / 1e6:.2f} MB")
    for label, srv in (("default limits", server), ("max_segments 2000 (former default)", other_limit_server)):
        if srv is None:
            continue
        t0 = time.perf_counter()
        r = httpx.post(srv.url + "/correspond", files={"bundle": ("c.zip", body)}, timeout=600)
        code = r.json().get("error", "") if r.status_code != 200 else f"{len(r.json()['segments'])} segments"
        print(f"  {label}: {r.status_code} {code} after {time.perf_counter() - t0:.1f} s")


def bench_memory(server: ServerProcess, n: int, size: int) -> None:
    print(f"\n[4] {n} concurrent uploads of {size / MiB:.0f} MiB (random bytes as application/zip)")
    payload = os.urandom(size)
    before = rss(server.pid)
    statuses: list[int] = []

    def post() -> None:
        with httpx.Client(timeout=600) as c:
            statuses.append(c.post(server.url + "/correspond", content=payload,
                                   headers={"Content-Type": "application/zip"}).status_code)

    import psutil

    main = psutil.Process(server.pid)
    with RssSampler(lambda: [main]) as sampler:
        threads = [threading.Thread(target=post) for _ in range(n)]
        t0 = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        took = time.perf_counter() - t0
    time.sleep(1.0)
    after = rss(server.pid)
    print(f"  statuses {sorted(statuses)} in {took:.1f} s")
    print(f"  main process RSS: before {before / MiB:.0f} MiB, peak {sampler.peak / MiB:.0f} MiB, "
          f"1 s after {after / MiB:.0f} MiB")


def bench_archive(server: ServerProcess, tiny: tuple[bytes, dict, dict[str, bytes]], unnamed_mib: int) -> None:
    print(f"\n[5] a valid bundle zipped with a {unnamed_mib} MiB member the manifest does not name")
    zipped, _, _ = tiny
    body = add_zeros_member(zipped, unnamed_mib, "extra/padding.bin")
    workers = server.worker_processes()
    base = sum(p.memory_info().rss for p in workers)
    with RssSampler(lambda: workers) as sampler:
        t0 = time.perf_counter()
        r = httpx.post(server.url + "/correspond", files={"bundle": ("s.zip", body)}, timeout=600)
        took = time.perf_counter() - t0
    warn = [w for w in r.json().get("warnings", []) if "padding" in w]
    print(f"  upload {len(body) / 1e6:.2f} MB ({unnamed_mib * MiB / len(body):.0f}:1): {r.status_code} in {took:.1f} s; "
          f"warning: {warn[0] if warn else '(none)'}")
    print(f"  worker processes RSS: before {base / MiB:.0f} MiB, peak {sampler.peak / MiB:.0f} MiB "
          f"(+{(sampler.peak - base) / MiB:.0f} MiB)")


def bench_hostile(server: ServerProcess, tiny: tuple[bytes, dict, dict[str, bytes]]) -> None:
    print("\n[6] small uploads that would cost gigabytes, corrupt data and overflowing numbers (one worker's memory)")
    zipped, manifest, files = tiny

    def overflowing(change: Callable[[dict], None]) -> Callable[[], tuple[bytes, str]]:
        def build() -> tuple[bytes, str]:
            m = json.loads(json.dumps(manifest))
            change(m)
            return zip_files({"manifest.json": json.dumps(m).encode(), **files}), "application/zip"
        return build

    cases: list[tuple[str, Callable[[], tuple[bytes, str]]]] = [
        ("checkerboard mask, 1920x1080, one id", hostile.checkerboard_mask_bundle),
        ("point-segment npz of 20 M points", hostile.huge_point_npz_bundle),
        ("16 views of 4096x4096, nearly empty", hostile.many_empty_pixels_bundle),
        ("corrupt deflate data in a member", hostile.corrupt_deflate_bundle),
        ("intrinsics.fx = 1e308", overflowing(lambda m: m["views"][0]["intrinsics"].update(fx=1e308))),
        ("depth.scale = 1e-30", overflowing(lambda m: m["views"][0]["depth"].update(scale=1e-30))),
        ("pose translated by 1e300", overflowing(lambda m: m["views"][0]["pose"]["matrix"][0].__setitem__(3, 1e300))),
    ]
    for label, build in cases:
        body, content_type = build()
        (worker,) = server.worker_processes()
        t0 = time.perf_counter()
        r, growth = hostile.peak_memory_growth(worker.pid, lambda: httpx.post(
            server.url + "/correspond", content=body, headers={"Content-Type": content_type}, timeout=600))
        took = time.perf_counter() - t0
        code = r.json().get("error", "") if r.status_code != 200 else "labelled"
        print(f"  {label:<40} upload {len(body) / 1e3:8.1f} kB: {r.status_code} {code:<16} after {took:5.2f} s, "
              f"worker peak +{growth / MiB:.0f} MiB")


def bench_shutdown(server: ServerProcess, grace_s: float) -> None:
    print(f"\n[3] SIGTERM while a long request runs (graceful_shutdown_s {grace_s:g})")
    if not SAMPLE_DIR.is_dir():
        print("  (skipped: no sample scene)")
        return
    from shadowcorr.convert.ue import load_ue_scene
    from shadowcorr.io import bundle_to_parts

    bundle = load_ue_scene(SAMPLE_DIR, 2001, range(8))
    bundle.views += [dataclasses.replace(v, name=v.name + "_again") for v in bundle.views]
    manifest, files = bundle_to_parts(bundle)
    parts = [("manifest", (None, json.dumps(manifest).encode()))] + [("f", (k, v)) for k, v in files.items()]
    result: dict = {}

    def post() -> None:
        result["r"] = httpx.post(server.url + "/correspond", files=parts, timeout=300)
        result["t"] = time.monotonic()

    t = threading.Thread(target=post)
    t.start()
    time.sleep(1.0)
    sent = time.monotonic()
    server.proc.send_signal(signal.SIGTERM)
    t.join(300)
    r = result["r"]
    print(f"  client got {r.status_code} {r.headers.get('content-type')} Retry-After={r.headers.get('retry-after')} "
          f"{r.text[:120]} ... {result['t'] - sent:.1f} s after SIGTERM")
    print(f"  server exit status {server.proc.wait(120)}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--requests", type=int, default=5, help="valid requests per latency measurement")
    p.add_argument("--uploads", type=int, default=8, help="concurrent large uploads (item 4)")
    p.add_argument("--upload-mib", type=int, default=120)
    p.add_argument("--unnamed-mib", type=int, default=400, help="size of the unnamed archive member (item 5)")
    p.add_argument("--skip", default="",
                   help="comma-separated items to skip: stalled,costly,memory,archive,hostile,shutdown")
    args = p.parse_args()
    skip = set(filter(None, args.skip.split(",")))
    grace = 2.0
    tiny = tiny_scene()
    server = ServerProcess(["--workers", str(args.workers), "--graceful-shutdown-s", str(grace)]).start()
    former = None
    try:
        print(f"server pid {server.pid} at {server.url}, {args.workers} workers, default limits; "
              f"main process RSS {rss(server.pid) / MiB:.0f} MiB")
        if "stalled" not in skip:
            bench_stalled(server, tiny[0], args.requests)
        if "costly" not in skip:
            former = ServerProcess(["--workers", "1", "--max-segments", "2000"]).start()
            bench_costly(server, former)
        if "memory" not in skip:
            bench_memory(server, args.uploads, args.upload_mib * MiB)
        if "archive" not in skip:
            bench_archive(server, tiny, args.unnamed_mib)
        if "hostile" not in skip:
            hostile_server = ServerProcess(["--workers", "1"]).start()
            try:
                bench_hostile(hostile_server, tiny)
            finally:
                hostile_server.stop()
        if "shutdown" not in skip:
            bench_shutdown(server, grace)
    finally:
        if former is not None:
            former.stop()
        server.stop()


if __name__ == "__main__":
    main()
