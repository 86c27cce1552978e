"""The results file of a dataset upload: one JSON line per scene attempt, and its summary.

Each line is ``{"scene", "status": "ok"|"failed", "result" | "error", "latency_ms", "source"}``.
The file is only ever appended to, one complete line per ``write`` + ``flush``, so an
interrupted upload (Ctrl-C, a killed process) leaves every finished scene on record and
at worst one torn last line, which :func:`read_records` skips and
:class:`RecordWriter` terminates before appending.  Resuming means: skip the scenes
whose *latest* line says ``ok``; a failed scene is tried again and its new line
supersedes the old one.
"""

from __future__ import annotations

import json
import math
import os
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Iterable, Mapping, Sequence

__all__ = [
    "UploadRecord",
    "RecordWriter",
    "read_records",
    "percentile",
    "UploadSummary",
    "summarize_records",
    "format_summary",
    "SUMMARY_METRICS",
    "format_metrics",
]

#: Result metrics shown in the summary (keys of ``Result.metrics``) -> (label, decimals).
SUMMARY_METRICS = {"average_purity": ("average purity", 2), "rock_purity": ("rock purity", 2),
                   "cluster_purity": ("cluster purity", 2), "voxel_ari": ("voxel ARI", 4), "coverage": ("coverage %", 1)}


def format_metrics(metrics: Mapping[str, Any]) -> str:
    """One line of a result's quality metrics: ``average purity 100.00  ...  voxel ARI 0.9947  coverage % 100.0``."""
    return "  ".join(f"{label} {metrics[key]:.{digits}f}" for key, (label, digits) in SUMMARY_METRICS.items()
                     if isinstance(metrics.get(key), (int, float)))


@dataclass
class UploadRecord:
    """The outcome of sending one scene."""

    scene: str
    status: str  # "ok" | "failed"
    latency_ms: float | None = None
    result: dict[str, Any] | None = None
    error: dict[str, Any] | None = None
    source: str | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def to_json(self) -> str:
        data: dict[str, Any] = {"scene": self.scene, "status": self.status}
        if self.ok:
            data["result"] = self.result
        else:
            data["error"] = self.error
        data["latency_ms"] = None if self.latency_ms is None else round(self.latency_ms, 1)
        if self.source is not None:
            data["source"] = self.source
        return json.dumps(data, separators=(",", ":"), allow_nan=False)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "UploadRecord":
        if not isinstance(data.get("scene"), str) or data.get("status") not in ("ok", "failed"):
            raise ValueError("not an upload record")
        return cls(scene=data["scene"], status=data["status"], latency_ms=data.get("latency_ms"),
                   result=data.get("result"), error=data.get("error"), source=data.get("source"))


