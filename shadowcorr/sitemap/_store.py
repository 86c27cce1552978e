"""The map file: one SQLite database (standard library), write-ahead log, one transaction per update.

Tables (lengths in the map's units, poses camera-to-world in the OpenCV optical frame)::

    meta       key -> value: format version, the map's configuration, the model it was made with
    scans      one row per update: name, time, views and segments added
    views      per view its pose (as registered with the map) and the pose its scan declared,
               intrinsics, image size and its summary: depth every ``stride``-th pixel (the
               pixel at stride * i + stride // 2), the segment-index image every
               ``labels_stride``-th pixel (1: every pixel; a window of the frame), depth and
               mask (rock or not) on the pose stage's sampling grid (every ``grid_stride``-th
               pixel, float32), and the footprint (bounding box of its segments' points)
    view_cells the footprint's cells (cube of CELL_SIZE voxels): which views may see a place
    segments   per segment its view, mask id, blob, the blob a depth step cut it from (-1: none),
               current object, support and evidence margin, centroid and its points averaged on
               the downsampling grid
    objects    every id ever given, the scan that created it and, once retired, when and into which
    events     the history: created, observed, merged, split, retired, with scan, views, segments

Arrays are stored as raw bytes beside their dtype and shape (``np.frombuffer``; images are zlib
compressed), never pickled: a map file is data, whoever wrote it.  Writers take SQLite's write
lock for the whole update (``BEGIN IMMEDIATE``): a second writer is refused with
:class:`MapBusyError` at once, readers keep reading the last committed state, and a writer killed
mid-update leaves only an uncommitted transaction, which SQLite rolls back when the file is next
opened.
"""

from __future__ import annotations

import json
import sqlite3
import time
import zlib
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

__all__ = ["FORMAT_VERSION", "MapBusyError", "MapConflictError", "MapFileError", "MapStore", "pack_array",
           "unpack_array"]

FORMAT_VERSION = "4"
#: Formats this version opens, upgrading them on opening: format 2 kept a view's segment image on
#: its depth's grid (read back as written); format 3 adds ``labels_stride`` (1: every pixel); format 4
#: adds each segment's ``cut`` (the blob a depth step cut it from, -1: none; -1 for older segments).
_UPGRADABLE = frozenset({"2", "3"})
#: Footprint cells are cubes of this many voxels: a view's footprint spans a few of them.
CELL_VOXELS = 64
_CELL_BITS = 21
_CELL_OFFSET = 1 << (_CELL_BITS - 1)
#: dtypes an array column may declare; anything else in a file is refused, not interpreted.
_DTYPES = frozenset({"float16", "float32", "float64", "int16", "int32", "int64", "uint8", "uint16"})

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE scans (
    scan INTEGER PRIMARY KEY, name TEXT NOT NULL, added_at REAL NOT NULL,
    num_views INTEGER NOT NULL, num_segments INTEGER NOT NULL, model TEXT);
CREATE TABLE views (
    view INTEGER PRIMARY KEY, scan INTEGER NOT NULL REFERENCES scans, name TEXT NOT NULL,
    pose BLOB NOT NULL, declared BLOB NOT NULL,
    fx REAL NOT NULL, fy REAL NOT NULL, cx REAL NOT NULL, cy REAL NOT NULL,
    width INTEGER NOT NULL, height INTEGER NOT NULL, stride INTEGER NOT NULL,
    depth BLOB NOT NULL, depth_dtype TEXT NOT NULL, depth_shape TEXT NOT NULL,
    labels BLOB NOT NULL, labels_dtype TEXT NOT NULL, labels_shape TEXT NOT NULL,
    labels_top INTEGER NOT NULL, labels_left INTEGER NOT NULL, labels_stride INTEGER NOT NULL,
    grid_stride INTEGER NOT NULL, grid_depth BLOB NOT NULL, grid_depth_dtype TEXT NOT NULL,
    grid_depth_shape TEXT NOT NULL, grid_mask BLOB NOT NULL, grid_mask_dtype TEXT NOT NULL,
    grid_mask_shape TEXT NOT NULL,
    lo_x REAL, lo_y REAL, lo_z REAL, hi_x REAL, hi_y REAL, hi_z REAL,
    UNIQUE (scan, name));
