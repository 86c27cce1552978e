"""ROS bags (ROS 1 ``.bag``; ROS 2 sqlite3 or MCAP) -> ShadowCorr bundles.

Read with the pure-Python ``rosbags`` library: no ROS installation is needed.

What a camera is (``BagCamera``): a depth topic, an instance-mask topic and a
``sensor_msgs/msg/CameraInfo`` topic (by default the ``camera_info`` sibling of the
depth topic: ``/cam0/depth/image_raw`` -> ``/cam0/depth/camera_info``).  Without
explicit cameras, every namespace ``NS`` with ``NS/depth/image_raw``,
``NS/depth/camera_info`` and ``NS/instances/image_raw`` is one (``discover_cameras``).

How a view is made:

* depth is a ``sensor_msgs/msg/Image`` in ``32FC1`` (metres; NaN and +-Inf are
  invalid, REP 117) or ``16UC1`` (millimetres, 0 invalid, REP 118);
* the mask is an ``Image`` of instance ids per pixel (``mono8``/``8UC1``,
  ``mono16``/``16UC1``, ``32SC1``; 0 = background) with the depth image's size and
  ``header.frame_id``;
* depth and mask are paired by ``header.stamp`` -- exactly, or the nearest mask within
  ``sync_tolerance`` seconds; each pair is one view, so a moving camera gives several
  (``every`` / ``max_views`` thin them);
* the pose is the transform from ``fixed_frame`` to the image's ``header.frame_id`` at
  ``header.stamp``, looked up in ``/tf_static`` and ``/tf``: chains of transforms,
  dynamic ones interpolated in time (linear translation, slerp rotation), never
  extrapolated further than ``sync_tolerance``.  The image frame must be an optical
  frame (z forward, x right, y down, REP 103), which is exactly the OpenCV convention
  of a bundle pose;
* intrinsics are ``CameraInfo.k`` (``fx = k[0]``, ``fy = k[4]``, ``cx = k[2]``,
  ``cy = k[5]``) of the camera-info message nearest in time.  An uncalibrated camera
  (``k[0] == 0``) is refused, and so is non-zero distortion ``d``: this converter does
  not undistort, so record rectified images (``image_rect``) with their camera info.

The bundle is in metres (``32FC1`` depth is kept bit for bit; ``16UC1`` becomes
``value / 1000``).  Every problem found is reported at once in a ``RosbagError`` (a
``BundleError``) naming the topics, frames and stamps involved.
"""

from __future__ import annotations

import bisect
import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..bundle import Intrinsics, SceneBundle, View
from ..errors import BundleError, Problem
from ..io import images
from ..io import write_bundle
from ._tf import TransformTree, fmt_stamp, stamp_ns

__all__ = [
    "BagCamera",
    "RosbagError",
    "DEPTH_ENCODINGS",
    "MASK_ENCODINGS",
    "discover_cameras",
    "load_rosbag_scene",
    "convert_rosbag",
    "is_rosbag",
]

log = logging.getLogger(__name__)

IMAGE_TYPE = "sensor_msgs/msg/Image"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
TF_TOPICS = ("/tf", "/tf_static")

#: Depth encoding -> (numpy dtype, metres per stored value).
DEPTH_ENCODINGS: dict[str, tuple[str, float]] = {"32FC1": ("f4", 1.0), "16UC1": ("u2", 0.001)}
#: Mask encoding -> numpy dtype of the instance ids.
MASK_ENCODINGS: dict[str, str] = {"mono8": "u1", "8UC1": "u1", "mono16": "u2", "16UC1": "u2", "32SC1": "i4"}

_DEPTH_SUFFIX = "/depth/image_raw"
_INFO_SUFFIX = "/depth/camera_info"
_MASK_SUFFIX = "/instances/image_raw"


class RosbagError(BundleError):
    """A bag that cannot become a bundle; ``problems`` name topics, frames and stamps."""