def read_records(path: str | os.PathLike[str]) -> tuple[dict[str, UploadRecord], int]:
    """Latest record per scene in a results file, and the number of unreadable lines skipped.

    A missing file is an empty one (a first run).
    """
    latest: dict[str, UploadRecord] = {}
    bad = 0
    p = Path(path)
    if not p.exists():
        return latest, 0
    with open(p, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if not line.strip():
                continue
            try:
                record = UploadRecord.from_dict(json.loads(line))
            except (ValueError, TypeError, AttributeError):  # a torn last line, or a foreign file
                bad += 1
                continue
            latest[record.scene] = record
    return latest, bad


class RecordWriter:
    """Appends records to a results file, one flushed line each."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: IO[str] = open(self.path, "a+", encoding="utf-8")
        # A run killed mid-write leaves a line without its newline: end it, or the next
        # record would be glued to it and both would be lost.
        self._fh.seek(0, os.SEEK_END)
        if self._fh.tell() > 0:
            self._fh.seek(self._fh.tell() - 1)
            if self._fh.read(1) != "\n":
                self._fh.write("\n")
        self._fh.seek(0, os.SEEK_END)

    def write(self, record: UploadRecord) -> None:
        self._fh.write(record.to_json() + "\n")
        self._fh.flush()

    def close(self) -> None:
        self._fh.close()

    def __enter__(self) -> "RecordWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def percentile(values: Sequence[float], q: float) -> float:
    """The ``q``-th percentile (0-100) with linear interpolation (numpy's default); NaN if empty."""
    data = sorted(v for v in values if v is not None and math.isfinite(v))
    if not data:
        return math.nan
    pos = (len(data) - 1) * q / 100.0
    lo, hi = math.floor(pos), math.ceil(pos)
    return data[lo] + (data[hi] - data[lo]) * (pos - lo)


def _mean_std(values: Iterable[Any]) -> tuple[float, float, int]:
    # Population std (ddof=0) with NaN skipped: the same definition as shadowcorr.evaluation.summarize.
    vals = [float(v) for v in values if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)]
    if not vals:
        return math.nan, math.nan, 0
    return statistics.fmean(vals), statistics.pstdev(vals), len(vals)


@dataclass
class UploadSummary:
    """Figures printed at the end of an upload."""

    scenes: int  # scenes found in the dataset
    skipped: int  # already "ok" in the results file: not sent again
    sent: int  # scenes attempted in this run
    ok: int  # successes in this run
    failed: int  # failures in this run
    pending: int  # neither done before nor attempted now (--limit, interruption)
    latency_p50_ms: float
    latency_p95_ms: float
    wall_s: float
    metrics: dict[str, tuple[float, float, int]] = field(default_factory=dict)  # name -> (mean, std, n)
    failures: list[tuple[str, str]] = field(default_factory=list)  # (scene, error message)


def summarize_records(
    scene_names: Sequence[str],
    skipped: int,
    run_records: Sequence[UploadRecord],
    all_latest: Mapping[str, UploadRecord],
    wall_s: float,
) -> UploadSummary:
    """Summary of a run (``run_records``) over a dataset whose latest records are ``all_latest``.

    Latency figures cover this run's successful requests; quality metrics cover every
    scene of the dataset whose latest record is ``ok`` (earlier runs included), so a
    resumed upload still reports the whole dataset.
    """
    names = set(scene_names)
    ok_now = [r for r in run_records if r.ok]
    failed_now = [r for r in run_records if not r.ok]
    latencies = [r.latency_ms for r in ok_now if r.latency_ms is not None]
    results = [r.result for n, r in all_latest.items() if n in names and r.ok and r.result]
    metrics = {}
    for key in SUMMARY_METRICS:
        mean, std, n = _mean_std((res.get("metrics") or {}).get(key) for res in results)
        if n:
            metrics[key] = (mean, std, n)
    attempted = {r.scene for r in run_records}
    done = {n for n, r in all_latest.items() if n in names and r.ok}
    failures = [(r.scene, str((r.error or {}).get("message") or r.error)) for r in failed_now]
    return UploadSummary(
        scenes=len(names), skipped=skipped, sent=len(run_records), ok=len(ok_now), failed=len(failed_now),
        pending=len(names - attempted - done), latency_p50_ms=percentile(latencies, 50),
        latency_p95_ms=percentile(latencies, 95), wall_s=wall_s, metrics=metrics, failures=failures,
    )


def format_summary(s: UploadSummary) -> str:
    """The summary as an aligned text table."""

    def ms(v: float) -> str:
        return "-" if math.isnan(v) else f"{v:,.0f} ms"

    rate = s.sent / s.wall_s if s.wall_s > 0 else math.nan
    rows = [
        ("scenes", f"{s.scenes}"),
        ("already done (skipped)", f"{s.skipped}"),
        ("sent this run", f"{s.sent}" + (f"  ({rate:.2f} scenes/s)" if s.sent and math.isfinite(rate) else "")),
        ("ok", f"{s.ok}"),
        ("failed", f"{s.failed}"),
    ]
    if s.pending:
        rows.append(("not yet sent", f"{s.pending}"))
    rows += [("latency p50", ms(s.latency_p50_ms)), ("latency p95", ms(s.latency_p95_ms))]
    for key, (mean, std, n) in s.metrics.items():
        label, digits = SUMMARY_METRICS.get(key, (key.replace("_", " "), 2))
        rows.append((label, f"{mean:.{digits}f} ± {std:.{digits}f}  (n={n})"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