CREATE TABLE view_cells (cell INTEGER NOT NULL, view INTEGER NOT NULL REFERENCES views,
    PRIMARY KEY (cell, view)) WITHOUT ROWID;
CREATE TABLE objects (
    object INTEGER PRIMARY KEY, created_scan INTEGER NOT NULL, retired_scan INTEGER, retired_into INTEGER);
CREATE TABLE segments (
    segment INTEGER PRIMARY KEY, scan INTEGER NOT NULL, view INTEGER NOT NULL REFERENCES views,
    local INTEGER NOT NULL, instance INTEGER NOT NULL, component INTEGER NOT NULL,
    num_pixels INTEGER NOT NULL, num_points INTEGER NOT NULL, cut INTEGER NOT NULL DEFAULT -1,
    object INTEGER NOT NULL REFERENCES objects, support REAL, margin REAL,
    cx REAL, cy REAL, cz REAL, lo_x REAL, lo_y REAL, lo_z REAL, hi_x REAL, hi_y REAL, hi_z REAL,
    points BLOB NOT NULL, points_dtype TEXT NOT NULL, points_shape TEXT NOT NULL);
CREATE INDEX segments_by_view ON segments (view, local);
CREATE INDEX segments_by_object ON segments (object);
CREATE TABLE events (
    event INTEGER PRIMARY KEY, scan INTEGER NOT NULL, kind TEXT NOT NULL, object INTEGER NOT NULL,
    into_object INTEGER, views TEXT NOT NULL, segments TEXT NOT NULL, moved TEXT NOT NULL, margin REAL);
