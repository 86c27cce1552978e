"""Load and write scene bundles: directories, ``.zip`` / ``.tar(.gz|.bz2|.xz)`` archives,
or a manifest plus in-memory file parts (what the HTTP service receives).

Bundles come from untrusted uploads, so loading is defensive throughout:

* sizes are checked before work is done: view count, pixels per view (from the
  intrinsics and from each image header), number of files, declared uncompressed
  archive sizes, compression ratio; and the bytes actually decompressed are capped
  as well, because archive headers can lie;
* archive member names and manifest paths must be relative and stay inside the
  bundle (no absolute paths, no ``..``); tar links, devices and fifos are refused;
  a directory bundle refuses symlinks that resolve outside its folder;
* nothing is ever unpickled (``allow_pickle=False``; ``.npz`` members are parsed one
  by one as ``.npy``);
* every problem found is collected and reported together in one ``BundleError``,
  each with a ``loc`` naming the view and field (``views[1:cam2].mask.file``).

Poses are converted to OpenCV camera-to-world (``bundle.pose_to_opencv``); depth given
as distance along the ray (``kind: "range"``) is converted to z-depth; invalid depth
(<= 0, non-finite) becomes 0.
"""

from __future__ import annotations

import bz2
import gzip
import io
import json
import lzma
import re
import stat
import tarfile
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..bundle import Manifest, PointSegments, SceneBundle, View, ViewSpec, pose_to_opencv
from ..errors import BundleError, Problem, problems_from_validation_error, view_loc
from . import images

__all__ = [
    "BundleLimits",
    "load_bundle",
    "load_bundle_from_parts",
    "write_bundle",
    "write_bundle_archive",
    "bundle_to_parts",
    "normalize_bundle_path",
    "range_to_z",
]

MiB = 1024 * 1024
MANIFEST_NAME = "manifest.json"