@dataclass(frozen=True)
class BagCamera:
    """The topics of one camera in a bag."""

    name: str
    depth_topic: str
    mask_topic: str
    info_topic: str = ""  # "" = the camera_info sibling of the depth topic

    @property
    def camera_info_topic(self) -> str:
        return self.info_topic or self.depth_topic.rsplit("/", 1)[0] + "/camera_info"

    @classmethod
    def parse(cls, text: str) -> "BagCamera":
        """``NAME=DEPTH_TOPIC,MASK_TOPIC[,INFO_TOPIC]`` (the ``--camera`` option).

        Spaces around the parts are ignored; a part may not be empty or hold a space, the name
        no comma and a topic no ``=`` (``shadowcorr-client`` checks the same rule)."""
        name, sep, topics = text.partition("=")
        name, parts = name.strip(), [t.strip() for t in topics.split(",")]
        if (not sep or not name or "," in name or len(parts) not in (2, 3)
                or any(not p or "=" in p for p in parts) or any(c.isspace() for c in name + "".join(parts))):
            raise ValueError(f"camera must be NAME=DEPTH_TOPIC,MASK_TOPIC[,INFO_TOPIC], got {text!r}")
        return cls(name, parts[0], parts[1], parts[2] if len(parts) == 3 else "")


def is_rosbag(path: str | Path) -> bool:
    """Whether ``path`` looks like a bag: a ROS 1 ``.bag`` file, or a ROS 2 bag directory or ``.mcap`` file."""
    p = Path(path)
    if p.is_file():
        return p.suffix in (".bag", ".mcap")
    return p.is_dir() and (p / "metadata.yaml").is_file()


def discover_cameras(topics: Mapping[str, str | None]) -> list[BagCamera]:
    """Cameras laid out as ``NS/depth/image_raw`` + ``NS/depth/camera_info`` + ``NS/instances/image_raw``.

    ``topics`` maps topic name -> message type.  The camera is named after ``NS``
    (slashes become ``_``: ``/rover/front`` -> ``rover_front``).
    """
    cameras = []
    for topic, msgtype in sorted(topics.items()):
        if msgtype != IMAGE_TYPE or not topic.endswith(_DEPTH_SUFFIX):
            continue
        ns = topic[: -len(_DEPTH_SUFFIX)]
        if topics.get(ns + _MASK_SUFFIX) == IMAGE_TYPE and topics.get(ns + _INFO_SUFFIX) == INFO_TYPE:
            name = ns.strip("/").replace("/", "_") or "camera"
            cameras.append(BagCamera(name, topic, ns + _MASK_SUFFIX, ns + _INFO_SUFFIX))
    return cameras


# --------------------------------------------------------------------------- time
# --------------------------------------------------------------------------- images
def _image_array(msg: Any, dtype: str) -> np.ndarray:
    """(H, W) array of a one-channel ``sensor_msgs/Image``, honouring ``step`` and ``is_bigendian``."""
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    data = np.asarray(msg.data, dtype=np.uint8)
    row = width * dt.itemsize
    if step < row or data.size < step * height:
        raise ValueError(f"{width}x{height} {msg.encoding} image needs {row} bytes per row and "
                         f"{step * height} in all; it has step {step} and {data.size} bytes")
    rows = data[: step * height].reshape(height, step)[:, :row]
    return np.ascontiguousarray(rows).view(dt).reshape(height, width).astype(dt.newbyteorder("="))


def _depth_metres(msg: Any) -> np.ndarray:
    dtype, scale = DEPTH_ENCODINGS[msg.encoding]
    raw = _image_array(msg, dtype)
    depth = raw if scale == 1.0 else raw.astype(np.float32) * np.float32(scale)
    return images.clean_depth(depth.astype(np.float32, copy=False), inplace=True)


def _mask_ids(msg: Any) -> np.ndarray:
    ids = _image_array(msg, MASK_ENCODINGS[msg.encoding]).astype(np.int32)
    if ids.min(initial=0) < 0:
        raise ValueError("negative instance ids (0 is background, objects are > 0)")
    return ids


