"""Where a bundle's files come from: in-memory parts or a local directory, by safe relative path.

Manifest paths and archive member names are normalised by one rule
(:func:`normalize_bundle_path`): relative, ``/``-separated, never leaving the bundle.  A
directory source refuses symlinks that resolve outside its folder and budgets the bytes read.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

from ..errors import BundleError
from ._limits import BundleLimits

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


class FileSource:
    """Where the files a manifest names come from.  ``read`` raises ``BundleError`` at ``loc``."""

    def read(self, rel: str, loc: str) -> bytes:  # pragma: no cover - interface
        raise NotImplementedError

    def exists(self, rel: str) -> bool:  # pragma: no cover - interface
        raise NotImplementedError

    def unreferenced(self, used: set[str]) -> list[str]:
        return []


class PartsSource(FileSource):
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


class DirSource(FileSource):
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