class BundleLimits(BaseModel):
    """Resource limits applied while loading one bundle (defaults suit the HTTP service)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_views: int = Field(16, ge=1)
    max_pixels_per_view: int = Field(4096 * 4096, ge=1)
    max_total_bytes: int = Field(512 * MiB, ge=1, description="uncompressed bytes of all files together")
    max_files: int = Field(64, ge=1, description="regular files in an archive / parts in an upload")
    max_manifest_bytes: int = Field(1 * MiB, ge=1)
    max_compression_ratio: float = Field(
        200.0, gt=1, description="uncompressed / compressed archive bytes; zip bombs reach ~1000"
    )
    ratio_check_min_bytes: int = Field(
        32 * MiB, ge=0, description="archives expanding to less than this are not ratio-checked (harmless)"
    )
    max_segments: int = Field(100_000, ge=1, description="point-segment bundles: number of segments")
    max_segment_points: int = Field(20_000_000, ge=1, description="point-segment bundles: total points")


# --------------------------------------------------------------------------- paths
_DRIVE = re.compile(r"^[A-Za-z]:")


def normalize_bundle_path(path: str) -> str:
    """Validate a path named in a manifest (or an archive member) and normalise it.

    Returns the POSIX-style relative path without ``.`` / empty components.  Raises
    ``ValueError`` (with a user-facing reason) for absolute paths, drive letters,
    backslashes, NUL bytes and any ``..`` component: a bundle can only name files
    inside itself.
    """
    if not isinstance(path, str) or not path:
        raise ValueError("path is empty")
    if "\x00" in path:
        raise ValueError("path contains a NUL byte")
    if path.startswith(("/", "\\")) or _DRIVE.match(path):
        raise ValueError(f"absolute path {path!r} is not allowed; paths are relative to the bundle root")
    if "\\" in path:
        raise ValueError(f"path {path!r} contains a backslash; use '/' as separator")
    parts = [p for p in path.split("/") if p not in ("", ".")]
    if any(p == ".." for p in parts):
        raise ValueError(f"path {path!r} leaves the bundle ('..' is not allowed)")
    if not parts:
        raise ValueError(f"path {path!r} names no file")
    return "/".join(parts)


# --------------------------------------------------------------------------- file sources
class _Source:
    """Where the files a manifest names come from.  ``read`` raises ``BundleError`` at ``loc``."""

    def read(self, rel: str, loc: str) -> bytes:  # pragma: no cover - interface
        raise NotImplementedError

    def exists(self, rel: str) -> bool:  # pragma: no cover - interface
        raise NotImplementedError

    def unreferenced(self, used: set[str]) -> list[str]:
        return []


class _PartsSource(_Source):
    """Files held in memory (upload parts, archive members), keyed by normalised path."""

    def __init__(self, files: Mapping[str, bytes], what: str, skipped: list[str] | None = None) -> None:
        self.files = dict(files)
        self.what = what  # "uploaded files" / "archive" -- used in messages
        self.skipped = list(skipped or [])  # archive members never decompressed: the manifest does not name them

    def exists(self, rel: str) -> bool:
        return rel in self.files

    def read(self, rel: str, loc: str) -> bytes:
        try:
            return self.files[rel]
        except KeyError:
            raise BundleError(f"file {rel!r} is not in the {self.what}", loc=loc) from None

    def unreferenced(self, used: set[str]) -> list[str]:
        return sorted((set(self.files) - used) | set(self.skipped))


class _DirSource(_Source):
    """Files under a local directory; symlinks may not lead outside it; bytes are budgeted."""

    def __init__(self, root: Path, limits: BundleLimits) -> None:
        self.root = root.resolve()
        self.budget = limits.max_total_bytes
        self.files_left = limits.max_files
        self._cache: dict[str, bytes] = {}  # a file named by several views is read (and budgeted) once

    def _resolve(self, rel: str) -> Path:
        return (self.root / rel).resolve()

    def exists(self, rel: str) -> bool:
        return (self.root / rel).is_file()

    def read(self, rel: str, loc: str) -> bytes:
        if rel in self._cache:
            return self._cache[rel]
        p = self.root / rel
        if not p.exists():
            raise BundleError(f"file {rel!r} not found in the bundle directory", loc=loc)
        real = self._resolve(rel)
        if not real.is_relative_to(self.root):
            raise BundleError(f"file {rel!r} resolves outside the bundle directory (symlink?)", loc=loc)
        if not real.is_file():
            raise BundleError(f"{rel!r} is not a regular file", loc=loc)
        size = real.stat().st_size
        self.files_left -= 1
        if self.files_left < 0:
            raise BundleError("too many files referenced", loc=loc)
        if size > self.budget:
            raise BundleError(f"file {rel!r} ({size} bytes) exceeds the remaining size budget of the bundle", loc=loc)
        self.budget -= size
        with open(real, "rb") as fh:
            data = fh.read(size + 1)  # the file may have grown since stat(); never read more than budgeted
        if len(data) > size:
            raise BundleError(f"file {rel!r} changed while being read", loc=loc)
        self._cache[rel] = data
        return data


# --------------------------------------------------------------------------- archives
class _Capped(io.RawIOBase):
    """Read-through wrapper that fails once more than ``cap`` bytes were read.

    Wraps the *decompressed* tar stream: whatever the headers claim, a bomb can make
    us decompress at most ``cap`` bytes.
    """

    def __init__(self, raw: IO[bytes], cap: int) -> None:
        self.raw, self.cap, self.count = raw, cap, 0

    def readable(self) -> bool:
        return True

    def readinto(self, b: Any) -> int:
        data = self.raw.read(len(b))
        self.count += len(data)
        if self.count > self.cap:
            raise _TooBig(f"archive expands to more than {self.cap} bytes")
        b[: len(data)] = data
        return len(data)


class _TooBig(Exception):
    pass


#: Members expanding to less than this are not ratio-checked one by one (a small file of
#: zeros compresses far beyond any bomb ratio and is harmless).
_MEMBER_RATIO_MIN_BYTES = 1 * MiB


def _is_manifest(name: str) -> bool:
    """A manifest candidate: at the archive root, or inside exactly one top-level folder."""
    return name == MANIFEST_NAME or (name.count("/") == 1 and name.endswith("/" + MANIFEST_NAME))


class _Named:
    """Which archive members to decompress: manifest candidates, then only what the manifest names.

    Until a manifest has been read every member is wanted (a tar stream may put files
    before it); afterwards only the manifest's own files under its folder.  A manifest
    that cannot be parsed names nothing: the loader reports it, from the manifest alone.
    """

    def __init__(self, limits: BundleLimits) -> None:
        self.limits = limits
        self.names: set[str] | None = None

    def learn(self, manifest_name: str, data: bytes) -> None:
        prefix = manifest_name[: -len(MANIFEST_NAME)]
        self.names = set()
        try:
            refs = _raw_file_refs(_parse_manifest(data, self.limits))
        except BundleError:
            return
        for _, path in refs:
            try:
                self.names.add(prefix + normalize_bundle_path(path))
            except (ValueError, TypeError):
                continue  # the loader reports the bad path

    def wants(self, name: str) -> bool:
        return self.names is None or _is_manifest(name) or name in self.names


_SKIP = re.compile(r"(^|/)(__MACOSX/|\._)")  # macOS Finder litter in zips: never bundle content


def _archive_kind(head: bytes) -> str | None:
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        return "zip"
    if head.startswith(b"\x1f\x8b"):
        return "gz"
    if head.startswith(b"BZh"):
        return "bz2"
    if head.startswith(b"\xfd7zXZ\x00"):
        return "xz"
    if len(head) >= 262 and head[257:262] == b"ustar":
        return "tar"
    return None


def _member_name(name: str, problems: list[Problem]) -> str | None:
    """Normalised archive member name, or ``None`` (problem recorded) when unsafe."""
    try:
        return normalize_bundle_path(name.rstrip("/") or name)
    except ValueError as e:
        problems.append(Problem(loc=f"archive[{name!r}]", msg=str(e)))
        return None


def _read_zip(
    fh: IO[bytes], archive_size: int, limits: BundleLimits
) -> tuple[dict[str, bytes], list[Problem], list[str]]:
    """The manifest and the members it names (decompressed), problems, and the names of members left unread."""
    problems: list[Problem] = []
    files: dict[str, bytes] = {}
    try:
        zf = zipfile.ZipFile(fh)
    except (zipfile.BadZipFile, OSError, ValueError) as e:
        return {}, [Problem(loc="archive", msg=f"not a readable .zip: {e}")], []
    with zf:
        infos = zf.infolist()
        if len(infos) > 4 * limits.max_files + 16:  # bound the work spent on directory entries too
            return {}, [Problem(loc="archive", msg=f"archive has {len(infos)} entries; the limit is {limits.max_files} files")], []
        wanted: list[tuple[str, zipfile.ZipInfo]] = []
        for info in infos:
            if _SKIP.search(info.filename) or info.is_dir():
                continue
            name = _member_name(info.filename, problems)
            if name is None:
                continue
            mode = info.external_attr >> 16
            if info.create_system == 3 and stat.S_IFMT(mode) not in (0, stat.S_IFREG):
                kind = "symlink" if stat.S_ISLNK(mode) else "special file"
                problems.append(Problem(loc=f"archive[{info.filename!r}]", msg=f"{kind} members are not allowed"))
                continue
            if info.flag_bits & 0x1:
                problems.append(Problem(loc=f"archive[{info.filename!r}]", msg="encrypted members are not supported"))
                continue
            wanted.append((name, info))
        names = [n for n, _ in wanted]
        dups = sorted({n for n in names if names.count(n) > 1})
        if dups:
            problems.append(Problem(loc="archive", msg=f"duplicate members {dups[:5]}"))
        if len(wanted) > limits.max_files:
            problems.append(Problem(loc="archive", msg=f"archive holds {len(wanted)} files; the limit is {limits.max_files}"))
        if problems:
            return {}, problems, []
        named = _Named(limits)
        manifests = [(n, i) for n, i in wanted if _is_manifest(n)]
        if len(manifests) == 1:  # several (or none): the loader says so, from the candidates alone
            data, problem = _zip_member(zf, manifests[0][1], limits.max_manifest_bytes + 1)
            if problem is not None:
                return {}, [problem], []
            named.learn(manifests[0][0], data)
        else:
            named.names = set()
        skipped = [n for n, _ in wanted if not named.wants(n)]
        wanted = [(n, i) for n, i in wanted if named.wants(n)]
        declared = sum(i.file_size for _, i in wanted)
        problems += _size_problems(0, declared, sum(i.compress_size for _, i in wanted) or archive_size, limits)
        for _, info in wanted:
            ratio = info.file_size / max(info.compress_size, 1)
            if info.file_size > _MEMBER_RATIO_MIN_BYTES and ratio > limits.max_compression_ratio:
                problems.append(Problem(loc=f"archive[{info.filename!r}]",
                                        msg=f"compression ratio {ratio:.0f}:1 exceeds "
                                        f"{limits.max_compression_ratio:.0f}:1 (zip bomb?)"))
        if problems:
            return {}, problems, []
        total = 0
        for name, info in wanted:
            # zipfile stops at the declared size; asking for one byte more detects a liar.
            data, problem = _zip_member(zf, info, info.file_size + 1)
            if problem is not None:
                problems.append(problem)
                continue
            total += len(data)
            if len(data) > info.file_size or total > limits.max_total_bytes:
                problems.append(Problem(loc=f"archive[{info.filename!r}]", msg="member is larger than declared / over the size limit"))
                break
            files[name] = data
    return files, problems, skipped


def _zip_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, max_bytes: int) -> tuple[bytes, Problem | None]:
    """At most ``max_bytes`` of one member, or the problem that stopped its extraction."""
    try:
        with zf.open(info) as m:
            return m.read(max_bytes), None
    except (zipfile.BadZipFile, OSError, NotImplementedError, RuntimeError, ValueError, EOFError, lzma.LZMAError) as e:
        return b"", Problem(loc=f"archive[{info.filename!r}]", msg=f"cannot extract: {e}")


def _size_problems(n_files: int, declared: int, compressed: int, limits: BundleLimits) -> list[Problem]:
    out: list[Problem] = []
    if n_files > limits.max_files:
        out.append(Problem(loc="archive", msg=f"archive holds {n_files} files; the limit is {limits.max_files}"))
    if declared > limits.max_total_bytes:
        out.append(
            Problem(loc="archive", msg=f"archive expands to {declared} bytes; the limit is {limits.max_total_bytes}")
        )
    ratio = declared / max(compressed, 1)
    if declared > limits.ratio_check_min_bytes and ratio > limits.max_compression_ratio:
        out.append(
            Problem(
                loc="archive",
                msg=f"compression ratio {ratio:.0f}:1 exceeds {limits.max_compression_ratio:.0f}:1 (zip bomb?)",
            )
        )
    return out


def _read_tar(
    fh: IO[bytes], kind: str, archive_size: int, limits: BundleLimits
) -> tuple[dict[str, bytes], list[Problem], list[str]]:
    """Like ``_read_zip``; a tar stream can only be skipped through, so members after the
    manifest that it does not name are passed over unkept (the decompressed stream stays capped)."""
    problems: list[Problem] = []
    files: dict[str, bytes] = {}
    named = _Named(limits)
    skipped: list[str] = []
    stream: IO[bytes] = fh
    if kind == "gz":
        stream = gzip.GzipFile(fileobj=fh, mode="rb")  # type: ignore[assignment]
    elif kind == "bz2":
        stream = bz2.BZ2File(fh, mode="rb")  # type: ignore[assignment]
    elif kind == "xz":
        stream = lzma.LZMAFile(fh, mode="rb")  # type: ignore[assignment]
    max_entries = 4 * limits.max_files + 16
    # Headers and padding cost 512-byte blocks on top of the payload.
    cap = limits.max_total_bytes + 1024 * (max_entries + 4) + 20 * 512 * 2
    capped = _Capped(stream, cap)  # type: ignore[arg-type]
    declared = entries = 0
    try:
        # "r|": a forward-only stream, so the (capped) decompressor is read exactly once.
        with tarfile.open(fileobj=io.BufferedReader(capped, 64 * 1024), mode="r|") as tf:
            for m in tf:
                entries += 1
                if entries > max_entries:
                    problems.append(Problem(loc="archive", msg=f"archive has more than {max_entries} entries"))
                    break
                if _SKIP.search(m.name) or m.isdir():
                    continue
                where = f"archive[{m.name!r}]"
                name = _member_name(m.name, problems)
                if name is None:
                    continue
                if m.issym() or m.islnk():
                    problems.append(Problem(loc=where, msg=f"links are not allowed (-> {m.linkname!r})"))
                    continue
                if not m.isreg() or m.issparse():
                    problems.append(Problem(loc=where, msg="only regular files are allowed (device, fifo or sparse member)"))
                    continue
                declared += m.size  # skipped members count too: the stream decompresses them all the same
                bomb = declared > limits.ratio_check_min_bytes and declared / max(archive_size, 1) > limits.max_compression_ratio
                if len(files) + 1 > limits.max_files or declared > limits.max_total_bytes or bomb:
                    problems += _size_problems(len(files) + 1, declared, archive_size, limits)
                    break
                if name in files:
                    problems.append(Problem(loc=where, msg="duplicate member"))
                    continue
                if not named.wants(name):
                    skipped.append(name)
                    continue
                ex = tf.extractfile(m)
                data = ex.read(m.size) if ex is not None else b""
                if len(data) != m.size:
                    problems.append(Problem(loc=where, msg="member is truncated"))
                    break
                files[name] = data
                if _is_manifest(name):
                    named.learn(name, data)
    except _TooBig as e:
        problems.append(Problem(loc="archive", msg=str(e)))
    except (tarfile.TarError, OSError, EOFError, lzma.LZMAError, ValueError) as e:
        problems.append(Problem(loc="archive", msg=f"not a readable .tar archive: {e}"))
    early = [n for n in files if not named.wants(n)]  # kept before the manifest came, not named by it
    for n in early:
        del files[n]
    return files, problems, skipped + early


def _load_archive(fh: IO[bytes], archive_size: int, limits: BundleLimits) -> SceneBundle:
    files, skipped = _read_archive(fh, archive_size, limits)
    manifest, rest = _split_root(files)
    return _load(manifest, _PartsSource(rest, "archive", skipped), limits)


def _read_archive(fh: IO[bytes], archive_size: int, limits: BundleLimits) -> tuple[dict[str, bytes], list[str]]:
    """The manifest and the members it names of a .zip / .tar(.gz|.bz2|.xz), bounded by ``limits``,
    and the names of the members left undecompressed."""
    head = fh.read(512)
    fh.seek(0)
    kind = _archive_kind(head)
    if kind is None:
        if zipfile.is_zipfile(fh):  # e.g. a zip with a prefix
            kind = "zip"
        fh.seek(0)
    if kind is None:
        raise BundleError("not a .zip or .tar archive (and not a bundle directory)", loc="archive")
    if kind == "zip":
        files, problems, skipped = _read_zip(fh, archive_size, limits)
    else:
        files, problems, skipped = _read_tar(fh, kind, archive_size, limits)
    if problems:
        raise BundleError(problems)
    return files, skipped


def _split_root(files: dict[str, bytes]) -> tuple[bytes, dict[str, bytes]]:
    """Find manifest.json at the archive root or in exactly one top-level folder."""
    if MANIFEST_NAME in files:
        prefix = ""
    else:
        cands = sorted(n for n in files if n.count("/") == 1 and n.endswith("/" + MANIFEST_NAME))
        if not cands:
            raise BundleError(
                f"no {MANIFEST_NAME} at the archive root or inside a single top-level folder", loc="manifest"
            )
        if len(cands) > 1:
            raise BundleError(f"several candidate manifests {cands[:5]}; the archive must hold one bundle", loc="manifest")
        prefix = cands[0][: -len(MANIFEST_NAME)]
    manifest = files[prefix + MANIFEST_NAME]
    rest = {n[len(prefix):]: b for n, b in files.items() if n.startswith(prefix) and n != prefix + MANIFEST_NAME}
    return manifest, rest


# --------------------------------------------------------------------------- manifest
def _parse_manifest(raw: dict | str | bytes, limits: BundleLimits) -> dict:
    if isinstance(raw, dict):
        return raw
    if isinstance(raw, (bytes, bytearray, memoryview)):
        raw = bytes(raw)
        if len(raw) > limits.max_manifest_bytes:
            raise BundleError(f"manifest is {len(raw)} bytes; the limit is {limits.max_manifest_bytes}", loc="manifest")
        try:
            raw = raw.decode("utf-8-sig")
        except UnicodeDecodeError as e:
            raise BundleError(f"manifest is not UTF-8 text: {e}", loc="manifest") from None
    if not isinstance(raw, str):
        raise BundleError(f"manifest must be JSON text or a dict, got {type(raw).__name__}", loc="manifest")
    if len(raw) > limits.max_manifest_bytes:
        raise BundleError(f"manifest is {len(raw)} characters; the limit is {limits.max_manifest_bytes}", loc="manifest")
    try:
        data = json.loads(raw)
    except json.JSONDecodeError as e:
        raise BundleError(f"manifest is not valid JSON: {e.msg} at line {e.lineno} column {e.colno}", loc="manifest") from None
    except RecursionError:
        raise BundleError("manifest JSON is nested too deeply", loc="manifest") from None
    except ValueError as e:  # e.g. an integer with more digits than Python will parse
        raise BundleError(f"manifest is not valid JSON: {e}", loc="manifest") from None
    if not isinstance(data, dict):
        raise BundleError(f"manifest must be a JSON object, got {type(data).__name__}", loc="manifest")
    return data


def _raw_file_refs(data: dict) -> list[tuple[str, Any]]:
    """(loc, path) of every file an *unvalidated* manifest names, for path checks that
    should be reported even when other parts of the manifest are invalid."""
    refs: list[tuple[str, Any]] = []
    views = data.get("views")
    if isinstance(views, list):
        for i, v in enumerate(views):
            if not isinstance(v, dict):
                continue
            name = v.get("name") if isinstance(v.get("name"), str) else None
            for key in ("depth", "mask"):
                spec = v.get(key)
                if isinstance(spec, dict) and "file" in spec:
                    refs.append((f"{view_loc(i, name)}.{key}.file", spec["file"]))
    seg = data.get("segments")
    if isinstance(seg, dict) and "file" in seg:
        refs.append(("segments.file", seg["file"]))
    return refs


def _check_refs(refs: list[tuple[str, Any]], source: _Source) -> tuple[dict[str, str], list[Problem]]:
    """Validate manifest paths: relative, inside the bundle, present.  Returns loc -> normalised path."""
    out: dict[str, str] = {}
    problems: list[Problem] = []
    for loc, path in refs:
        if not isinstance(path, str):
            continue  # pydantic reports the type error
        try:
            rel = normalize_bundle_path(path)
        except ValueError as e:
            problems.append(Problem(loc=loc, msg=str(e)))
            continue
        if not source.exists(rel):
            problems.append(Problem(loc=loc, msg=f"file {path!r} not found in the bundle"))
            continue
        out[loc] = rel
    return out, problems


# --------------------------------------------------------------------------- decoding
def range_to_z(rng: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Distance along each pixel's ray -> z-depth along the optical axis (pixel centres at integer u, v)."""
    h, w = rng.shape
    x = (np.arange(w, dtype=np.float32) - np.float32(cx)) / np.float32(fx)
    y = (np.arange(h, dtype=np.float32) - np.float32(cy)) / np.float32(fy)
    norm = np.sqrt(x[None, :] ** 2 + y[:, None] ** 2 + np.float32(1.0))
    return (rng / norm).astype(np.float32)


