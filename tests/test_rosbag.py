"""ROS bags -> bundles: real bags written with ``rosbags``' own writers (ROS 2 sqlite3 and MCAP, ROS 1).

The scene is the real sample (set 2001, cameras 0, 2, 4, 6), halved in resolution to keep
the bags small, expressed in metres.  The reference bundle holds exactly the pixels the
bag carries (16-bit millimetre depth is quantised on both sides), so "the converted bundle
gives the same labels" compares the converter, not two different inputs.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import shadowcorr
from shadowcorr.bundle import Intrinsics, SceneBundle, View
from shadowcorr.cli import main as cli_main
from shadowcorr.convert import load_ue_scene
from shadowcorr.convert.rosbag import BagCamera, RosbagError, discover_cameras, load_rosbag_scene
from shadowcorr.io import load_bundle
from shadowcorr.poses import look_at_pose

from .paths import SAMPLE_DIR

rosbags = pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

needs_sample = pytest.mark.skipif(not (SAMPLE_DIR / "Set2001_Depth_0.exr").is_file(), reason="sample data missing")

STAMP = 1_700_000_000_000_000_000  # ns
# Optical frame (z forward, x right, y down) in its camera link frame (x forward, y left, z up): REP 103.
LINK_TO_OPTICAL = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
# Sample cameras -> (depth encoding, mask encoding): every supported encoding is exercised.
ENCODINGS = {0: ("32FC1", "mono8"), 2: ("16UC1", "mono16"), 4: ("32FC1", "32SC1"), 6: ("16UC1", "16UC1")}
DTYPES = {"32FC1": "<f4", "16UC1": "<u2", "mono8": "u1", "mono16": "<u2", "32SC1": "<i4", "rgb8": "u1"}


def rigid(yaw: float, pitch: float, translation) -> np.ndarray:
    """A pose with a non-trivial rotation, so frame chains are really composed."""
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    m = np.eye(4)
    m[:3, :3] = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    m[:3, 3] = translation
    return m


MAP_TO_ODOM = rigid(0.3, 0.0, [1.5, -2.0, 0.1])


# --------------------------------------------------------------------------- writing bags
class BagWriter:
    """Messages of one bag in the ROS 1 or ROS 2 flavour, written with the rosbags writers."""

    def __init__(self, path: Path, kind: str) -> None:
        self.ros1 = kind == "ros1"
        self.ts = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self.ts.types:  # rosbags' Noetic store lacks it: define it as ROS 1 does
            self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
        if self.ros1:
            self.writer: Any = Writer1(path)
        else:
            plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(path, version=9, storage_plugin=plugin)
        self.connections: dict[str, Any] = {}
        self.types = self.ts.types

    def __enter__(self) -> "BagWriter":
        self.writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.writer.close()

    def write(self, topic: str, msg: Any, stamp: int) -> None:
        msgtype = msg.__msgtype__
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
        data = self.ts.serialize_ros1(msg, msgtype) if self.ros1 else self.ts.serialize_cdr(msg, msgtype)
        self.writer.write(self.connections[topic], stamp, data)

    def header(self, stamp: int, frame: str) -> Any:
        time = self.types["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
        fields = {"stamp": time, "frame_id": frame}
        if self.ros1:
            fields["seq"] = 0
        return self.types["std_msgs/msg/Header"](**fields)

    def image(self, stamp: int, frame: str, array: np.ndarray, encoding: str) -> Any:
        raw = np.ascontiguousarray(array.astype(DTYPES[encoding]))
        return self.types["sensor_msgs/msg/Image"](
            header=self.header(stamp, frame), height=raw.shape[0], width=raw.shape[1], encoding=encoding,
            is_bigendian=0, step=raw.shape[1] * raw.itemsize, data=np.frombuffer(raw.tobytes(), np.uint8))

    def camera_info(self, stamp: int, frame: str, intr: Intrinsics, *, d=(0.0,) * 5, k: Any = None) -> Any:
        k = [intr.fx, 0, intr.cx, 0, intr.fy, intr.cy, 0, 0, 1] if k is None else k
        p = [k[0], 0, k[2], 0, 0, k[4], k[5], 0, 0, 0, 1, 0]
        cls = self.types["sensor_msgs/msg/CameraInfo"]
        case = str.upper if self.ros1 else str.lower  # ROS 1 names the matrices D, K, R, P
        roi = self.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return cls(header=self.header(stamp, frame), height=intr.height, width=intr.width,
                   distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi,
                   **{case("d"): np.asarray(d, float), case("k"): np.asarray(k, float),
                      case("r"): np.eye(3).ravel(), case("p"): np.asarray(p, float)})

    def tf(self, topic: str, stamp: int, transforms: list[tuple[str, str, np.ndarray]]) -> None:
        t = self.types
        items = []
        for parent, child, m in transforms:
            q = Rotation.from_matrix(m[:3, :3]).as_quat()  # (x, y, z, w)
            items.append(t["geometry_msgs/msg/TransformStamped"](
                header=self.header(stamp, parent), child_frame_id=child,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=t["geometry_msgs/msg/Vector3"](x=m[0, 3], y=m[1, 3], z=m[2, 3]),
                    rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))))
        self.write(topic, t["tf2_msgs/msg/TFMessage"](transforms=items), stamp)


def publish_base(bag: BagWriter, stamp: int, odom_to_base: np.ndarray) -> None:
    """odom -> base_link on /tf as two samples around ``stamp`` that interpolate to ``odom_to_base`` exactly.

    The samples differ by a rotation about the base's z axis and a translation: only a
    correct slerp + linear interpolation gives the pose at ``stamp``.
    """
    for sign in (-1, 1):
        wobble = rigid(sign * 0.2, 0.0, [0.0, 0.0, 0.0])
        sample = odom_to_base @ wobble
        sample[:3, 3] = odom_to_base[:3, 3] + sign * np.array([0.3, -0.1, 0.05])
        bag.tf("/tf", stamp + sign * 50_000_000, [("odom", "base_link", sample)])


def write_scene_bag(path: Path, kind: str, views: list[dict[str, Any]], *, moving: bool = False) -> Path:
    """A bag of ``views`` (dicts: ns, stamp, pose (camera-to-map, OpenCV), intrinsics, depth, mask, encodings).

    Static: map -> odom, and per camera base_link -> NS_link -> NS_optical.  Dynamic:
    odom -> base_link around each stamp.  ``moving``: one base pose per stamp carries the
    camera (its links stay fixed); otherwise one base pose holds all cameras still.
    """
    base_to_link = rigid(-0.4, 0.1, [0.2, 0.0, 0.5])
    fixed_base = rigid(1.1, 0.0, [0.4, 0.7, 0.0])
    with BagWriter(path, kind) as bag:
        static = [("map", "odom", MAP_TO_ODOM)]
        for ns in dict.fromkeys(v["ns"] for v in views):
            link, optical = f"{ns.strip('/')}_link", f"{ns.strip('/')}_optical"
            first = next(v for v in views if v["ns"] == ns)
            if moving:
                static.append(("base_link", link, base_to_link))
            else:
                # map->odom->base->link->optical must equal the camera pose.
                odom_to_cam = np.linalg.inv(MAP_TO_ODOM) @ first["pose"]
                static.append(("base_link", link, np.linalg.inv(fixed_base) @ odom_to_cam @ np.linalg.inv(LINK_TO_OPTICAL)))
            static.append((link, optical, LINK_TO_OPTICAL))
        bag.tf("/tf_static", views[0]["stamp"] - 10**9, static)
        bases = {}
        for v in views:
            bases[v["stamp"]] = (np.linalg.inv(MAP_TO_ODOM) @ v["pose"] @ np.linalg.inv(LINK_TO_OPTICAL)
                                 @ np.linalg.inv(base_to_link)) if moving else fixed_base
        for stamp, base in sorted(bases.items(), key=lambda sb: sb[0]):
            publish_base(bag, stamp, base)
        for v in views:
            ns, stamp, intr = v["ns"], v["stamp"], v["intrinsics"]
            frame = f"{ns.strip('/')}_optical"
            depth_enc, mask_enc = v.get("encodings", ("32FC1", "mono16"))
            bag.write(f"{ns}/depth/camera_info", v.get("info") or bag.camera_info(stamp, frame, intr), stamp)
            bag.write(f"{ns}/depth/image_raw", bag.image(stamp, v.get("depth_frame", frame), v["depth"], depth_enc), stamp)
            bag.write(f"{ns}/instances/image_raw", bag.image(stamp + v.get("mask_offset", 0), frame, v["mask"], mask_enc),
                      stamp)
    return path


# --------------------------------------------------------------------------- the sample scene
@pytest.fixture(scope="module")
def sample_views() -> list[dict[str, Any]]:
    """Cameras 0, 2, 4, 6 of the sample at half resolution, in metres, with the pixels a bag carries."""
    ue = load_ue_scene(SAMPLE_DIR, 2001, list(ENCODINGS))
    views = []
    for view in ue.views:
        cam = int(view.name.removeprefix("cam"))
        depth_enc, mask_enc = ENCODINGS[cam]
        depth_m = view.depth[::2, ::2] * np.float32(0.01)
        depth = depth_m if depth_enc == "32FC1" else np.round(depth_m * 1000).astype(np.uint16)
        pose = view.pose.copy()
        pose[:3, 3] *= 0.01
        k = view.intrinsics
        intr = Intrinsics(fx=k.fx / 2, fy=k.fy / 2, cx=k.cx / 2, cy=k.cy / 2, width=k.width // 2, height=k.height // 2)
        views.append({"ns": f"/cam{cam}", "stamp": STAMP, "pose": pose, "intrinsics": intr,
                      "depth": depth, "mask": view.mask[::2, ::2], "encodings": (depth_enc, mask_enc)})
    return views


@pytest.fixture(scope="module")
def reference(sample_views) -> tuple[SceneBundle, list[int]]:
    """The bundle the bags are made from (metres, instance ground truth) and its labels."""
    views = []
    for v in sample_views:
        depth = v["depth"] if v["encodings"][0] == "32FC1" else v["depth"].astype(np.float32) * np.float32(0.001)
        views.append(View(name=v["ns"].strip("/"), pose=v["pose"], intrinsics=v["intrinsics"],
                          depth=depth.astype(np.float32), mask=v["mask"].astype(np.int32)))
    bundle = SceneBundle(units="m", views=views, name="sample_m", ground_truth="instance")
    return bundle, shadowcorr.correspond(bundle).labels


def assert_same_scene(converted: SceneBundle, expected: SceneBundle) -> None:
    assert [v.name for v in converted.views] == [v.name for v in expected.views]
    assert converted.units == "m"
    for got, want in zip(converted.views, expected.views):
        np.testing.assert_array_equal(got.depth, want.depth, err_msg=got.name)
        np.testing.assert_array_equal(got.mask, want.mask, err_msg=got.name)
        assert got.intrinsics == want.intrinsics
        np.testing.assert_allclose(got.pose, want.pose, atol=1e-9, err_msg=got.name)


@needs_sample
@pytest.mark.parametrize("kind", ["sqlite3", "mcap", "ros1"])
def test_bag_of_the_sample_scene_gives_the_same_labels(tmp_path, kind, sample_views, reference) -> None:
    bundle, labels = reference
    bag = write_scene_bag(tmp_path / ("scene.bag" if kind == "ros1" else "scene"), kind, sample_views)
    converted = load_rosbag_scene(bag, ground_truth="instance")  # cameras discovered from the topic layout
    assert_same_scene(converted, bundle)
    result = shadowcorr.correspond(converted)
    assert result.labels == labels
    assert result.metrics["average_purity"] > 90  # the ids really are objects: metrics agree with the labels


@needs_sample
def test_moving_camera_gives_one_view_per_stamp_with_interpolated_poses(tmp_path, sample_views, reference) -> None:
    bundle, labels = reference
    # One camera, recorded at four stamps from the four sample poses: the base moves, the links are fixed.
    moving = [{**v, "ns": "/rover/front", "stamp": STAMP + i * 10**9} for i, v in enumerate(sample_views)]
    bag = write_scene_bag(tmp_path / "moving", "mcap", moving, moving=True)
    (camera,) = discover_cameras({t: "sensor_msgs/msg/Image" for t in ("/rover/front/depth/image_raw",
                                                                      "/rover/front/instances/image_raw")}
                                 | {"/rover/front/depth/camera_info": "sensor_msgs/msg/CameraInfo"})
    assert camera == BagCamera("rover_front", "/rover/front/depth/image_raw", "/rover/front/instances/image_raw",
                               "/rover/front/depth/camera_info")
    converted = load_rosbag_scene(bag)
    assert [v.name for v in converted.views] == [f"rover_front_{k:03d}" for k in range(4)]
    expected = SceneBundle(units="m", name="x", views=[replace(v, name=f"rover_front_{k:03d}")
                                                       for k, v in enumerate(bundle.views)])
    assert_same_scene(converted, expected)
    assert shadowcorr.correspond(converted).labels == labels
    # Thinning: every second pair, then at most one.
    assert [v.name for v in load_rosbag_scene(bag, every=2).views] == ["rover_front_000", "rover_front_001"]
    thinned = load_rosbag_scene(bag, every=2, max_views=1)
    assert [v.name for v in thinned.views] == ["rover_front"]
    np.testing.assert_allclose(thinned.views[0].pose, bundle.views[0].pose, atol=1e-9)


@needs_sample
def test_cli_converts_a_bag_with_explicit_cameras(tmp_path, sample_views, reference, capsys) -> None:
    bundle, _ = reference
    views = [{**v, "mask_offset": 3_000_000} for v in sample_views[:2]]  # masks 3 ms after their depth
    bag = write_scene_bag(tmp_path / "two", "sqlite3", views)
    out = tmp_path / "B"
    args = ["convert", "rosbag", str(bag), "--out", str(out), "--fixed-frame", "map", "--sync-tolerance", "0.005"]
    for v in views:
        ns = v["ns"]
        args += ["--camera", f"{ns.strip('/')}={ns}/depth/image_raw,{ns}/instances/image_raw,{ns}/depth/camera_info"]
    assert cli_main(args) == 0, capsys.readouterr().err
    loaded = load_bundle(out)
    expected = SceneBundle(units="m", views=bundle.views[:2])
    assert_same_scene(loaded, expected)
    # Without the tolerance the 3 ms offset leaves no pair: a clear error naming the topics and stamps.
    assert cli_main(args[:6] + args[8:] + ["--out", str(tmp_path / "C")]) == 2
    err = capsys.readouterr().err
    assert "/cam0/instances/image_raw" in err and "same header.stamp" in err and "--sync-tolerance" in err


# --------------------------------------------------------------------------- malformed bags
TINY = Intrinsics(fx=20.0, fy=20.0, cx=8.0, cy=6.0, width=16, height=12)


def tiny_view(**changes: Any) -> dict[str, Any]:
    depth = np.full((12, 16), 2.0, np.float32)
    mask = np.zeros((12, 16), np.int32)
    mask[3:9, 4:12] = 7
    view = {"ns": "/cam0", "stamp": STAMP, "pose": look_at_pose([0, -3, 1], [0, 0, 0]), "intrinsics": TINY,
            "depth": depth, "mask": mask, "encodings": ("32FC1", "mono8")}
    view.update(changes)
    return view


def convert_error(tmp_path: Path, view: dict[str, Any], **options: Any) -> str:
    bag = write_scene_bag(tmp_path / "bad", "sqlite3", [view])
    with pytest.raises(RosbagError) as info:
        load_rosbag_scene(bag, **options)
    return str(info.value)


def test_tiny_bag_converts(tmp_path) -> None:
    bundle = load_rosbag_scene(write_scene_bag(tmp_path / "ok", "sqlite3", [tiny_view()]))
    (view,) = bundle.views
    np.testing.assert_allclose(view.pose, look_at_pose([0, -3, 1], [0, 0, 0]), atol=1e-9)
    assert view.intrinsics == TINY and int(view.mask.max()) == 7


def test_wrong_depth_encoding_is_named(tmp_path) -> None:
    msg = convert_error(tmp_path, tiny_view(depth=np.zeros((12, 48), np.uint8), encodings=("rgb8", "mono8")))
    assert "/cam0/depth/image_raw" in msg and "'rgb8'" in msg and "32FC1" in msg


def test_wrong_mask_encoding_is_named(tmp_path) -> None:
    msg = convert_error(tmp_path, tiny_view(encodings=("32FC1", "32FC1")))
    assert "/cam0/instances/image_raw" in msg and "'32FC1'" in msg and "mono8" in msg


def test_mask_of_another_size_is_refused(tmp_path) -> None:
    msg = convert_error(tmp_path, tiny_view(mask=np.zeros((6, 8), np.int32)))
    assert "8x6" in msg and "16x12" in msg and "/cam0/instances/image_raw" in msg


def test_mask_in_another_frame_is_refused(tmp_path) -> None:
    msg = convert_error(tmp_path, tiny_view(depth_frame="cam0_link"))
    assert "'cam0_optical'" in msg and "'cam0_link'" in msg


def test_missing_transform_names_frames_and_stamp(tmp_path) -> None:
    msg = convert_error(tmp_path, tiny_view(), fixed_frame="world")
    assert "'world'" in msg and "'cam0_optical'" in msg and "1700000000.000000000 s" in msg


def test_transform_outside_the_recorded_time_is_not_extrapolated(tmp_path) -> None:
    bag = BagWriter(tmp_path / "late", "sqlite3")
    view = tiny_view()
    with bag:
        bag.tf("/tf_static", STAMP, [("map", "odom", np.eye(4)), ("base_link", "cam0_optical", np.eye(4))])
        publish_base(bag, STAMP + 10**9, np.eye(4))  # the base is only known a second later
        bag.write("/cam0/depth/camera_info", bag.camera_info(STAMP, "cam0_optical", TINY), STAMP)
        bag.write("/cam0/depth/image_raw", bag.image(STAMP, "cam0_optical", view["depth"], "32FC1"), STAMP)
        bag.write("/cam0/instances/image_raw", bag.image(STAMP, "cam0_optical", view["mask"], "mono8"), STAMP)
    with pytest.raises(RosbagError, match=r"'odom' -> 'base_link' is known from 1700000000.95"):
        load_rosbag_scene(tmp_path / "late")


def test_missing_camera_info(tmp_path) -> None:
    bag = BagWriter(tmp_path / "noinfo", "mcap")
    view = tiny_view()
    with bag:
        bag.tf("/tf_static", STAMP, [("map", "cam0_optical", np.eye(4))])
        bag.write("/cam0/depth/image_raw", bag.image(STAMP, "cam0_optical", view["depth"], "32FC1"), STAMP)
        bag.write("/cam0/instances/image_raw", bag.image(STAMP, "cam0_optical", view["mask"], "mono8"), STAMP)
    # Discovery needs the camera_info topic: it says what layout it looked for.
    with pytest.raises(RosbagError, match=r"no camera found .*NS/depth/camera_info.*/cam0/depth/image_raw"):
        load_rosbag_scene(tmp_path / "noinfo")
    camera = BagCamera.parse("cam0=/cam0/depth/image_raw,/cam0/instances/image_raw")
    with pytest.raises(RosbagError, match=r"cameras\[cam0\]\.camera_info: topic '/cam0/depth/camera_info' is not in the bag"):
        load_rosbag_scene(tmp_path / "noinfo", [camera])


def test_uncalibrated_camera_is_refused(tmp_path) -> None:
    messages = BagWriter(tmp_path / "unused", "sqlite3")  # never opened: only builds messages
    msg = convert_error(tmp_path, tiny_view(info=messages.camera_info(STAMP, "cam0_optical", TINY, k=[0.0] * 9)))
    assert "/cam0/depth/camera_info" in msg and "uncalibrated" in msg


def test_distortion_is_refused_with_the_way_out(tmp_path) -> None:
    messages = BagWriter(tmp_path / "unused", "sqlite3")  # never opened: only builds messages
    info = messages.camera_info(STAMP, "cam0_optical", TINY, d=(-0.1, 0.01, 0.0, 0.0, 0.0))
    msg = convert_error(tmp_path, tiny_view(info=info))
    assert "does not undistort" in msg and "image_rect" in msg and "-0.1" in msg


def test_camera_option_is_parsed_strictly() -> None:
    assert BagCamera.parse("left=/a/depth,/a/mask").camera_info_topic == "/a/camera_info"
    assert BagCamera.parse("left=/a/depth,/a/mask,/a/info").camera_info_topic == "/a/info"
    for bad in ("left", "left=/a", "=/a,/b", "left=/a,,/c", "left=/a,/b,/c,/d"):
        with pytest.raises(ValueError, match="NAME=DEPTH_TOPIC,MASK_TOPIC"):
            BagCamera.parse(bad)


def test_client_finds_bags_and_converts_them_with_the_camera_options(tmp_path) -> None:
    from shadowcorr_client import BagOptions, discover_scenes

    data = tmp_path / "data"
    write_scene_bag(data / "site" / "run_ros2", "sqlite3", [tiny_view()])
    write_scene_bag(data / "run.bag", "ros1", [tiny_view()])
    mcap_dir = write_scene_bag(tmp_path / "mcap_dir", "mcap", [tiny_view()])
    (mcap_file,) = mcap_dir.glob("*.mcap")
    (data / "site" / "single.mcap").write_bytes(mcap_file.read_bytes())  # a bare ROS 2 MCAP file
    options = BagOptions(cameras=("front=/cam0/depth/image_raw,/cam0/instances/image_raw",))
    scenes = discover_scenes(data, bag=options)
    assert [(s.name, s.kind) for s in scenes] == [("run.bag", "rosbag"), ("site/run_ros2", "rosbag"),
                                                   ("site/single.mcap", "rosbag")]
    for scene in scenes:
        (view,) = scene.load_bundle().views
        assert view.name == "front" and int(view.mask.max()) == 7
    upload = scenes[0].load()
    assert upload.parts[0][0] == "manifest" and b'"front"' in upload.parts[0][1][1]


def test_not_a_bag_is_a_clear_error(tmp_path) -> None:
    (tmp_path / "x.bag").write_bytes(b"not a bag")
    with pytest.raises(RosbagError, match=r"bag: cannot open '.*x.bag' as a ROS bag"):
        load_rosbag_scene(tmp_path / "x.bag")
    with pytest.raises(RosbagError, match=r"bag: no such bag '.*missing'"):
        load_rosbag_scene(tmp_path / "missing")
