"""Find the scenes of a dataset directory, and pack each one for upload on demand.

A dataset directory may hold, at any depth:

* bundle directories (a ``manifest.json`` inside) -- sent as manifest + files;
* bundle archives (``.zip``, ``.tar``, ``.tar.gz`` / ``.tgz``, ``.tar.bz2``, ``.tar.xz``) -- sent as is;
* Unreal-layout folders (``SetNNNN_Depth_C.exr`` + ``SetNNNN_Segment_C.png``) -- every set
  is converted on the fly (``shadowcorr.convert.load_ue_scene``) with the chosen cameras.

The directory given may itself be a bundle, an archive or an Unreal-layout folder.
Scene names are paths relative to it (``rocks/a.zip``, ``ue/Set2001``), stable across
runs so that an upload can be resumed from its results file.  Discovery only looks
at names; nothing is read until :meth:`SceneSource.load` is called, so a large
dataset never sits in memory at once.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Sequence

from .upload import MANIFEST_NAME, BundleUpload

if TYPE_CHECKING:
    from shadowcorr.bundle import SceneBundle

__all__ = ["SceneSource", "discover_scenes", "ARCHIVE_SUFFIXES"]

ARCHIVE_SUFFIXES = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tar.xz")
_MAX_DEPTH = 8  # deep enough for any sane layout; bounds the walk on a mistaken root like "/"


@dataclass(frozen=True)
class SceneSource:
    """One scene of a dataset, not yet read."""

    name: str
    path: Path
    kind: Literal["bundle_dir", "archive", "unreal"]
    set_id: str | None = None
    cameras: tuple[int, ...] | None = None

    def load(self) -> BundleUpload:
        """Read (and for Unreal sets, convert) the scene into an upload.

        Raises ``BundleInputError`` for an unusable bundle directory and the library's
        ``BundleError`` (a ``ValueError``) for an Unreal set that cannot be converted.
        """
        if self.kind == "unreal":
            # The converter needs numpy/OpenEXR/PIL: import it only for datasets that need it.
            from shadowcorr.convert import load_ue_scene

            bundle = load_ue_scene(self.path, self.set_id, list(self.cameras or ()))
            return BundleUpload.from_bundle(bundle, name=self.name)
        return BundleUpload.from_path(self.path, name=self.name)

    def load_bundle(self) -> "SceneBundle":
        """Decode the scene locally into a ``SceneBundle`` (for drawing a result over it)."""
        if self.kind == "unreal":
            from shadowcorr.convert import load_ue_scene

            return load_ue_scene(self.path, self.set_id, list(self.cameras or ()))
        from shadowcorr.io import load_bundle

        return load_bundle(self.path)


def _is_archive(path: Path) -> bool:
    return path.is_file() and path.name.lower().endswith(ARCHIVE_SUFFIXES)


def _unreal_sets(directory: Path) -> dict[str, list[int]]:
    # The file-naming rule belongs to the Unreal converter's side of the library: reuse it.
    from shadowcorr.cli import ue_sets

    return ue_sets(directory)


def _scene_name(root: Path, path: Path) -> str:
    rel = path.relative_to(root).as_posix()
    return path.name if rel == "." else rel


def discover_scenes(root: str | os.PathLike[str], cameras: Sequence[int] | None = None) -> list[SceneSource]:
    """Every scene under ``root``, in a stable (sorted) order.

    ``cameras`` selects the cameras of Unreal-layout sets (default: every camera present).
    Raises ``FileNotFoundError`` when ``root`` does not exist or holds no scene.
    """
    root = Path(root)
    cams = tuple(int(c) for c in cameras) if cameras else None
    if root.is_file():
        return [SceneSource(root.name, root, "archive")]
    if not root.is_dir():
        raise FileNotFoundError(f"{str(root)!r}: no such dataset directory, bundle or archive")
    scenes: list[SceneSource] = []
    seen: set[Path] = set()

    def walk(directory: Path, depth: int) -> None:
        real = directory.resolve()
        if real in seen or depth > _MAX_DEPTH:  # symlinked folders may loop
            return
        seen.add(real)
        if (directory / MANIFEST_NAME).is_file():
            scenes.append(SceneSource(_scene_name(root, directory), directory, "bundle_dir"))
            return  # a bundle's subfolders (depth/, mask/) are its own files, not scenes
        sets = _unreal_sets(directory)
        prefix = "" if directory == root else directory.relative_to(root).as_posix() + "/"
        for set_id, present in sets.items():
            scenes.append(SceneSource(f"{prefix}Set{set_id}", directory, "unreal", set_id, cams or tuple(present)))
        for child in sorted(directory.iterdir()):
            if child.name.startswith("."):
                continue
            if child.is_dir():
                walk(child, depth + 1)
            elif _is_archive(child):
                scenes.append(SceneSource(_scene_name(root, child), child, "archive"))

    walk(root, 0)
    if not scenes:
        raise FileNotFoundError(f"{str(root)!r} holds no bundle directory, bundle archive or Unreal-layout set")
    return scenes