def _decode_view(
    i: int, spec: ViewSpec, paths: dict[str, str], source: _Source, limits: BundleLimits, warnings: list[str]
) -> tuple[View | None, list[Problem]]:
    vloc = view_loc(i, spec.name)
    problems: list[Problem] = []
    pose = pose_to_opencv(np.asarray(spec.pose.matrix, dtype=np.float64), spec.pose.convention)
    intr = spec.intrinsics
    shape = (intr.height, intr.width) if intr is not None else None
    if intr is not None and intr.width * intr.height > limits.max_pixels_per_view:
        problems.append(
            Problem(
                loc=f"{vloc}.intrinsics",
                msg=f"{intr.width}x{intr.height} pixels exceeds the limit of {limits.max_pixels_per_view} per view",
            )
        )
        return None, problems
    depth = mask = None
    if spec.depth is not None:
        loc = f"{vloc}.depth.file"
        if intr is None:
            problems.append(Problem(loc=f"{vloc}.intrinsics", msg="a view with depth needs intrinsics"))
        elif loc in paths:
            try:
                depth = images.read_depth(
                    source.read(paths[loc], loc),
                    spec.depth.format,
                    scale=spec.depth.scale,
                    channel=spec.depth.channel,
                    shape=shape,
                    max_pixels=limits.max_pixels_per_view,
                    loc=loc,
                )
                if spec.depth.kind == "range":
                    depth = range_to_z(depth, intr.fx, intr.fy, intr.cx, intr.cy)
                if not depth.any():
                    warnings.append(f"{vloc}: depth has no valid pixel (all <= 0 or non-finite)")
            except BundleError as e:
                problems += e.problems
    if spec.mask is not None:
        loc = f"{vloc}.mask.file"
        if intr is None:
            problems.append(Problem(loc=f"{vloc}.intrinsics", msg="a view with a mask needs intrinsics"))
        elif loc in paths:
            try:
                mask = images.read_mask(
                    source.read(paths[loc], loc),
                    spec.mask.format,
                    palette=spec.mask.palette,
                    shape=shape,
                    max_pixels=limits.max_pixels_per_view,
                    loc=loc,
                    warnings=warnings,
                )
                if not mask.any():
                    warnings.append(f"{vloc}: mask has no instances (all background)")
            except BundleError as e:
                problems += e.problems
    if mask is not None and spec.instance_objects is not None:
        ids = _mask_ids(mask)
        unmapped = sorted(set(ids.tolist()) - set(spec.instance_objects) - {0})
        if unmapped:
            warnings.append(f"{vloc}: instance ids {unmapped[:10]} have no entry in instance_objects (no ground truth)")
    if problems:
        return None, problems
    view = View(
        name=spec.name,
        pose=pose,
        intrinsics=intr,
        depth=depth,
        mask=mask,
        instance_objects=dict(spec.instance_objects) if spec.instance_objects is not None else None,
    )
    return view, problems


