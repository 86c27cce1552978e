"""Archive safety: the members of a ``.zip`` / ``.tar(.gz|.bz2|.xz)`` that a bundle may use, read within limits.

Archives come from untrusted uploads.  Sizes are checked before decompressing (member
count, declared sizes, compression ratio) and the bytes actually decompressed are capped
too, because headers can lie; member names must be relative and stay inside the bundle;
tar links, devices and fifos are refused.  Of a zip and of an uncompressed tar only the
manifest and the files it names are read (and decompressed); a compressed tar is one
compressed stream, so every member is decompressed on the way through it (capped), and
only the manifest and the files it names are kept.  :func:`read_archive` returns the members, :func:`split_root` finds the
manifest at the root or in one top-level folder.
"""

from __future__ import annotations

import bz2
import gzip
import io
import lzma
import re
import stat
import tarfile
import zipfile
import zlib
from collections import Counter
from collections.abc import Callable
from typing import IO, Any

from ..errors import BundleError, Problem
from ._limits import MANIFEST_NAME, MEMBER_RATIO_MIN_BYTES, BundleLimits
from ._manifest import parse_manifest, raw_file_refs
from ._sources import normalize_bundle_path

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
            refs = raw_file_refs(parse_manifest(data, self.limits))
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
        problems += _listing_problems([n for n, _ in wanted], limits)
        if problems:
            return {}, problems, []
        manifest_problems: list[Problem] = []

        def read_manifest(info: zipfile.ZipInfo) -> bytes:
            data, problem = _zip_member(zf, info, limits.max_manifest_bytes + 1)
            manifest_problems.extend([problem] if problem is not None else [])
            return data

        wanted, skipped = _split_by_manifest(wanted, read_manifest, limits)
        if manifest_problems:
            return {}, manifest_problems, []
        declared = sum(i.file_size for _, i in wanted)
        problems += _size_problems(0, declared, sum(i.compress_size for _, i in wanted) or archive_size, limits)
        for _, info in wanted:
            ratio = info.file_size / max(info.compress_size, 1)
            if info.file_size > MEMBER_RATIO_MIN_BYTES and ratio > limits.max_compression_ratio:
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


def _split_by_manifest(listed: list[tuple[str, Any]], read_manifest: Callable[[Any], bytes],
                       limits: BundleLimits) -> tuple[list[tuple[str, Any]], list[str]]:
    """Of an archive's listed ``(name, member)``, those its manifest names (the manifest included)
    and the names of the others.  With several manifest candidates or none, only those are
    wanted: the loader says so, from the candidates alone."""
    named = _Named(limits)
    manifests = [(n, m) for n, m in listed if _is_manifest(n)]
    if len(manifests) == 1:
        named.learn(manifests[0][0], read_manifest(manifests[0][1]))
    else:
        named.names = set()
    return [(n, m) for n, m in listed if named.wants(n)], [n for n, _ in listed if not named.wants(n)]


def _listing_problems(names: list[str], limits: BundleLimits) -> list[Problem]:
    """Duplicate names and too many files, from an archive's listing."""
    counts = Counter(names)
    dups = sorted(n for n, c in counts.items() if c > 1)
    out = [Problem(loc="archive", msg=f"duplicate members {dups[:5]}")] if dups else []
    if len(names) > limits.max_files:
        out.append(Problem(loc="archive", msg=f"archive holds {len(names)} files; the limit is {limits.max_files}"))
    return out


