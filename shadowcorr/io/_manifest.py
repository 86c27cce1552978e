"""Manifest parsing: JSON text within limits, and every file path it names checked before anything is decoded."""

from __future__ import annotations

import json
from typing import Any

from ..errors import BundleError, Problem, view_loc
from ._limits import BundleLimits
from ._sources import FileSource, normalize_bundle_path

def parse_manifest(raw: dict | str | bytes, limits: BundleLimits) -> dict:
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


def raw_file_refs(data: dict) -> list[tuple[str, Any]]:
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


def check_refs(refs: list[tuple[str, Any]], source: FileSource) -> tuple[dict[str, str], list[Problem]]:
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