def _mask_ids(mask: np.ndarray) -> np.ndarray:
    """Distinct ids of a mask; bincount is ~10x faster than unique for the usual small ids."""
    hi = int(mask.max(initial=0))
    if hi < 1 << 20:
        return np.flatnonzero(np.bincount(mask.ravel(), minlength=1))
    return np.unique(mask)


_SEG_REQUIRED = ("points", "lengths", "view", "instance")
_SEG_OPTIONAL = ("object",)


def _read_segments_npz(data: bytes, n_views: int, limits: BundleLimits, warnings: list[str]) -> PointSegments:
    """Parse a point-segment ``.npz`` member by member (never ``np.load`` on the zip: no pickles, bounded sizes)."""
    base = "segments"
    problems: list[Problem] = []
    arrays: dict[str, np.ndarray] = {}
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except (zipfile.BadZipFile, ValueError) as e:
        raise BundleError(f"not an .npz file: {e}", loc=f"{base}.file") from None
    with zf:
        infos = [i for i in zf.infolist() if not i.is_dir()]
        if len(infos) > 16:
            raise BundleError(f".npz has {len(infos)} members; expected {_SEG_REQUIRED + _SEG_OPTIONAL}", loc=f"{base}.file")
        declared = sum(i.file_size for i in infos)
        if declared > limits.max_total_bytes:
            raise BundleError(f".npz expands to {declared} bytes; the limit is {limits.max_total_bytes}", loc=f"{base}.file")
        for info in infos:
            key = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            if key not in _SEG_REQUIRED + _SEG_OPTIONAL:
                warnings.append(f"{base}: ignored unknown array {key!r}")
                continue
            try:
                with zf.open(info) as m:
                    raw = m.read(info.file_size + 1)
            except Exception as e:
                problems.append(Problem(loc=f"{base}.{key}", msg=f"cannot extract: {e}"))
                continue
            try:
                arrays[key] = images.read_npy(raw, max_elements=3 * limits.max_segment_points, loc=f"{base}.{key}")
            except BundleError as e:
                problems += e.problems
    for key in _SEG_REQUIRED:
        if key not in arrays and not any(p.loc == f"{base}.{key}" for p in problems):
            problems.append(Problem(loc=f"{base}.{key}", msg="required array missing"))
    if problems:
        raise BundleError(problems)

    pts = arrays["points"]
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.dtype.kind not in "fiu":
        problems.append(Problem(loc=f"{base}.points", msg=f"must be a numeric (P, 3) array, got {pts.dtype} {pts.shape}"))
    elif pts.shape[0] > limits.max_segment_points:
        problems.append(Problem(loc=f"{base}.points", msg=f"{pts.shape[0]} points; the limit is {limits.max_segment_points}"))
    elif not np.isfinite(pts).all():
        problems.append(Problem(loc=f"{base}.points", msg="points must be finite (found NaN or inf)"))
    ints: dict[str, np.ndarray] = {}
    for key in ("lengths", "view", "instance", "object"):
        if key not in arrays:
            continue
        a = arrays[key]
        if a.ndim != 1 or a.dtype.kind not in "iu":
            problems.append(Problem(loc=f"{base}.{key}", msg=f"must be a 1-D integer array, got {a.dtype} {a.shape}"))
            continue
        ints[key] = a.astype(np.int64)
    if "lengths" in ints:
        n_seg = len(ints["lengths"])
        if n_seg > limits.max_segments:
            problems.append(Problem(loc=f"{base}.lengths", msg=f"{n_seg} segments; the limit is {limits.max_segments}"))
        if (ints["lengths"] < 0).any():
            problems.append(Problem(loc=f"{base}.lengths", msg="lengths must be >= 0"))
        elif pts.ndim == 2 and int(ints["lengths"].sum()) != pts.shape[0]:
            problems.append(
                Problem(loc=f"{base}.lengths", msg=f"lengths sum to {int(ints['lengths'].sum())} but there are {pts.shape[0]} points")
            )
        for key in ("view", "instance", "object"):
            if key in ints and len(ints[key]) != n_seg:
                problems.append(Problem(loc=f"{base}.{key}", msg=f"has {len(ints[key])} entries for {n_seg} segments"))
        if "view" in ints and len(ints["view"]) == n_seg and n_seg:
            bad = (ints["view"] < 0) | (ints["view"] >= n_views)
            if bad.any():
                problems.append(
                    Problem(loc=f"{base}.view", msg=f"view indices must be in 0..{n_views - 1}; found {int(ints['view'][bad][0])}")
                )
        if n_seg and (ints["lengths"] == 0).any():
            warnings.append(f"{base}: {int((ints['lengths'] == 0).sum())} segments have no points")
    if problems:
        raise BundleError(problems)
    return PointSegments(
        points=np.ascontiguousarray(pts, dtype=np.float64),
        lengths=ints["lengths"],
        view=ints["view"],
        instance=ints["instance"],
        object=ints.get("object"),
    )


