"""Find the scenes of a dataset directory, and pack each one for upload on demand.

A dataset directory may hold, at any depth:

* bundle directories (a ``manifest.json`` inside) -- sent as manifest + files;
* bundle archives (``.zip``, ``.tar``, ``.tar.gz`` / ``.tgz``, ``.tar.bz2``, ``.tar.xz``) -- sent as is;
* Unreal-layout folders (``SetNNNN_Depth_C.exr`` + ``SetNNNN_Segment_C.png``) -- every set
  is converted on the fly (``shadowcorr.convert.load_ue_scene``) with the chosen cameras;
* ROS bags -- ROS 2 bag directories (``metadata.yaml``), ROS 1 ``.bag`` and ROS 2 ``.mcap``
  files -- converted on the fly (``shadowcorr.convert.rosbag``) with the ``BagOptions``.

Converting needs the ShadowCorr library; a client installed alone finds such scenes and
reports, per scene, the ``pip install`` that would convert them.

The directory given may itself be a bundle, an archive, an Unreal-layout folder or a bag.
Scene names are paths relative to it (``rocks/a.zip``, ``ue/Set2001``), stable across
runs so that an upload can be resumed from its results file.  Discovery only looks
at names; nothing is read until :meth:`SceneSource.load` is called, so a large
dataset never sits in memory at once.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Sequence

from .errors import BundleInputError
from .request_body import MANIFEST_NAME, BundleUpload

if TYPE_CHECKING:
    from shadowcorr.bundle import SceneBundle

__all__ = ["SceneSource", "BagOptions", "discover_scenes", "parse_bag_camera", "ARCHIVE_SUFFIXES", "BAG_SUFFIXES",
           "LIBRARY_INSTALL"]

ARCHIVE_SUFFIXES = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tar.xz")
BAG_SUFFIXES = (".bag", ".mcap")  # ROS 1 bag, ROS 2 MCAP file; a ROS 2 directory is found by its metadata.yaml
_MAX_DEPTH = 8  # deep enough for any sane layout; bounds the walk on a mistaken root like "/"
#: What a user without the library must run to convert Unreal folders and bags locally.
LIBRARY_INSTALL = "pip install shadowcorr  (the library: from a ShadowCorr checkout, `pip install .` at its root)"
# The dataset's file names (SPEC §4); the client must find these scenes without the library.
_UE_DEPTH_FILE = re.compile(r"^Set(\d+)_Depth_(\d+)\.exr$")
def parse_bag_camera(text: str) -> str:
    """Check a ``NAME=DEPTH_TOPIC,MASK_TOPIC[,INFO_TOPIC]`` camera spec and return it without the
    spaces around its parts (the library's ``BagCamera.parse`` rule, which converts it later):
    no part empty or holding a space, no comma in the name, no ``=`` in a topic."""
    name, sep, topics = text.partition("=")
    name, parts = name.strip(), [t.strip() for t in topics.split(",")]
    if (not sep or not name or "," in name or len(parts) not in (2, 3)
            or any(not p or "=" in p for p in parts) or any(c.isspace() for c in name + "".join(parts))):
        raise ValueError(f"camera must be NAME=DEPTH_TOPIC,MASK_TOPIC[,INFO_TOPIC], got {text!r}")
    return f"{name}={','.join(parts)}"


@dataclass(frozen=True)
class BagOptions:
    """How bags are converted (the options of ``shadowcorr convert rosbag``)."""

    cameras: tuple[str, ...] = ()  # NAME=DEPTH_TOPIC,MASK_TOPIC[,INFO_TOPIC]; () = found by topic layout
    fixed_frame: str = "map"
    sync_tolerance: float = 0.0
    max_views: int | None = None
    every: int = 1

    def load(self, path: Path) -> "SceneBundle":
        from shadowcorr.convert.rosbag import BagCamera, load_rosbag_scene

        cameras = [BagCamera.parse(c) for c in self.cameras] or None
        return load_rosbag_scene(path, cameras, fixed_frame=self.fixed_frame, sync_tolerance=self.sync_tolerance,
                                 max_views=self.max_views, every=self.every)


@dataclass(frozen=True)
class SceneSource:
    """One scene of a dataset, not yet read."""

    name: str
    path: Path
    kind: Literal["bundle_dir", "archive", "unreal", "rosbag"]
    set_id: str | None = None
    cameras: tuple[int, ...] | None = None
    bag: BagOptions | None = None

    @property
    def needs_conversion(self) -> bool:
        """Unreal sets and bags are converted locally (by the library) before they are sent."""
        return self.kind in ("unreal", "rosbag")

    def load(self) -> BundleUpload:
        """Read (and for Unreal sets and bags, convert) the scene into an upload.

        Raises ``BundleInputError`` for an unusable bundle directory, or for a scene to
        convert when the library is not installed, and the library's ``BundleError`` (a
        ``ValueError``) for an Unreal set or a bag that cannot be converted.
        """
        if self.needs_conversion:
            return BundleUpload.from_bundle(self.load_bundle(), name=self.name)
        return BundleUpload.from_path(self.path, name=self.name)

    def load_bundle(self) -> "SceneBundle":
        """Decode the scene locally into a ``SceneBundle`` (to convert it, or to draw a result over it)."""
        try:
            if self.kind == "unreal":
                # The converter needs numpy/OpenEXR/PIL: import it only for datasets that need it.
                from shadowcorr.convert.ue import load_ue_scene

                return load_ue_scene(self.path, self.set_id, list(self.cameras or ()))
            if self.kind == "rosbag":
                return (self.bag or BagOptions()).load(self.path)
            from shadowcorr.io import load_bundle

            return load_bundle(self.path)
        except ModuleNotFoundError as exc:
            what = {"unreal": "converting an Unreal-layout set", "rosbag": "converting a ROS bag"}.get(
                self.kind, "decoding a bundle locally")
            raise BundleInputError(f"{self.name}: {what} needs the ShadowCorr library, which is not installed "
                                   f"(no module {exc.name!r}): {LIBRARY_INSTALL}") from None


def _is_archive(path: Path) -> bool:
    return path.is_file() and path.name.lower().endswith(ARCHIVE_SUFFIXES)


def _unreal_sets(directory: Path) -> dict[str, list[int]]:
    """Set id -> cameras that have both a depth and a mask file (by name only: nothing is read)."""
    names = {f.name for f in directory.iterdir()}
    sets: dict[str, list[int]] = {}
    for name in names:
        m = _UE_DEPTH_FILE.match(name)
        if m and f"Set{m.group(1)}_Segment_{m.group(2)}.png" in names:
            sets.setdefault(m.group(1), []).append(int(m.group(2)))
    return {k: sorted(v) for k, v in sorted(sets.items())}


def _is_bag(path: Path) -> bool:
    if path.is_file():
        return path.suffix in BAG_SUFFIXES
    return path.is_dir() and (path / "metadata.yaml").is_file()


def _scene_name(root: Path, path: Path) -> str:
    rel = path.relative_to(root).as_posix()
    return path.name if rel == "." else rel


def discover_scenes(root: str | os.PathLike[str], cameras: Sequence[int] | None = None, *,
                    bag: BagOptions | None = None) -> list[SceneSource]:
    """Every scene under ``root``, in a stable (sorted) order.

    ``cameras`` selects the cameras of Unreal-layout sets (default: every camera present);
    ``bag`` says how bags are converted (default: cameras found by their topic layout).
    Raises ``FileNotFoundError`` when ``root`` does not exist or holds no scene.
    """
    root = Path(root)
    cams = tuple(int(c) for c in cameras) if cameras else None
    if _is_bag(root):
        return [SceneSource(root.name, root, "rosbag", bag=bag)]
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
        if _is_bag(directory):
            scenes.append(SceneSource(_scene_name(root, directory), directory, "rosbag", bag=bag))
            return  # a ROS 2 bag directory holds its storage files, not scenes
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
            elif _is_bag(child):
                scenes.append(SceneSource(_scene_name(root, child), child, "rosbag", bag=bag))

    walk(root, 0)
    if not scenes:
        raise FileNotFoundError(f"{str(root)!r} holds no bundle directory, bundle archive, Unreal-layout set or ROS bag")
    return scenes
