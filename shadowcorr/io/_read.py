"""Load scene bundles: directories, ``.zip`` / ``.tar(.gz|.bz2|.xz)`` archives,
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

The loaders here compose the pieces: :mod:`._archives` (archive safety),
:mod:`._manifest` (manifest text and paths), :mod:`._views` (images per view),
:mod:`._segments_npz` (the point flavour), :mod:`._sources` (where files come from).
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from typing import IO
from pathlib import Path

from pydantic import ValidationError

from ..bundle import Manifest, SceneBundle, View
from ..errors import BundleError, Problem, SceneLimitError, problems_from_validation_error
from ._archives import read_archive, split_root
from ._limits import MANIFEST_NAME, BundleLimits
from ._manifest import check_refs, parse_manifest, raw_file_refs
from ._segments_npz import read_segments_npz
from ._sources import DirSource, FileSource, PartsSource, normalize_bundle_path
from ._views import decode_view

def _load(manifest: dict | str | bytes, source: FileSource, limits: BundleLimits) -> SceneBundle:
    """Shared core: parse + validate the manifest, check every path, decode every file."""
    data = parse_manifest(manifest, limits)
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
    paths, path_problems = check_refs(raw_file_refs(data), source)
    problems += path_problems
    if man is None:
        raise BundleError(problems)
    # With a valid manifest, keep going past bad paths: the files that *are* there are
    # decoded too, so one response lists missing files and undecodable ones together.

    # Decoded images cost memory in proportion to their declared size, however small their
    # files: refuse the scene before the first image is decoded.
    pixels = sum(v.intrinsics.width * v.intrinsics.height for v in man.views
                 if v.intrinsics is not None and (v.depth is not None or v.mask is not None))
    if pixels > limits.max_scene_pixels:
        raise SceneLimitError("max_scene_pixels", pixels, limits.max_scene_pixels,
                              "pixels of all views' images together")
    warnings: list[str] = []
    views: list[View] = []
    for i, spec in enumerate(man.views):
        view, vp = decode_view(i, spec, paths, source, limits, warnings)
        problems += vp
        if view is not None:
            views.append(view)
    point_segments = None
    if man.segments is not None and "segments.file" in paths:
        try:
            point_segments = read_segments_npz(
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


def _load_archive(fh: IO[bytes], archive_size: int, limits: BundleLimits) -> SceneBundle:
    files, skipped = read_archive(fh, archive_size, limits)
    manifest, rest = split_root(files)
    return _load(manifest, PartsSource(rest, "archive", skipped), limits)



def load_bundle_from_parts(
    manifest: dict | str | bytes, files: Mapping[str, bytes], *, limits: BundleLimits | None = None
) -> SceneBundle:
    """Load a bundle from a manifest and in-memory files keyed by their manifest path.

    This is what the HTTP service uses for multipart uploads (one part per file, the
    part's filename = the path in the manifest).  Keys are normalised like manifest
    paths; unsafe keys are problems.  Raises ``BundleError`` listing every problem, or
    ``SceneLimitError`` as :func:`load_bundle` does.  ``limits`` defaults to
    :meth:`BundleLimits.local` (a server passes its own).
    """
    limits = limits or BundleLimits.local()
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
    return _load(manifest, PartsSource(norm, "uploaded files"), limits)


def load_bundle(source: str | Path | bytes, *, limits: BundleLimits | None = None) -> SceneBundle:
    """Load a bundle from a directory, a ``manifest.json`` path, a .zip/.tar(.gz) path, or raw archive bytes.

    Raises ``BundleError`` (a ``ValueError``) whose ``.problems`` lists every problem found,
    or :class:`~shadowcorr.errors.SceneLimitError` for a scene larger than ``limits`` allow
    (``max_scene_pixels``, ``max_scene_points``), before the images or points are decoded.
    ``limits`` defaults to :meth:`BundleLimits.local`: a user's own files are loaded whatever their
    size (the HTTP service passes its own limits).
    """
    limits = limits or BundleLimits.local()
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
    return _load(mpath.read_bytes(), DirSource(root, limits), limits)