def _load(manifest: dict | str | bytes, source: _Source, limits: BundleLimits) -> SceneBundle:
    """Shared core: parse + validate the manifest, check every path, decode every file."""
    data = _parse_manifest(manifest, limits)
    views_raw = data.get("views")
    if isinstance(views_raw, list) and len(views_raw) > limits.max_views:
        # Refuse before validating thousands of views.
        raise BundleError(f"{len(views_raw)} views; the limit is {limits.max_views}", loc="views")
    problems: list[Problem] = []
    try:
        man = Manifest.model_validate(data)
    except ValidationError as e:
        man = None
        problems += problems_from_validation_error(e, data)
    paths, path_problems = _check_refs(_raw_file_refs(data), source)
    problems += path_problems
    if man is None:
        raise BundleError(problems)
    # With a valid manifest, keep going past bad paths: the files that *are* there are
    # decoded too, so one response lists missing files and undecodable ones together.

    warnings: list[str] = []
    views: list[View] = []
    for i, spec in enumerate(man.views):
        view, vp = _decode_view(i, spec, paths, source, limits, warnings)
        problems += vp
        if view is not None:
            views.append(view)
    point_segments = None
    if man.segments is not None and "segments.file" in paths:
        try:
            point_segments = _read_segments_npz(
                source.read(paths["segments.file"], "segments.file"), len(man.views), limits, warnings
            )
        except BundleError as e:
            problems += e.problems
    if problems:
        raise BundleError(problems)
    extra = source.unreferenced(set(paths.values()))
    if extra:
        warnings.append(f"ignored {len(extra)} file(s) the manifest does not name: {extra[:5]}")
    return SceneBundle(
        units=man.units,
        views=views,
        name=man.name,
        ground_truth=man.ground_truth,
        point_segments=point_segments,
        warnings=warnings,
    )