# --------------------------------------------------------------------------- reading
@dataclass
class _Frame:
    """What the first pass keeps of one image message: not its pixels."""

    index: int  # position among the messages of its topic
    stamp: int
    frame_id: str
    encoding: str
    size: tuple[int, int]  # (width, height)


@dataclass
class _Pair:
    camera: BagCamera
    depth: _Frame
    mask: _Frame
    name: str = ""


def _open_reader(bag: Path):
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ModuleNotFoundError as exc:  # pragma: no cover - rosbags is a dependency of the library
        raise BundleError(f"reading ROS bags needs the 'rosbags' package ({exc}): pip install rosbags",
                          loc="bag") from None
    if not bag.exists():
        raise RosbagError(f"no such bag {str(bag)!r}", loc="bag")
    try:
        # Bags without embedded message definitions (old ROS 2 sqlite3) fall back to Humble's.
        return AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    except Exception as exc:  # rosbags' own errors: not a bag, an unknown storage format
        raise RosbagError(f"cannot open {str(bag)!r} as a ROS bag: {exc}", loc="bag") from None


def _distortion_free(info: Any) -> bool:
    d = np.asarray(getattr(info, "d", getattr(info, "D", ())), dtype=np.float64)
    return not np.any(d != 0)


def _calibration(info: Any) -> np.ndarray:
    return np.asarray(getattr(info, "k", getattr(info, "K", ())), dtype=np.float64)


def _pair(depths: list[_Frame], masks: list[_Frame], tolerance_ns: int) -> list[tuple[_Frame, _Frame]]:
    """Each depth image with the mask nearest in stamp (within the tolerance); each mask used once."""
    stamps = [m.stamp for m in masks]
    used: set[int] = set()
    pairs = []
    for d in depths:
        i = bisect.bisect_left(stamps, d.stamp)
        candidates = [j for j in (i - 1, i) if 0 <= j < len(masks) and j not in used]
        if not candidates:
            continue
        j = min(candidates, key=lambda k: abs(stamps[k] - d.stamp))
        if abs(stamps[j] - d.stamp) <= tolerance_ns:
            used.add(j)
            pairs.append((d, masks[j]))
    return pairs


def _thin(pairs: list, every: int, max_views: int | None) -> list:
    kept = pairs[::every]
    if max_views is not None and len(kept) > max_views:
        picks = np.unique(np.round(np.linspace(0, len(kept) - 1, max_views)).astype(int))
        kept = [kept[i] for i in picks]
    return kept


def load_rosbag_scene(
    bag: str | Path,
    cameras: Sequence[BagCamera] | None = None,
    *,
    fixed_frame: str = "map",
    sync_tolerance: float = 0.0,
    max_views: int | None = None,
    every: int = 1,
    ground_truth: Literal["none", "instance"] = "none",
    name: str | None = None,
) -> SceneBundle:
    """Decode a bag into a ``SceneBundle`` (metres; see the module docstring for the rules).

    ``cameras`` default to the ones ``discover_cameras`` finds.  ``sync_tolerance``
    (seconds) is how far apart a depth and a mask stamp may be, and how far a dynamic
    transform may be extrapolated.  ``every`` keeps every k-th pair of a camera and
    ``max_views`` at most that many per camera (evenly spread).  ``ground_truth =
    "instance"`` declares that mask ids are object identities across views (metrics only).
    """
    bag = Path(bag)
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    if max_views is not None and max_views < 1:
        raise ValueError(f"max_views must be >= 1, got {max_views}")
    if sync_tolerance < 0:
        raise ValueError(f"sync_tolerance must be >= 0 s, got {sync_tolerance}")
    tolerance_ns = int(round(sync_tolerance * 1e9))
    reader = _open_reader(bag)
    try:
        reader.open()
    except Exception as exc:  # rosbags' own errors: a corrupt or unsupported bag
        raise RosbagError(f"cannot open {str(bag)!r} as a ROS bag: {exc}", loc="bag") from None
    try:
        topics = {t: info.msgtype for t, info in reader.topics.items()}
        cams = list(cameras) if cameras else discover_cameras(topics)
        if not cams:
            images_found = sorted(t for t, ty in topics.items() if ty == IMAGE_TYPE) or ["none"]
            raise RosbagError(
                f"no camera found in {str(bag)!r}: expected NS{_DEPTH_SUFFIX} + NS{_INFO_SUFFIX} + NS{_MASK_SUFFIX}, "
                f"or give --camera NAME=DEPTH_TOPIC,MASK_TOPIC[,INFO_TOPIC] (image topics: {', '.join(images_found)})",
                loc="bag")
        _check_topics(cams, topics)
        tree, infos, frames = _first_pass(reader, cams, tolerance_ns)
        pairs, problems = _pairs(cams, frames, tolerance_ns, every, max_views)
        views, view_problems = _views(reader, pairs, tree, infos, fixed_frame)
    finally:
        reader.close()
    problems = tree.problems + problems + view_problems
    if problems:
        raise RosbagError(problems)
    return SceneBundle(units="m", views=views, name=name or bag.stem, ground_truth=ground_truth)