def _zip_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, max_bytes: int) -> tuple[bytes, Problem | None]:
    """At most ``max_bytes`` of one member, or the problem that stopped its extraction."""
    try:
        with zf.open(info) as m:
            return m.read(max_bytes), None
    # zlib.error: corrupt deflate data (a flipped byte) surfaces only while decompressing.
    except (zipfile.BadZipFile, OSError, NotImplementedError, RuntimeError, ValueError, EOFError, lzma.LZMAError,
            zlib.error) as e:
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
    """Like ``_read_zip``, for a compressed tar (or an unseekable one): the stream can only be
    read through, so members it holds before the manifest are kept until the manifest says
    whether it names them, and members after it that it does not name are decompressed and
    passed over unkept (the decompressed stream stays capped)."""
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
                name = _tar_member(m, problems)
                if name is None:
                    continue
                where = f"archive[{m.name!r}]"
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
    except (tarfile.TarError, OSError, EOFError, lzma.LZMAError, zlib.error, ValueError) as e:
        problems.append(Problem(loc="archive", msg=f"not a readable .tar archive: {e}"))
    early = [n for n in files if not named.wants(n)]  # kept before the manifest came, not named by it
    for n in early:
        del files[n]
    return files, problems, skipped + early


def _tar_member(m: tarfile.TarInfo, problems: list[Problem]) -> str | None:
    """The normalised name of a tar member a bundle may use; ``None`` for a directory or macOS
    litter (skipped) and for a link, special file or unsafe name (problem recorded)."""
    if _SKIP.search(m.name) or m.isdir():
        return None
    where = f"archive[{m.name!r}]"
    name = _member_name(m.name, problems)
    if name is None:
        return None
    if m.issym() or m.islnk():
        problems.append(Problem(loc=where, msg=f"links are not allowed (-> {m.linkname!r})"))
        return None
    if not m.isreg() or m.issparse():
        problems.append(Problem(loc=where, msg="only regular files are allowed (device, fifo or sparse member)"))
        return None
    return name


def _read_plain_tar(fh: IO[bytes], limits: BundleLimits) -> tuple[dict[str, bytes], list[Problem], list[str]]:
    """Like ``_read_zip``, for an uncompressed tar in a seekable file: the headers are listed
    first (tarfile seeks over each member's data), then only the manifest and the members it
    names are read; the others are never read at all."""
    problems: list[Problem] = []
    files: dict[str, bytes] = {}
    max_entries = 4 * limits.max_files + 16
    try:
        with tarfile.open(fileobj=fh, mode="r:") as tf:
            listed: list[tuple[str, tarfile.TarInfo]] = []
            for entries, m in enumerate(tf, start=1):
                if entries > max_entries:
                    return {}, [Problem(loc="archive", msg=f"archive has more than {max_entries} entries")], []
                name = _tar_member(m, problems)
                if name is not None:
                    listed.append((name, m))
            problems += _listing_problems([n for n, _ in listed], limits)
            if problems:
                return {}, problems, []
            wanted, skipped = _split_by_manifest(listed, lambda m: _tar_data(tf, m, limits.max_manifest_bytes + 1),
                                                 limits)
            declared = sum(m.size for _, m in wanted)
            if declared > limits.max_total_bytes:
                return {}, _size_problems(0, declared, declared, limits), []
            for name, m in wanted:
                data = _tar_data(tf, m, m.size)
                if len(data) != m.size:
                    return {}, [Problem(loc=f"archive[{m.name!r}]", msg="member is truncated")], []
                files[name] = data
    except (tarfile.TarError, OSError, EOFError, ValueError) as e:
        return {}, [Problem(loc="archive", msg=f"not a readable .tar archive: {e}")], []
    return files, problems, skipped


def _tar_data(tf: tarfile.TarFile, m: tarfile.TarInfo, max_bytes: int) -> bytes:
    ex = tf.extractfile(m)
    return ex.read(max_bytes) if ex is not None else b""


def read_archive(fh: IO[bytes], archive_size: int, limits: BundleLimits) -> tuple[dict[str, bytes], list[str]]:
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
    elif kind == "tar" and fh.seekable():
        files, problems, skipped = _read_plain_tar(fh, limits)
    else:
        files, problems, skipped = _read_tar(fh, kind, archive_size, limits)
    if problems:
        raise BundleError(problems)
    return files, skipped


def split_root(files: dict[str, bytes]) -> tuple[bytes, dict[str, bytes]]:
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