# --------------------------------------------------------------------------- public loaders
def load_bundle_from_parts(
    manifest: dict | str | bytes, files: Mapping[str, bytes], *, limits: BundleLimits | None = None
) -> SceneBundle:
    """Load a bundle from a manifest and in-memory files keyed by their manifest path.

    This is what the HTTP service uses for multipart uploads (one part per file, the
    part's filename = the path in the manifest).  Keys are normalised like manifest
    paths; unsafe keys are problems.  Raises ``BundleError`` listing every problem.
    """
    limits = limits or BundleLimits()
    problems: list[Problem] = []
    norm: dict[str, bytes] = {}
    total = 0
    for key, data in files.items():
        try:
            rel = normalize_bundle_path(key)
        except ValueError as e:
            problems.append(Problem(loc=f"files[{key!r}]", msg=str(e)))
            continue
        if rel in norm:
            problems.append(Problem(loc=f"files[{key!r}]", msg=f"duplicate file {rel!r}"))
            continue
        norm[rel] = bytes(data) if not isinstance(data, bytes) else data
        total += len(data)
    if len(files) > limits.max_files:
        problems.append(Problem(loc="files", msg=f"{len(files)} files; the limit is {limits.max_files}"))
    if total > limits.max_total_bytes:
        problems.append(Problem(loc="files", msg=f"{total} bytes in all; the limit is {limits.max_total_bytes}"))
    if problems:
        raise BundleError(problems)
    return _load(manifest, _PartsSource(norm, "uploaded files"), limits)