def _check_topics(cams: Sequence[BagCamera], topics: Mapping[str, str | None]) -> None:
    problems = []
    names = [c.name for c in cams]
    for dup in sorted({n for n in names if names.count(n) > 1}):
        problems.append(Problem(loc=f"cameras[{dup}]", msg="camera name given twice"))
    for cam in cams:
        for what, topic, want in (("depth", cam.depth_topic, IMAGE_TYPE), ("mask", cam.mask_topic, IMAGE_TYPE),
                                  ("camera_info", cam.camera_info_topic, INFO_TYPE)):
            have = topics.get(topic, "missing")
            if have != want:
                problems.append(Problem(loc=f"cameras[{cam.name}].{what}",
                                        msg=f"topic {topic!r} is {'not in the bag' if have == 'missing' else have}; "
                                            f"expected {want}"))
    if problems:
        raise RosbagError(problems)


def _first_pass(reader: Any, cams: Sequence[BagCamera], tolerance_ns: int):
    """tf tree, camera infos per topic (stamp, msg) and image headers per topic; no pixels kept."""
    tree = TransformTree(tolerance_ns)
    image_topics = {c.depth_topic for c in cams} | {c.mask_topic for c in cams}
    info_topics = {c.camera_info_topic for c in cams}
    wanted = [c for c in reader.connections if c.topic in image_topics | info_topics | set(TF_TOPICS)]
    infos: dict[str, list[tuple[int, Any]]] = {t: [] for t in info_topics}
    frames: dict[str, list[_Frame]] = {t: [] for t in image_topics}
    for conn, _, raw in reader.messages(connections=wanted):
        msg = reader.deserialize(raw, conn.msgtype)
        if conn.topic in TF_TOPICS:
            tree.add(msg, conn.topic == "/tf_static", conn.topic)
        elif conn.topic in info_topics:
            infos[conn.topic].append((stamp_ns(msg.header), msg))
        else:
            frames[conn.topic].append(_Frame(len(frames[conn.topic]), stamp_ns(msg.header),
                                             msg.header.frame_id.lstrip("/"), msg.encoding,
                                             (int(msg.width), int(msg.height))))
    return tree, infos, frames


