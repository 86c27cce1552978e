"""Request bodies -> bundle sources, parsed in a worker process (never on the event loop).

A ``POST /correspond`` body is one of

* ``multipart/form-data`` with a part ``bundle`` (a .zip / .tar archive), or a part
  ``manifest`` (manifest.json text) plus one file part per file the manifest names,
  the part's *filename* being the path in the manifest;
* a bare archive (``application/zip``, ``application/x-tar``, ``application/gzip`` or
  ``application/octet-stream``), handy for ``curl --data-binary @scene.zip``.

Parsing is streaming-free on purpose: the main process has already read (and counted)
the whole body, and the parse runs where CPU time is cheap, in a worker.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header

__all__ = [
    "ARCHIVE_TYPES",
    "BodyError",
    "ParsedBody",
    "Part",
    "content_kind",
    "parse_body",
    "parse_multipart",
]

#: Content types accepted as a bare archive body.
ARCHIVE_TYPES = ("application/zip", "application/x-zip-compressed", "application/x-tar", "application/gzip",
                 "application/x-gzip", "application/octet-stream")


class BodyError(ValueError):
    """The body cannot be understood as a form / bundle upload (HTTP 400 or 415)."""

    def __init__(self, message: str, loc: str = "body", status: int = 400) -> None:
        super().__init__(message)
        self.loc = loc
        self.status = status


@dataclass
class Part:
    """One part of a multipart/form-data body."""

    name: str
    filename: str | None
    content_type: str | None
    data: bytes


@dataclass
class ParsedBody:
    """What the loader needs: an archive, or a manifest plus files keyed by manifest path."""

    archive: bytes | None = None
    manifest: bytes | None = None
    files: dict[str, bytes] = field(default_factory=dict)


def content_kind(content_type: str | None) -> str:
    """``'multipart'``, ``'archive'`` or raise 415: a cheap header check for the main process."""
    if not content_type:
        raise BodyError("missing Content-Type; send multipart/form-data (or a .zip/.tar body)", "headers.content-type", 415)
    ctype, params = parse_options_header(content_type)
    ctype_s = ctype.decode("latin-1").lower()
    if ctype_s == "multipart/form-data":
        if not params.get(b"boundary"):
            raise BodyError("multipart/form-data without a boundary parameter", "headers.content-type", 400)
        return "multipart"
    if ctype_s in ARCHIVE_TYPES:
        return "archive"
    raise BodyError(
        f"unsupported Content-Type {ctype_s!r}; send multipart/form-data with a 'bundle' part or a 'manifest' "
        "part plus file parts, or a bare .zip/.tar body",
        "headers.content-type",
        415,
    )


def parse_multipart(body: bytes, content_type: str, *, max_parts: int, max_header_bytes: int = 16 * 1024) -> list[Part]:
    """Split a complete multipart/form-data body into parts.

    Raises :class:`BodyError` for a malformed body: bad boundary, a truncated body
    (no closing boundary), a part without a ``Content-Disposition: form-data; name=...``
    header, or more than ``max_parts`` parts.
    """
    _, params = parse_options_header(content_type)
    boundary = params.get(b"boundary")
    if not boundary:
        raise BodyError("multipart/form-data without a boundary parameter", "headers.content-type")

    parts: list[Part] = []
    headers: dict[str, bytes] = {}
    header_field = bytearray()
    header_value = bytearray()
    chunks: list[bytes] = []
    state = {"ended": False, "header_bytes": 0}

    def on_part_begin() -> None:
        headers.clear()
        chunks.clear()
        if len(parts) >= max_parts:
            raise BodyError(f"more than {max_parts} parts in the form", "body")

    def on_header_field(data: bytes, start: int, end: int) -> None:
        header_field.extend(data[start:end])
        state["header_bytes"] += end - start

    def on_header_value(data: bytes, start: int, end: int) -> None:
        header_value.extend(data[start:end])
        state["header_bytes"] += end - start
        if state["header_bytes"] > max_header_bytes:
            raise BodyError(f"part headers larger than {max_header_bytes} bytes", f"body.parts[{len(parts)}]")

    def on_header_end() -> None:
        headers[bytes(header_field).decode("latin-1").lower()] = bytes(header_value)
        header_field.clear()
        header_value.clear()

    def on_part_data(data: bytes, start: int, end: int) -> None:
        chunks.append(data[start:end])

    def on_part_end() -> None:
        index = len(parts)
        disposition = headers.get("content-disposition")
        if disposition is None:
            raise BodyError("part has no Content-Disposition header", f"body.parts[{index}]")
        kind, opts = parse_options_header(disposition)
        if kind.lower() != b"form-data" or b"name" not in opts:
            raise BodyError("part is not 'Content-Disposition: form-data' with a name", f"body.parts[{index}]")
        name = opts[b"name"].decode("utf-8", "replace")
        filename = opts[b"filename"].decode("utf-8", "replace") if b"filename" in opts else None
        ctype = headers.get("content-type")
        parts.append(Part(name, filename, ctype.decode("latin-1") if ctype else None, b"".join(chunks)))
        chunks.clear()
        state["header_bytes"] = 0

    def on_end() -> None:
        state["ended"] = True

    callbacks = {
        "on_part_begin": on_part_begin,
        "on_part_data": on_part_data,
        "on_part_end": on_part_end,
        "on_header_field": on_header_field,
        "on_header_value": on_header_value,
        "on_header_end": on_header_end,
        "on_end": on_end,
    }
    try:
        parser = MultipartParser(boundary, callbacks)  # type: ignore[arg-type]
        parser.write(body)
        parser.finalize()
    except MultipartParseError as e:
        raise BodyError(f"malformed multipart/form-data body: {e}") from None
    if not state["ended"]:
        raise BodyError("truncated multipart/form-data body: the closing boundary is missing")
    return parts


def parse_body(body: bytes, content_type: str, *, max_files: int) -> ParsedBody:
    """Interpret an upload: which part is the archive, the manifest, the files.

    Rules (each violation is a :class:`BodyError` naming the part):
    a ``bundle`` part excludes ``manifest`` and file parts; a ``manifest`` part may
    also arrive as a file part named ``manifest.json``; every other part must carry a
    filename (its manifest path) and no filename may repeat.
    """
    if content_kind(content_type) == "archive":
        if not body:
            raise BodyError("empty request body; expected a .zip or .tar bundle")
        return ParsedBody(archive=body)

    parts = parse_multipart(body, content_type, max_parts=max_files + 2)
    if not parts:
        raise BodyError("the form has no parts; send a 'bundle' part, or a 'manifest' part plus file parts")
    out = ParsedBody()
    for i, part in enumerate(parts):
        loc = f"form[{part.name!r}]" if part.filename is None else f"form[{part.name!r}:{part.filename!r}]"
        if part.name == "bundle":
            if out.archive is not None:
                raise BodyError("more than one 'bundle' part", loc)
            if not part.data:
                raise BodyError("the 'bundle' part is empty", loc)
            out.archive = part.data
        elif part.name == "manifest":
            if out.manifest is not None:
                raise BodyError("more than one 'manifest' part", loc)
            out.manifest = part.data
        elif part.filename is not None:
            if part.filename in out.files:
                raise BodyError(f"file {part.filename!r} uploaded twice", loc)
            out.files[part.filename] = part.data
        else:
            raise BodyError(
                f"unexpected form field {part.name!r}: options go in the query string; "
                "files need a filename (their path in the manifest)",
                loc,
            )
    if out.manifest is None and "manifest.json" in out.files:
        out.manifest = out.files.pop("manifest.json")
    if out.archive is not None and (out.manifest is not None or out.files):
        raise BodyError("send either a 'bundle' archive part or a 'manifest' with file parts, not both", "form")
    if out.archive is None and out.manifest is None:
        what = f" (got file parts {sorted(out.files)[:5]})" if out.files else ""
        raise BodyError(f"no 'bundle' part and no 'manifest' part{what}", "form")
    return out