def load_bundle(source: str | Path | bytes, *, limits: BundleLimits | None = None) -> SceneBundle:
    """Load a bundle from a directory, a ``manifest.json`` path, a .zip/.tar(.gz) path, or raw archive bytes.

    Raises ``BundleError`` (a ``ValueError``) whose ``.problems`` lists every problem found.
    """
    limits = limits or BundleLimits()
    if isinstance(source, (bytes, bytearray, memoryview)):
        data = bytes(source)
        return _load_archive(io.BytesIO(data), len(data), limits)
    path = Path(source)
    if path.is_dir():
        return _load_dir(path, limits)
    if path.is_file() and path.name == MANIFEST_NAME:
        return _load_dir(path.parent, limits)
    if not path.is_file():
        raise BundleError(f"no such bundle directory or archive: {str(path)!r}", loc="source")
    with open(path, "rb") as fh:
        return _load_archive(fh, path.stat().st_size, limits)


def _load_dir(root: Path, limits: BundleLimits) -> SceneBundle:
    mpath = root / MANIFEST_NAME
    if not mpath.is_file():
        raise BundleError(f"no {MANIFEST_NAME} in {str(root)!r}", loc="manifest")
    size = mpath.stat().st_size
    if size > limits.max_manifest_bytes:
        raise BundleError(f"manifest is {size} bytes; the limit is {limits.max_manifest_bytes}", loc="manifest")
    return _load(mpath.read_bytes(), _DirSource(root, limits), limits)


# --------------------------------------------------------------------------- writers
_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


def _file_stem(i: int, name: str) -> str:
    # Index first: two view names may sanitise to the same text.
    return f"{i:02d}_{_SAFE.sub('_', name)[:64].strip('._') or 'view'}"