def _pairs(cams: Sequence[BagCamera], frames: Mapping[str, list[_Frame]], tolerance_ns: int, every: int,
           max_views: int | None) -> tuple[list[_Pair], list[Problem]]:
    problems: list[Problem] = []
    out: list[_Pair] = []
    for cam in cams:
        depths = sorted(frames[cam.depth_topic], key=lambda f: f.stamp)
        masks = sorted(frames[cam.mask_topic], key=lambda f: f.stamp)
        loc = f"cameras[{cam.name}]"
        if not depths or not masks:
            empty = cam.depth_topic if not depths else cam.mask_topic
            problems.append(Problem(loc=loc, msg=f"topic {empty!r} has no message"))
            continue
        pairs = _pair(depths, masks, tolerance_ns)
        if not pairs:
            problems.append(Problem(loc=loc, msg=(
                f"no depth image of {cam.depth_topic!r} has a mask of {cam.mask_topic!r} with the same header.stamp"
                f" (within the sync tolerance of {tolerance_ns / 1e9:g} s); first stamps "
                f"{fmt_stamp(depths[0].stamp)} and {fmt_stamp(masks[0].stamp)}: raise --sync-tolerance")))
            continue
        kept = _thin(pairs, every, max_views)
        for k, (d, m) in enumerate(kept):
            out.append(_Pair(cam, d, m, cam.name if len(kept) == 1 else f"{cam.name}_{k:03d}"))
    return out, problems


def _views(reader: Any, pairs: list[_Pair], tree: TransformTree, infos: Mapping[str, list[tuple[int, Any]]],
           fixed_frame: str) -> tuple[list[View], list[Problem]]:
    """Check every pair's metadata, then decode the pixels of the good ones (second pass over the bag)."""
    problems: list[Problem] = []
    ready: list[tuple[_Pair, Intrinsics, np.ndarray]] = []
    for i, pair in enumerate(pairs):
        loc = f"views[{i}:{pair.name}]"
        found = _check_pair(pair, loc, tree, infos, fixed_frame)
        if isinstance(found, Problem):
            problems.append(found)
        else:
            ready.append((pair, *found))
    if problems:
        return [], problems
    pixels = _read_images(reader, {(p.camera.depth_topic, p.depth.index) for p, _, _ in ready}
                          | {(p.camera.mask_topic, p.mask.index) for p, _, _ in ready})
    views: list[View] = []
    for i, (pair, intrinsics, pose) in enumerate(ready):
        loc = f"views[{i}:{pair.name}]"
        try:
            depth = _depth_metres(pixels[pair.camera.depth_topic, pair.depth.index])
        except ValueError as exc:
            problems.append(Problem(loc=f"{loc}.depth", msg=f"{pair.camera.depth_topic} at {fmt_stamp(pair.depth.stamp)}: {exc}"))
            continue
        try:
            mask = _mask_ids(pixels[pair.camera.mask_topic, pair.mask.index])
        except ValueError as exc:
            problems.append(Problem(loc=f"{loc}.mask", msg=f"{pair.camera.mask_topic} at {fmt_stamp(pair.mask.stamp)}: {exc}"))
            continue
        views.append(View(name=pair.name, pose=pose, intrinsics=intrinsics, depth=depth, mask=mask))
    return views, problems


