"""Load test of the HTTP service: latency, throughput and batching under N concurrent clients.

Starts a server (``python -m shadowcorr_service``) or uses a running one (``--url``), then for each
client count N (default 1, 4, 16) runs N concurrent clients that each send the same
scene ``--requests`` times, back to back.  Prints per N: p50 / p95 / max latency,
throughput (scenes/s), mean network batch size (from ``/metrics``), the latency of
``/health`` probed during the load, and errors (non-200 answers, or labels that differ
from the first answer).  When it started the server itself it also prints the CPU
seconds the server and its workers spent per scene: on a shared machine wall-clock
figures depend on what else runs, CPU per scene does not, and ``cores / CPU per
scene`` bounds the throughput of an idle machine.

    .venv/bin/python benchmarks/bench_service.py                       # sample scene, 2 workers
    .venv/bin/python benchmarks/bench_service.py --clients 1,4,16 --requests 4 --workers 2
    .venv/bin/python benchmarks/bench_service.py --url http://127.0.0.1:8000 --token "$TOKEN"

The default scene is the real sample (set 2001, cameras 0, 2, 4, 6) from
``examples/ue_sample`` (or ``../shared/data/ue_sample``); ``--scene PATH`` sends any bundle archive, ``--synthetic``
a small analytic scene.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import httpx
from prometheus_client.parser import text_string_to_metric_families

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.harness import ServerProcess  # noqa: E402

SAMPLE_DIR = next(
    (d for d in (ROOT / "examples" / "ue_sample", ROOT.parent / "shared" / "data" / "ue_sample") if d.is_dir()),
    ROOT / "examples" / "ue_sample",
)


def build_scene(args: argparse.Namespace) -> tuple[bytes, str]:
    """The archive to send, and a description of it."""
    if args.scene:
        return Path(args.scene).read_bytes(), str(args.scene)
    from shadowcorr.io import write_bundle_archive

    if args.synthetic or not SAMPLE_DIR.is_dir():
        from shadowcorr_service.synthetic import synthetic_bundle

        bundle, what = synthetic_bundle(n_rocks=4, n_views=3, width=200, height=150), "synthetic 4 rocks x 3 views"
    else:
        from shadowcorr.convert.ue import load_ue_scene

        bundle, what = load_ue_scene(SAMPLE_DIR, 2001, (0, 2, 4, 6)), "ue sample set 2001, cameras 0,2,4,6"
    with tempfile.TemporaryDirectory() as tmp:
        path = write_bundle_archive(bundle, Path(tmp) / "scene.zip")
        return path.read_bytes(), what


def batch_totals(client: httpx.Client) -> tuple[float, float]:
    """(sum of batch sizes, number of batches) so far."""
    text = client.get("/metrics").text
    total = count = 0.0
    for fam in text_string_to_metric_families(text):
        if fam.name == "shadowcorr_batch_size":
            for s in fam.samples:
                if s.name.endswith("_sum"):
                    total = s.value
                elif s.name.endswith("_count"):
                    count = s.value
    return total, count


def server_cpu_s(server: ServerProcess | None) -> float | None:
    """CPU seconds (user + system) of the server process and all its children so far."""
    if server is None:
        return None
    try:
        import psutil
    except ImportError:
        return None
    main = psutil.Process(server.pid)
    total = 0.0
    for p in [main, *main.children(recursive=True)]:
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.Error:
            pass
    return total


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    values = sorted(values)
    k = (len(values) - 1) * q
    lo, hi = int(k), min(int(k) + 1, len(values) - 1)
    return values[lo] + (values[hi] - values[lo]) * (k - lo)


async def run_level(url: str, headers: dict, scene: bytes, clients: int, requests: int, reference: list | None):
    latencies: list[float] = []
    health: list[float] = []
    errors: list[str] = []
    done = asyncio.Event()
    limits = httpx.Limits(max_connections=clients + 2)
    async with httpx.AsyncClient(base_url=url, headers=headers, timeout=600.0, limits=limits) as ac:

        async def one_client() -> None:
            for _ in range(requests):
                t0 = time.perf_counter()
                try:
                    r = await ac.post("/correspond", files={"bundle": ("scene.zip", scene)})
                except httpx.HTTPError as e:
                    errors.append(f"{type(e).__name__}: {e}")
                    continue
                dt = time.perf_counter() - t0
                if r.status_code != 200:
                    errors.append(f"{r.status_code}: {r.text[:200]}")
                    continue
                labels = [s["object"] for s in r.json()["segments"]]
                if reference is not None and labels != reference:
                    errors.append("labels differ from the first answer")
                latencies.append(dt)

        async def probe_health() -> None:
            while not done.is_set():
                t0 = time.perf_counter()
                await ac.get("/health")
                health.append(time.perf_counter() - t0)
                await asyncio.sleep(0.1)

        prober = asyncio.create_task(probe_health())
        t0 = time.perf_counter()
        await asyncio.gather(*(one_client() for _ in range(clients)))
        wall = time.perf_counter() - t0
        done.set()
        await prober
    return latencies, errors, wall, health


def _load_average() -> str:
    try:
        import os

        return " ".join(f"{x:.1f}" for x in os.getloadavg())
    except (OSError, AttributeError):
        return ""


def _cores() -> int:
    import os

    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--url", help="use this running server instead of starting one")
    p.add_argument("--token", help="bearer token of the server at --url")
    p.add_argument("--clients", default="1,4,16", help="comma-separated concurrent client counts")
    p.add_argument("--requests", type=int, default=3, help="requests per client per level")
    p.add_argument("--scene", help="bundle archive (.zip/.tar) to send")
    p.add_argument("--synthetic", action="store_true", help="send a small synthetic scene")
    p.add_argument("--workers", type=int, default=2, help="started server: worker processes")
    p.add_argument("--max-batch-size", type=int, default=8, help="started server: batch size")
    p.add_argument("--max-wait-ms", type=float, default=10.0, help="started server: batching window")
    p.add_argument("--server-arg", action="append", default=[], help="extra flag for the started server (repeat)")
    p.add_argument("--json", help="also write the results here as JSON")
    args = p.parse_args(argv)

    scene, what = build_scene(args)
    server = None
    if args.url:
        url, headers = args.url.rstrip("/"), ({"Authorization": f"Bearer {args.token}"} if args.token else {})
    else:
        server = ServerProcess(
            ["--workers", str(args.workers), "--max-batch-size", str(args.max_batch_size),
             "--max-wait-ms", str(args.max_wait_ms), "--queue-size", "256", "--request-timeout-s", "600",
             *args.server_arg]
        )
        t0 = time.perf_counter()
        server.start()
        print(f"server started and warmed up in {time.perf_counter() - t0:.1f} s ({server.url})")
        url, headers = server.url, {}
    try:
        with httpx.Client(base_url=url, headers=headers, timeout=600.0) as c:
            info = c.get("/info").json()
            settings = info.get("settings", {})
            print(f"scene: {what} ({len(scene) / 1e6:.1f} MB); workers {settings.get('workers')}, "
                  f"max_batch_size {settings.get('max_batch_size')}, max_wait_ms {settings.get('max_wait_ms')}")
            first = c.post("/correspond", files={"bundle": ("scene.zip", scene)})  # also warms the caches
            if first.status_code != 200:
                print(f"the scene is refused: {first.status_code} {first.text[:500]}")
                return 1
            reference = [s["object"] for s in first.json()["segments"]]
            print(f"{'N':>3} {'reqs':>5} {'p50 s':>7} {'p95 s':>7} {'max s':>7} {'scenes/s':>9} {'batch':>6} "
                  f"{'health p50/max ms':>18} {'errors':>6} {'cpu s/scene':>11}")
            rows = []
            for n in [int(x) for x in args.clients.split(",") if x.strip()]:
                s0, c0 = batch_totals(c)
                cpu0 = server_cpu_s(server)
                lat, errors, wall, health = asyncio.run(run_level(url, headers, scene, n, args.requests, reference))
                cpu1 = server_cpu_s(server)
                s1, c1 = batch_totals(c)
                cpu_per_scene = (cpu1 - cpu0) / max(len(lat), 1) if cpu0 is not None and cpu1 is not None else None
                mean_batch = (s1 - s0) / (c1 - c0) if c1 > c0 else float("nan")
                row = {
                    "clients": n,
                    "requests": n * args.requests,
                    "p50_s": pct(lat, 0.5),
                    "p95_s": pct(lat, 0.95),
                    "max_s": max(lat) if lat else float("nan"),
                    "throughput_scenes_per_s": len(lat) / wall,
                    "mean_batch_size": mean_batch,
                    "health_p50_ms": 1e3 * statistics.median(health) if health else float("nan"),
                    "health_max_ms": 1e3 * max(health) if health else float("nan"),
                    "errors": len(errors),
                    "server_cpu_s_per_scene": cpu_per_scene,
                }
                rows.append(row)
                print(f"{n:>3} {row['requests']:>5} {row['p50_s']:>7.2f} {row['p95_s']:>7.2f} {row['max_s']:>7.2f} "
                      f"{row['throughput_scenes_per_s']:>9.2f} {mean_batch:>6.2f} "
                      f"{row['health_p50_ms']:>8.1f}/{row['health_max_ms']:<9.1f} {len(errors):>6} "
                      f"{cpu_per_scene if cpu_per_scene is not None else float('nan'):>11.2f}")
                for e in errors[:5]:
                    print(f"      error: {e}")
            load = _load_average()
            if load:
                print(f"load average at the end: {load} on {_cores()} cores (other processes share them)")
            if args.json:
                Path(args.json).write_text(json.dumps({"scene": what, "settings": settings, "rows": rows}, indent=1))
    finally:
        if server is not None:
            server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