def bundle_to_parts(
    bundle: SceneBundle,
    *,
    depth_format: Literal["exr", "npy", "png"] = "exr",
    mask_format: Literal["png", "npy"] = "png",
    depth_png_scale: float | None = None,
) -> tuple[dict, dict[str, bytes]]:
    """Encode a ``SceneBundle`` as (manifest dict, {path: bytes}) -- the upload form of a bundle.

    ``exr`` depth is float32 (lossless for ``View.depth``); ``png`` depth is 16-bit and
    quantised to ``depth_png_scale`` units (default: max depth / 65535, i.e. lossy);
    ``png`` masks are 8-bit when ids <= 255, else 16-bit.  Poses are written in the
    OpenCV convention.  The manifest is validated before it is returned.
    """
    if depth_format not in ("exr", "npy", "png"):
        raise ValueError(f"depth_format must be 'exr', 'npy' or 'png', got {depth_format!r}")
    if mask_format not in ("png", "npy"):
        raise ValueError(f"mask_format must be 'png' or 'npy', got {mask_format!r}")
    files: dict[str, bytes] = {}
    views: list[dict] = []
    for i, v in enumerate(bundle.views):
        stem = _file_stem(i, v.name)
        entry: dict[str, Any] = {"name": v.name, "pose": {"matrix": np.asarray(v.pose, float).tolist(), "convention": "opencv"}}
        if v.intrinsics is not None:
            entry["intrinsics"] = v.intrinsics.model_dump()
        if v.depth is not None:
            path = f"depth/{stem}.{depth_format}"
            spec: dict[str, Any] = {"file": path, "format": depth_format}
            if depth_format == "exr":
                files[path] = images.encode_depth_exr(v.depth)
            elif depth_format == "npy":
                files[path] = images.encode_npy(np.asarray(v.depth, dtype=np.float32))
            else:
                d = np.asarray(v.depth, dtype=np.float64)
                dmax = float(d[np.isfinite(d)].max(initial=0.0))
                scale = depth_png_scale or (dmax / 65535.0 if dmax > 0 else 1.0)
                files[path] = images.encode_depth_png16(d, scale)
                spec["scale"] = scale
            entry["depth"] = spec
        if v.mask is not None:
            path = f"mask/{stem}.{mask_format}"
            files[path] = images.encode_mask_png(v.mask) if mask_format == "png" else images.encode_npy(
                np.asarray(v.mask, dtype=np.int32)
            )
            entry["mask"] = {"file": path, "format": mask_format}
        if v.instance_objects is not None:
            entry["instance_objects"] = {str(k): int(o) for k, o in v.instance_objects.items()}
        views.append(entry)
    manifest: dict[str, Any] = {
        "format": "shadowcorr-bundle",
        "version": 1,
        "name": bundle.name,
        "units": bundle.units,
        "ground_truth": bundle.ground_truth,
        "views": views,
    }
    ps = bundle.point_segments
    if ps is not None:
        arrays = {
            "points": np.asarray(ps.points, dtype=np.float64),
            "lengths": np.asarray(ps.lengths, dtype=np.int64),
            "view": np.asarray(ps.view, dtype=np.int64),
            "instance": np.asarray(ps.instance, dtype=np.int64),
        }
        if ps.object is not None:
            arrays["object"] = np.asarray(ps.object, dtype=np.int64)
        buf = io.BytesIO()
        np.savez_compressed(buf, allow_pickle=False, **arrays)
        files["segments.npz"] = buf.getvalue()
        manifest["segments"] = {"file": "segments.npz"}
    try:
        Manifest.model_validate(manifest)
    except ValidationError as e:  # a bundle we cannot write validly is a caller bug: say exactly what
        raise BundleError(problems_from_validation_error(e, manifest)) from None
    return manifest, files


def write_bundle(
    bundle: SceneBundle,
    out_dir: str | Path,
    *,
    depth_format: Literal["exr", "npy", "png"] = "exr",
    mask_format: Literal["png", "npy"] = "png",
    depth_png_scale: float | None = None,
) -> Path:
    """Write ``bundle`` as a bundle directory; returns the directory.

    The manifest is written last, so an interrupted write leaves no loadable half-bundle.
    """
    out = Path(out_dir)
    manifest, files = bundle_to_parts(
        bundle, depth_format=depth_format, mask_format=mask_format, depth_png_scale=depth_png_scale
    )
    out.mkdir(parents=True, exist_ok=True)
    for rel, data in files.items():
        p = out / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    (out / MANIFEST_NAME).write_text(json.dumps(manifest, indent=1))
    return out


_STORED_SUFFIXES = (".exr", ".png")  # already compressed: deflating again costs CPU for nothing


def write_bundle_archive(
    bundle: SceneBundle,
    path: str | Path,
    *,
    depth_format: Literal["exr", "npy", "png"] = "exr",
    mask_format: Literal["png", "npy"] = "png",
    depth_png_scale: float | None = None,
) -> Path:
    """Write ``bundle`` as a ``.zip`` (or ``.tar`` / ``.tar.gz`` / ``.tgz``, by suffix); returns the path.

    Files sit at the archive root next to ``manifest.json``.
    """
    p = Path(path)
    manifest, files = bundle_to_parts(
        bundle, depth_format=depth_format, mask_format=mask_format, depth_png_scale=depth_png_scale
    )
    files = {MANIFEST_NAME: json.dumps(manifest, indent=1).encode(), **files}
    name = p.name.lower()
    if name.endswith(".zip"):
        with zipfile.ZipFile(p, "w") as zf:
            for rel, data in files.items():
                ct = zipfile.ZIP_STORED if rel.endswith(_STORED_SUFFIXES) else zipfile.ZIP_DEFLATED
                zf.writestr(rel, data, compress_type=ct)
    elif name.endswith((".tar", ".tar.gz", ".tgz")):
        mode = "w" if name.endswith(".tar") else "w:gz"
        with tarfile.open(p, mode) as tf:  # type: ignore[call-overload]
            for rel, data in files.items():
                info = tarfile.TarInfo(rel)
                info.size = len(data)
                info.mode = 0o644
                tf.addfile(info, io.BytesIO(data))
    else:
        raise ValueError(f"archive path must end in .zip, .tar, .tar.gz or .tgz: {str(p)!r}")
    return p