def _check_pair(pair: _Pair, loc: str, tree: TransformTree, infos: Mapping[str, list[tuple[int, Any]]],
                fixed_frame: str) -> tuple[Intrinsics, np.ndarray] | Problem:
    """Intrinsics and pose of a pair, or the first problem with it."""
    cam, d, m = pair.camera, pair.depth, pair.mask
    at = f"at {fmt_stamp(d.stamp)}"
    if d.encoding not in DEPTH_ENCODINGS:
        return Problem(loc=f"{loc}.depth", msg=f"{cam.depth_topic} {at} has encoding {d.encoding!r}; depth must be "
                                               "32FC1 (metres) or 16UC1 (millimetres)")
    if m.encoding not in MASK_ENCODINGS:
        return Problem(loc=f"{loc}.mask", msg=f"{cam.mask_topic} {at} has encoding {m.encoding!r}; an instance mask "
                                              f"must be one of {', '.join(MASK_ENCODINGS)}")
    if d.size != m.size:
        return Problem(loc=f"{loc}.mask", msg=f"{cam.mask_topic} {at} is {m.size[0]}x{m.size[1]} but the depth image "
                                              f"{cam.depth_topic} is {d.size[0]}x{d.size[1]}")
    if d.frame_id != m.frame_id:
        return Problem(loc=f"{loc}.mask", msg=f"{cam.mask_topic} {at} is in frame {m.frame_id!r} but the depth image "
                                              f"{cam.depth_topic} is in {d.frame_id!r}")
    if d.size[0] < 1 or d.size[1] < 1:
        return Problem(loc=f"{loc}.depth", msg=f"{cam.depth_topic} {at} is an empty image")
    recorded = infos.get(cam.camera_info_topic) or []
    if not recorded:
        return Problem(loc=f"{loc}.intrinsics", msg=f"no CameraInfo on {cam.camera_info_topic!r}: the camera's "
                                                    "intrinsics are unknown (give INFO_TOPIC in --camera)")
    stamp, info = min(recorded, key=lambda si: abs(si[0] - d.stamp))
    k = _calibration(info)
    info_at = f"{cam.camera_info_topic} at {fmt_stamp(stamp)}"
    if k.size != 9 or not np.all(np.isfinite(k)) or k[0] <= 0 or k[4] <= 0:
        return Problem(loc=f"{loc}.intrinsics", msg=f"{info_at} is uncalibrated (k = {k.tolist()}; fx = k[0] and "
                                                    "fy = k[4] must be > 0): calibrate the camera")
    if not _distortion_free(info):
        d_coeffs = np.asarray(getattr(info, "d", getattr(info, "D", ())), dtype=np.float64).tolist()
        return Problem(loc=f"{loc}.intrinsics", msg=(
            f"{info_at} has distortion {info.distortion_model!r} d = {d_coeffs}; this converter does not undistort: "
            "record rectified images (e.g. image_proc's image_rect) with their camera info, whose d is zero"))
    if (int(info.width), int(info.height)) not in ((0, 0), d.size):
        return Problem(loc=f"{loc}.intrinsics", msg=f"{info_at} is for {info.width}x{info.height} images but "
                                                    f"{cam.depth_topic} is {d.size[0]}x{d.size[1]}")
    try:
        pose = tree.lookup(fixed_frame, d.frame_id, d.stamp)
    except LookupError as exc:
        return Problem(loc=f"{loc}.pose", msg=f"{cam.depth_topic} {at} in frame {d.frame_id!r}: {exc}")
    intrinsics = Intrinsics(fx=float(k[0]), fy=float(k[4]), cx=float(k[2]), cy=float(k[5]),
                            width=d.size[0], height=d.size[1])
    return intrinsics, pose


def _read_images(reader: Any, wanted: Iterable[tuple[str, int]]) -> dict[tuple[str, int], Any]:
    """The image messages at (topic, index) positions, deserialised (second pass: only these keep pixels)."""
    wanted = set(wanted)
    if not wanted:  # an empty connection filter would mean "every message" to rosbags
        return {}
    topics = {t for t, _ in wanted}
    counters = dict.fromkeys(topics, 0)
    out: dict[tuple[str, int], Any] = {}
    for conn, _, raw in reader.messages(connections=[c for c in reader.connections if c.topic in topics]):
        key = (conn.topic, counters[conn.topic])
        counters[conn.topic] += 1
        if key in wanted:
            out[key] = reader.deserialize(raw, conn.msgtype)
    return out


def convert_rosbag(bag: str | Path, out_dir: str | Path, cameras: Sequence[BagCamera] | None = None,
                   **options: Any) -> Path:
    """Write a bag as a bundle directory (float32 EXR depth in metres, PNG masks); returns ``out_dir``.

    ``options`` are those of :func:`load_rosbag_scene`.
    """
    bundle = load_rosbag_scene(bag, cameras, **options)
    log.info("%s: %d views (%s)", bag, len(bundle.views), ", ".join(v.name for v in bundle.views))
    return write_bundle(bundle, Path(out_dir), depth_format="exr", mask_format="png")

