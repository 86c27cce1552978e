"""Pack a scene into the multipart body of ``POST /correspond``.

The service takes either a ``bundle`` part (a .zip / .tar archive) or a ``manifest``
part plus one file part per file the manifest names, the part's *filename* being the
path in the manifest (docs/CONTRACTS.md).  :class:`BundleUpload` holds those parts in
memory, fully read, so a retried request re-sends exactly the same bytes and a file
edited between attempts cannot produce a torn upload.

Bundle *directories* are sent as manifest + files, not zipped: the files (EXR, PNG) are
already compressed, so an archive would only cost client CPU and server memory.  Only
the files the manifest references are sent, and a path that would leave the bundle
directory is refused here, before anything is read -- the same rule the server applies.

Packing an in-memory ``SceneBundle`` needs :mod:`shadowcorr.io` (numpy, OpenEXR); it is
imported only then, so talking to a server from a path or bytes stays light.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Union

from .errors import BundleInputError

if TYPE_CHECKING:  # only for annotations: importing the library types is not needed to send paths or bytes
    from shadowcorr.bundle import SceneBundle

__all__ = ["BundleUpload", "BundleSource", "as_upload", "archive_content_type"]

MANIFEST_NAME = "manifest.json"

#: (form field, (filename, content, content type)) -- the shape httpx takes for ``files=``.
FilePart = tuple[str, tuple[str, bytes, str]]

_ARCHIVE_TYPES = (
    (".zip", "application/zip"),
    (".tar.gz", "application/gzip"),
    (".tgz", "application/gzip"),
    (".tar.bz2", "application/x-bzip2"),
    (".tar.xz", "application/x-xz"),
    (".tar", "application/x-tar"),
)


def archive_content_type(data: bytes, filename: str = "") -> tuple[str, str]:
    """(suggested filename, content type) of archive bytes, from the name or the magic bytes."""
    low = filename.lower()
    for suffix, ctype in _ARCHIVE_TYPES:
        if low.endswith(suffix):
            return filename, ctype
    # No telling suffix (bytes given directly): sniff, so the server's log and any proxy see a sane type.
    if data.startswith(b"PK\x03\x04") or data.startswith(b"PK\x05\x06"):
        return filename or "bundle.zip", "application/zip"
    if data.startswith(b"\x1f\x8b"):
        return filename or "bundle.tar.gz", "application/gzip"
    if data.startswith(b"BZh"):
        return filename or "bundle.tar.bz2", "application/x-bzip2"
    if data.startswith(b"\xfd7zXZ\x00"):
        return filename or "bundle.tar.xz", "application/x-xz"
    if data[257:262] == b"ustar":
        return filename or "bundle.tar", "application/x-tar"
    return filename or "bundle", "application/octet-stream"


def _safe_relative(path: str) -> str:
    """Normalise a manifest path, refusing anything that would leave the bundle directory."""
    if not path or "\x00" in path or "\\" in path:
        raise ValueError(f"unusable path {path!r}")
    if path.startswith("/") or (len(path) > 1 and path[1] == ":"):
        raise ValueError(f"absolute path {path!r}; paths are relative to the bundle")
    parts = [p for p in path.split("/") if p not in ("", ".")]
    if not parts or ".." in parts:
        raise ValueError(f"path {path!r} leaves the bundle or names no file")
    return "/".join(parts)


def _file_refs(node: Any, loc: str = "") -> list[tuple[str, str]]:
    """(loc, path) of every ``{"file": "..."}`` in a manifest, at any depth.

    Walking generically (rather than listing views[*].depth / .mask / segments) keeps
    the client right when the manifest format gains another file-bearing field.
    """
    refs: list[tuple[str, str]] = []
    if isinstance(node, dict):
        if isinstance(node.get("file"), str):
            refs.append((f"{loc}.file" if loc else "file", node["file"]))
        for key, value in node.items():
            refs.extend(_file_refs(value, f"{loc}.{key}" if loc else str(key)))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            # Views are located as the library locates them, ``views[1:cam2]``: users think in view names.
            name = value.get("name") if loc == "views" and isinstance(value, dict) else None
            refs.extend(_file_refs(value, f"{loc}[{i}:{name}]" if isinstance(name, str) and name else f"{loc}[{i}]"))
    return refs


@dataclass(frozen=True)
class BundleUpload:
    """One scene, packed as the multipart parts of a ``POST /correspond``.

    Build it with :meth:`from_path`, :meth:`from_archive_bytes`, :meth:`from_parts`
    or :meth:`from_bundle` (or let :func:`as_upload` choose).
    """

    name: str
    parts: tuple[FilePart, ...]

    @property
    def nbytes(self) -> int:
        """Payload bytes (without multipart framing)."""
        return sum(len(content) for _, (_, content, _) in self.parts)

    @property
    def is_archive(self) -> bool:
        return len(self.parts) == 1 and self.parts[0][0] == "bundle"

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_archive_bytes(cls, data: bytes, *, filename: str = "", name: str | None = None) -> "BundleUpload":
        """A .zip / .tar(.gz) archive held in memory, sent as the ``bundle`` part."""
        if not data:
            raise BundleInputError("the bundle archive is empty")
        fname, ctype = archive_content_type(bytes(data), filename)
        return cls(name=name or fname, parts=(("bundle", (fname, bytes(data), ctype)),))

    @classmethod
    def from_parts(cls, manifest: Mapping[str, Any] | str | bytes, files: Mapping[str, bytes], *,
                   name: str | None = None) -> "BundleUpload":
        """A manifest (dict or JSON text) and its files keyed by manifest path."""
        if isinstance(manifest, Mapping):
            manifest_bytes = json.dumps(manifest).encode()
            label = manifest.get("name")
        else:
            manifest_bytes = manifest.encode() if isinstance(manifest, str) else bytes(manifest)
            label = None
        parts: list[FilePart] = [("manifest", (MANIFEST_NAME, manifest_bytes, "application/json"))]
        parts += [("files", (path, bytes(content), "application/octet-stream")) for path, content in files.items()]
        return cls(name=name or (label if isinstance(label, str) else "bundle"), parts=tuple(parts))

    @classmethod
    def from_path(cls, path: str | os.PathLike[str], *, name: str | None = None) -> "BundleUpload":
        """A bundle directory (or its ``manifest.json``) or a bundle archive file."""
        p = Path(path)
        if p.is_file() and p.name == MANIFEST_NAME:
            p = p.parent
        if p.is_dir():
            return cls._from_directory(p, name=name)
        if p.is_file():
            return cls.from_archive_bytes(p.read_bytes(), filename=p.name, name=name or p.name)
        raise BundleInputError(f"{str(p)!r}: no such bundle directory or archive")

    @classmethod
    def _from_directory(cls, root: Path, *, name: str | None) -> "BundleUpload":
        mpath = root / MANIFEST_NAME
        if not mpath.is_file():
            raise BundleInputError(f"{str(root)!r} holds no {MANIFEST_NAME}: not a bundle directory")
        raw = mpath.read_bytes()
        try:
            manifest = json.loads(raw.decode("utf-8-sig"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            # Send it anyway: the server reports JSON errors with line and column, in the
            # same shape as every other bundle problem.  There are simply no files to attach.
            manifest = {}
        real_root = root.resolve()
        files: dict[str, bytes] = {}
        problems: list[str] = []
        for loc, ref in _file_refs(manifest):
            try:
                rel = _safe_relative(ref)
            except ValueError as exc:
                problems.append(f"{loc}: {exc}")
                continue
            if rel in files:
                continue  # several views may share one file; send it once
            target = root / rel
            # Symlinks are fine inside the bundle (a dataset may share files) but not out of it.
            if not target.resolve().is_relative_to(real_root):
                problems.append(f"{loc}: {ref!r} resolves outside the bundle directory")
            elif not target.is_file():
                problems.append(f"{loc}: file {ref!r} not found in {str(root)!r}")
            else:
                files[rel] = target.read_bytes()
        if problems:
            raise BundleInputError(f"cannot pack bundle {str(root)!r}: " + "; ".join(problems))
        return cls.from_parts(raw, files, name=name or root.name)

    @classmethod
    def from_bundle(cls, bundle: "SceneBundle", *, name: str | None = None) -> "BundleUpload":
        """An in-memory ``SceneBundle`` (float32 EXR depth, PNG masks: lossless)."""
        from shadowcorr.io import bundle_to_parts  # numpy/OpenEXR: only needed for in-memory bundles

        manifest, files = bundle_to_parts(bundle, depth_format="exr", mask_format="png")
        return cls.from_parts(manifest, files, name=name or bundle.name)


#: Everything :func:`as_upload` understands.
BundleSource = Union[str, os.PathLike, bytes, bytearray, memoryview, BundleUpload, "SceneBundle"]


def as_upload(source: BundleSource) -> BundleUpload:
    """Turn any supported bundle form into a :class:`BundleUpload`."""
    if isinstance(source, BundleUpload):
        return source
    if isinstance(source, (str, os.PathLike)):
        return BundleUpload.from_path(source)
    if isinstance(source, (bytes, bytearray, memoryview)):
        return BundleUpload.from_archive_bytes(bytes(source))
    if type(source).__name__ == "SceneBundle":
        # Checked by name first so that sending a path never imports the library's data model.
        from shadowcorr.bundle import SceneBundle

        if isinstance(source, SceneBundle):
            return BundleUpload.from_bundle(source)
    raise TypeError(
        f"cannot send a {type(source).__name__}: pass a bundle directory or archive path, archive bytes, "
        "a SceneBundle or a BundleUpload"
    )