CREATE INDEX events_by_scan ON events (scan);
"""


class MapFileError(ValueError):
    """The file is not a site map this version can read (or not a database at all)."""


class MapBusyError(RuntimeError):
    """Another writer is updating the map; try again when it has finished."""


class MapConflictError(RuntimeError):
    """The map changed between preparing an update and committing it; prepare it again."""


def pack_array(array: np.ndarray, compress: bool = False) -> tuple[bytes, str, str]:
    """(bytes, dtype, shape) of an array, little-endian C order; zlib-compressed when ``compress``."""
    a = np.ascontiguousarray(array)
    if a.dtype.name not in _DTYPES:
        raise TypeError(f"cannot store arrays of dtype {a.dtype}")
    data = a.astype(a.dtype.newbyteorder("<"), copy=False).tobytes()
    return (zlib.compress(data, 1) if compress else data), a.dtype.name, ",".join(map(str, a.shape))


def unpack_array(data: bytes, dtype: str, shape: str, compressed: bool = False) -> np.ndarray:
    """The array :func:`pack_array` stored (a read-only view of the bytes where not compressed)."""
    if dtype not in _DTYPES:
        raise MapFileError(f"the map file declares an array of dtype {dtype!r}")
    dims = tuple(int(d) for d in shape.split(",") if d != "")
    raw = zlib.decompress(data) if compressed else data
    dt = np.dtype(dtype).newbyteorder("<")
    if len(raw) != int(np.prod(dims, dtype=np.int64)) * dt.itemsize:
        raise MapFileError(f"an array of the map file holds {len(raw)} bytes, not {dims} of {dtype}")
    return np.frombuffer(raw, dtype=dt).reshape(dims)


def cell_keys(lo: np.ndarray, hi: np.ndarray, cell: float) -> np.ndarray:
    """Keys of the cubic cells of size ``cell`` that the box [lo, hi] touches."""
    a = np.floor(np.asarray(lo) / cell).astype(np.int64)
    b = np.floor(np.asarray(hi) / cell).astype(np.int64)
    axes = [np.arange(a[i], b[i] + 1) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3) + _CELL_OFFSET
    if grid.size and (grid.min() < 0 or grid.max() >= 1 << _CELL_BITS):
        raise ValueError("a view's footprint lies beyond the map's cell range; express poses in a local frame")
    return (grid[:, 0] << (2 * _CELL_BITS)) | (grid[:, 1] << _CELL_BITS) | grid[:, 2]


class MapStore:
    """One open map file (see the module docstring)."""

    def __init__(self, path: str | Path, *, create: bool = True, busy_timeout_s: float = 5.0) -> None:
        self.path = Path(path)
        exists = self.path.exists() and self.path.stat().st_size > 0
        if not exists and not create:
            raise FileNotFoundError(f"{self.path}: no such map")
        self.busy_timeout_s = busy_timeout_s
        # Autocommit mode: transactions are begun and ended explicitly below.
        self.db = sqlite3.connect(str(self.path), timeout=busy_timeout_s, isolation_level=None,
                                  check_same_thread=False)
        try:
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=FULL")
            self.db.execute("PRAGMA foreign_keys=ON")
            if not exists or not self._has_schema():
                self._create()
            self._check_format()
        except sqlite3.DatabaseError as e:
            self.db.close()
            raise MapFileError(f"{self.path}: not a site map ({e})") from None
        except Exception:
            self.db.close()
            raise

    # ------------------------------------------------------------------ set-up
    def _has_schema(self) -> bool:
        return self.db.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='meta'").fetchone() is not None

    def _create(self) -> None:
        with self.writing(wait_s=self.busy_timeout_s):
            if not self._has_schema():  # another process may have created it meanwhile
                for statement in filter(str.strip, _SCHEMA.split(";")):  # executescript would commit first
                    self.db.execute(statement)
                self.db.execute("INSERT INTO meta VALUES ('format', ?)", (FORMAT_VERSION,))

    def _check_format(self) -> None:
        version = self.meta("format")
        if version in _UPGRADABLE:
            self._upgrade()
            version = self.meta("format")
        if version != FORMAT_VERSION:
            raise MapFileError(f"{self.path}: map format {version!r}; this version reads {FORMAT_VERSION!r}")

    def _upgrade(self) -> None:
        """An older file made the current format in one transaction.  Format 2 -> 3: its views'
        segment images stay on their depth's grid (``labels_stride`` = ``stride``); views added later
        keep theirs at every pixel.  3 -> 4: its segments were cut from no blob they remember
        (``cut`` -1: a stored piece of a cut blob groups as a blob of its mask)."""
        with self.writing(wait_s=self.busy_timeout_s):
            version = self.meta("format")
            if version not in _UPGRADABLE:  # another process upgraded it meanwhile
                return
            if version == "2":
                self.db.execute("ALTER TABLE views ADD COLUMN labels_stride INTEGER NOT NULL DEFAULT 0")
                self.db.execute("UPDATE views SET labels_stride = stride")
            self.db.execute("ALTER TABLE segments ADD COLUMN cut INTEGER NOT NULL DEFAULT -1")
            self.set_meta("format", FORMAT_VERSION)

    def close(self) -> None:
        self.db.close()

    # ------------------------------------------------------------------ transactions
    @contextmanager
    def writing(self, wait_s: float = 0.0) -> Iterator[sqlite3.Connection]:
        """The write lock and one transaction: committed when the block ends, rolled back on an error.

        A second writer waits up to ``wait_s`` seconds, then gets :class:`MapBusyError`.
        """
        self.db.execute(f"PRAGMA busy_timeout={int(wait_s * 1000)}")
        try:
            self.db.execute("BEGIN IMMEDIATE")
        except sqlite3.OperationalError as e:
            if "locked" in str(e) or "busy" in str(e):
                raise MapBusyError(f"{self.path}: another writer is updating this map; try again when it has "
                                   "finished") from None
            raise
        finally:
            self.db.execute(f"PRAGMA busy_timeout={int(self.busy_timeout_s * 1000)}")
        try:
            yield self.db
        except BaseException:
            self.db.execute("ROLLBACK")
            raise
        self.db.execute("COMMIT")

    @contextmanager
    def reading(self) -> Iterator[sqlite3.Connection]:
        """One consistent snapshot for several reads (nested in a write, the write's own view)."""
        if self.db.in_transaction:
            yield self.db
            return
        self.db.execute("BEGIN")
        try:
            yield self.db
        finally:
            self.db.execute("COMMIT")

    # ------------------------------------------------------------------ meta
    def meta(self, key: str) -> str | None:
        row = self.db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else row[0]

    def set_meta(self, key: str, value: str) -> None:
        self.db.execute("INSERT INTO meta VALUES (?, ?) ON CONFLICT (key) DO UPDATE SET value = excluded.value",
                        (key, value))

    def last_scan(self) -> int:
        return int(self.db.execute("SELECT COALESCE(MAX(scan), 0) FROM scans").fetchone()[0])

    def next_object(self) -> int:
        return int(self.db.execute("SELECT COALESCE(MAX(object), -1) + 1 FROM objects").fetchone()[0])

    # ------------------------------------------------------------------ reads for linking
    def views_in_cells(self, keys: np.ndarray) -> list[int]:
        """Views whose footprint shares a cell with ``keys``."""
        found: set[int] = set()
        keys = np.unique(keys).tolist()
        for start in range(0, len(keys), 500):  # SQLite's bound-parameter limit
            chunk = keys[start:start + 500]
            marks = ",".join("?" * len(chunk))
            found.update(r[0] for r in self.db.execute(f"SELECT DISTINCT view FROM view_cells WHERE cell IN ({marks})",
                                                         chunk))
        return sorted(found)

    def view_rows(self, views: Sequence[int], with_images: bool = True) -> list[sqlite3.Row]:
        cols = "*" if with_images else ("view, scan, name, pose, declared, fx, fy, cx, cy, width, height, stride, "
                                        "lo_x, lo_y, lo_z, hi_x, hi_y, hi_z")
        return self._rows(f"SELECT {cols} FROM views WHERE view IN ({{}}) ORDER BY view", views)

    def segment_rows(self, views: Sequence[int], with_points: bool = True) -> list[sqlite3.Row]:
        cols = "*" if with_points else ("segment, scan, view, local, instance, component, num_pixels, num_points, "
                                        "cut, object, support, margin, cx, cy, cz")
        return self._rows(f"SELECT {cols} FROM segments WHERE view IN ({{}}) ORDER BY view, local", views)

    def _rows(self, query: str, ids: Sequence[int]) -> list[sqlite3.Row]:
        self.db.row_factory = sqlite3.Row
        try:
            out: list[sqlite3.Row] = []
            ids = list(ids)
            for start in range(0, len(ids), 500):
                chunk = ids[start:start + 500]
                out += self.db.execute(query.format(",".join("?" * len(chunk))), chunk).fetchall()
            return out
        finally:
            self.db.row_factory = None

    def object_sizes(self, objects: Sequence[int]) -> dict[int, int]:
        """Segments per object, over the whole map."""
        sizes: dict[int, int] = {}
        objects = list(objects)
        for start in range(0, len(objects), 500):
            chunk = objects[start:start + 500]
            sizes.update(self.db.execute(f"SELECT object, COUNT(*) FROM segments WHERE object IN "
                                         f"({','.join('?' * len(chunk))}) GROUP BY object", chunk).fetchall())
        return sizes

    # ------------------------------------------------------------------ writes (inside writing())
    def add_scan(self, name: str, num_views: int, num_segments: int, model: str | None) -> int:
        cur = self.db.execute("INSERT INTO scans (name, added_at, num_views, num_segments, model) VALUES (?, ?, ?, ?, ?)",
                              (name, time.time(), num_views, num_segments, model))
        return int(cur.lastrowid)

    def add_view(self, scan: int, name: str, pose: np.ndarray, declared: np.ndarray,
                 intrinsics: tuple[float, float, float, float, int, int], stride: int, depth: np.ndarray,
                 labels: np.ndarray, labels_top: int, labels_left: int, labels_stride: int, grid_stride: int,
                 grid_depth: np.ndarray, grid_mask: np.ndarray, lo: np.ndarray | None, hi: np.ndarray | None,
                 cell: float) -> int:
        arrays = [x for a in (depth, labels, grid_depth, grid_mask) for x in pack_array(a, compress=True)]
        box = [None] * 6 if lo is None else [float(x) for x in (*lo, *hi)]
        cur = self.db.execute(
            "INSERT INTO views (scan, name, pose, declared, fx, fy, cx, cy, width, height, stride, depth, depth_dtype, "
            "depth_shape, labels, labels_dtype, labels_shape, labels_top, labels_left, labels_stride, grid_stride, "
            "grid_depth, grid_depth_dtype, grid_depth_shape, grid_mask, grid_mask_dtype, grid_mask_shape, lo_x, lo_y, "
            f"lo_z, hi_x, hi_y, hi_z) VALUES ({', '.join('?' * 33)})",
            (scan, name, pack_array(np.asarray(pose, dtype=np.float64))[0],
             pack_array(np.asarray(declared, dtype=np.float64))[0], *map(float, intrinsics[:4]),
             int(intrinsics[4]), int(intrinsics[5]), stride, *arrays[:6], labels_top, labels_left, labels_stride,
             grid_stride,
             *arrays[6:], *box))
        view = int(cur.lastrowid)
        if lo is not None:
            self.db.executemany("INSERT INTO view_cells VALUES (?, ?)",
                                [(int(k), view) for k in cell_keys(lo, hi, cell)])
        return view

    def add_segments(self, rows: list[tuple]) -> list[int]:
        """Insert segments: (scan, view, local, instance, component, num_pixels, cut, object, support,
        margin, points (n, 3) float32); returns their ids.  Centroid and box come from the points."""
        ids = []
        for scan, view, local, instance, component, pixels, cut, obj, support, margin, points in rows:
            data, dtype, shape = pack_array(points)
            geometry = _geometry(points)
            cur = self.db.execute(
                "INSERT INTO segments (scan, view, local, instance, component, num_pixels, num_points, cut, object, "
                "support, margin, cx, cy, cz, lo_x, lo_y, lo_z, hi_x, hi_y, hi_z, points, points_dtype, points_shape) "
                f"VALUES ({', '.join('?' * 23)})",
                (scan, view, local, instance, component, pixels, len(points), cut, obj, support, margin, *geometry,
                 data, dtype, shape))
            ids.append(int(cur.lastrowid))
        return ids

    def move_view(self, view: int, pose: np.ndarray, lo: np.ndarray | None, hi: np.ndarray | None, cell: float,
                  segments: Sequence[int], points: Sequence[np.ndarray]) -> None:
        """A view's corrected pose, its footprint and its segments' moved points."""
        box = [None] * 6 if lo is None else [float(x) for x in (*lo, *hi)]
        self.db.execute("UPDATE views SET pose = ?, lo_x = ?, lo_y = ?, lo_z = ?, hi_x = ?, hi_y = ?, hi_z = ? "
                        "WHERE view = ?", (pack_array(np.asarray(pose, dtype=np.float64))[0], *box, view))
        self.db.execute("DELETE FROM view_cells WHERE view = ?", (view,))
        if lo is not None:
            self.db.executemany("INSERT INTO view_cells VALUES (?, ?)",
                                [(int(k), view) for k in cell_keys(lo, hi, cell)])
        rows = []
        for segment, pts in zip(segments, points):
            data, dtype, shape = pack_array(pts)
            rows.append((*_geometry(pts), data, dtype, shape, segment))
        self.db.executemany("UPDATE segments SET cx = ?, cy = ?, cz = ?, lo_x = ?, lo_y = ?, lo_z = ?, hi_x = ?, "
                            "hi_y = ?, hi_z = ?, points = ?, points_dtype = ?, points_shape = ? WHERE segment = ?", rows)

    def add_objects(self, objects: Sequence[int], scan: int) -> None:
        self.db.executemany("INSERT INTO objects (object, created_scan) VALUES (?, ?)", [(o, scan) for o in objects])

    def move_segments(self, segments: Sequence[int], objects: Sequence[int], supports: Sequence[float],
                      margins: Sequence[float]) -> None:
        """Segments placed anew: their object, support and margin."""
        self.db.executemany("UPDATE segments SET object = ?, support = ?, margin = ? WHERE segment = ?",
                            list(zip(objects, supports, margins, segments)))

    def merge_object(self, retired: int, into: int) -> list[int]:
        """Every segment of ``retired`` takes ``into``; returns the segments moved."""
        moved = [r[0] for r in self.db.execute("SELECT segment FROM segments WHERE object = ? ORDER BY segment",
                                                (retired,))]
        self.db.execute("UPDATE segments SET object = ? WHERE object = ?", (into, retired))
        return moved

    def retire_object(self, obj: int, scan: int, into: int | None) -> None:
        self.db.execute("UPDATE objects SET retired_scan = ?, retired_into = ? WHERE object = ?", (scan, into, obj))

    def add_event(self, scan: int, kind: str, obj: int, into: int | None, views: list[str], segments: list[int],
                  moved: list[int], margin: float | None) -> int:
        cur = self.db.execute(
            "INSERT INTO events (scan, kind, object, into_object, views, segments, moved, margin) "
            "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            (scan, kind, obj, into, json.dumps(views), json.dumps(segments), json.dumps(moved), margin))
        return int(cur.lastrowid)

    # ------------------------------------------------------------------ reads for reports
    def segment_table(self, scan: int | None = None) -> list[tuple]:
        """(segment, scan, view name, instance, component, num_points, object, support, margin) per segment."""
        where, args = ("WHERE s.scan = ?", (scan,)) if scan is not None else ("", ())
        return self.db.execute(
            "SELECT s.segment, s.scan, v.name, s.instance, s.component, s.num_points, s.object, s.support, s.margin "
            f"FROM segments s JOIN views v ON v.view = s.view {where} ORDER BY s.segment", args).fetchall()

    def object_table(self) -> list[tuple]:
        """Per object with segments: (object, created_scan, segments, centroid x, y, z, box lo x, y, z, hi x, y, z)."""
        return self.db.execute(
            "SELECT o.object, o.created_scan, COUNT(s.segment), "
            "SUM(s.cx * s.num_points) / NULLIF(SUM(CASE WHEN s.cx IS NULL THEN 0 ELSE s.num_points END), 0), "
            "SUM(s.cy * s.num_points) / NULLIF(SUM(CASE WHEN s.cy IS NULL THEN 0 ELSE s.num_points END), 0), "
            "SUM(s.cz * s.num_points) / NULLIF(SUM(CASE WHEN s.cz IS NULL THEN 0 ELSE s.num_points END), 0), "
            "MIN(s.lo_x), MIN(s.lo_y), MIN(s.lo_z), MAX(s.hi_x), MAX(s.hi_y), MAX(s.hi_z) "
            "FROM objects o JOIN segments s ON s.object = o.object GROUP BY o.object ORDER BY o.object").fetchall()

    def object_views(self) -> list[tuple]:
        """Distinct (object, scan, view name), ordered."""
        return self.db.execute(
            "SELECT DISTINCT s.object, s.scan, v.name FROM segments s JOIN views v ON v.view = s.view "
            "ORDER BY s.object, s.scan, v.view").fetchall()

    def event_table(self, since: int = 0) -> list[tuple]:
        return self.db.execute(
            "SELECT event, kind, object, into_object, scan, views, segments, moved, margin FROM events "
            "WHERE event > ? ORDER BY event", (since,)).fetchall()

    def scan_table(self) -> list[tuple]:
        return self.db.execute("SELECT scan, name, added_at, num_segments, model FROM scans ORDER BY scan").fetchall()

    def scan_views(self) -> list[tuple]:
        return self.db.execute("SELECT scan, name FROM views ORDER BY view").fetchall()


def _geometry(points: np.ndarray) -> list[float | None]:
    """Centroid, box minimum and box maximum of a segment's points (9 numbers; None without points)."""
    if not len(points):
        return [None] * 9
    return [float(x) for x in (*points.mean(axis=0), *points.min(axis=0), *points.max(axis=0))]
