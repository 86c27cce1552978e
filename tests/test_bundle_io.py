"""Bundle loading / writing: round trips and the many ways an upload can be bad.

Everything here is synthetic and tiny (32x24 views) so the file runs in about a second.
"""

from __future__ import annotations

import io
import json
import os
import tarfile
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from shadowcorr.bundle import Intrinsics, PointSegments, SceneBundle, View
from shadowcorr.errors import BundleError, Problem
from shadowcorr.io import (
    BundleLimits,
    bundle_to_parts,
    load_bundle,
    load_bundle_from_parts,
    write_bundle,
    write_bundle_archive,
)
from shadowcorr.io import images

from .harness import zip_files

W, H = 32, 24


def _rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    r = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    return r


def make_bundle(n_views: int = 2, seed: int = 0) -> SceneBundle:
    rng = np.random.default_rng(seed)
    views = []
    for i in range(n_views):
        pose = np.eye(4)
        pose[:3, :3] = _rot_z(30.0 * i)
        pose[:3, 3] = [10.0 * i, -5.0, 3.0]
        depth = rng.uniform(50, 300, size=(H, W)).astype(np.float32)
        depth[0, 0] = 0.0  # invalid pixels survive as 0
        mask = np.zeros((H, W), np.int32)
        mask[4:12, 5:15] = 3
        mask[14:20, 18:30] = 7 + i
        views.append(
            View(
                name=f"cam{i}",
                pose=pose,
                intrinsics=Intrinsics(fx=40.0, fy=41.0, cx=W / 2, cy=H / 2, width=W, height=H),
                depth=depth,
                mask=mask,
            )
        )
    return SceneBundle(units="cm", views=views, name="synthetic", ground_truth="instance")


def assert_same(a: SceneBundle, b: SceneBundle, depth_atol: float = 0.0) -> None:
    assert (a.units, a.name, a.ground_truth) == (b.units, b.name, b.ground_truth)
    assert [v.name for v in a.views] == [v.name for v in b.views]
    for va, vb in zip(a.views, b.views):
        np.testing.assert_allclose(va.pose, vb.pose, atol=1e-12)
        assert va.intrinsics == vb.intrinsics
        assert vb.depth.dtype in (np.float32, np.float16) and vb.mask.dtype in (np.uint8, np.uint16, np.int32)
        np.testing.assert_allclose(va.depth, vb.depth, atol=depth_atol, rtol=0)
        np.testing.assert_array_equal(va.mask, vb.mask)


def parts(bundle: SceneBundle | None = None, **kw) -> tuple[dict, dict[str, bytes]]:
    return bundle_to_parts(bundle or make_bundle(), **kw)


def expect_error(fn, *needles: str) -> BundleError:
    """Call ``fn``; it must raise BundleError whose text contains every needle."""
    with pytest.raises(BundleError) as ei:
        fn()
    err = ei.value
    assert isinstance(err, ValueError) and err.problems
    text = str(err)
    for n in needles:
        assert n in text, f"{n!r} not in {text!r}"
    return err


def tar_bytes(members: list[tarfile.TarInfo | tuple[str, bytes]], mode: str = "w") -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode=mode) as tf:
        for m in members:
            if isinstance(m, tarfile.TarInfo):
                tf.addfile(m)
            else:
                info = tarfile.TarInfo(m[0])
                info.size = len(m[1])
                tf.addfile(info, io.BytesIO(m[1]))
    return buf.getvalue()


def with_manifest(manifest: dict, files: dict[str, bytes]) -> dict[str, bytes]:
    return {"manifest.json": json.dumps(manifest).encode(), **files}


# --------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("depth_format,mask_format", [("exr", "png"), ("npy", "npy")])
def test_roundtrip_directory(tmp_path: Path, depth_format: str, mask_format: str) -> None:
    b = make_bundle()
    out = write_bundle(b, tmp_path / "b", depth_format=depth_format, mask_format=mask_format)
    assert (out / "manifest.json").is_file()
    loaded = load_bundle(out)
    assert_same(b, loaded)
    assert loaded.warnings == []
    # a path to manifest.json works too
    assert_same(b, load_bundle(out / "manifest.json"))


@pytest.mark.parametrize("high_id", [255, 256, 65535])
def test_mask_png_round_trip_is_exact_in_8_and_16_bits(high_id: int) -> None:
    rng = np.random.default_rng(high_id)
    mask = rng.integers(0, 40, (90, 120))
    mask[10:20, 30:70] = high_id  # flat regions, as a segmenter writes them
    data = images.encode_mask_png(mask)
    image = Image.open(io.BytesIO(data))
    assert image.mode == ("P" if high_id <= 255 else "I;16")
    np.testing.assert_array_equal(images.read_mask_png(data), mask)
    if high_id <= 255:  # the palette is grey: a viewer shows each id as that grey level
        np.testing.assert_array_equal(np.asarray(image.convert("L")), mask)


def test_roundtrip_png_depth_is_quantised(tmp_path: Path) -> None:
    b = make_bundle()
    loaded = load_bundle(write_bundle(b, tmp_path / "b", depth_format="png", depth_png_scale=0.01))
    assert_same(b, loaded, depth_atol=0.005 + 1e-4)
    assert loaded.views[0].depth[0, 0] == 0.0


def test_exr_depth_is_written_as_half_floats_only_when_every_value_is_one() -> None:
    rng = np.random.default_rng(0)
    half_exact = (rng.uniform(50, 900, (60, 80)).astype(np.float16)).astype(np.float32)
    half_exact[0, :3] = [0.0, np.nan, np.inf]
    not_half = half_exact.copy()
    not_half[5, 5] += 0.01  # one value between two half floats
    beyond = half_exact.copy()
    beyond[7, 7] = 70000.0  # beyond the half range (65504)
    sizes = {}
    for name, depth in (("half", half_exact), ("float", not_half), ("beyond", beyond)):
        data = images.encode_depth_exr(depth)
        sizes[name] = len(data)
        np.testing.assert_array_equal(images.read_exr_channel(data), depth)  # exact either way
    assert sizes["half"] < 0.7 * sizes["float"] and sizes["half"] < 0.7 * sizes["beyond"]
    lossy = images.read_exr_channel(images.encode_depth_exr(not_half, half=True))
    assert not np.array_equal(lossy, not_half, equal_nan=True) and np.array_equal(lossy, half_exact, equal_nan=True)
    # Half floats are DWAB-compressed, which would quantise a colour-named channel: such a channel
    # gets PXR24 instead, so the depth survives whatever the channel is called.
    for channel in ("Z", "depth.Z", "R", "Y", "view.b"):
        data = images.encode_depth_exr(half_exact, channel=channel)
        np.testing.assert_array_equal(images.read_exr_channel(data, channel=channel), half_exact)



def test_half_float_depth_loads_as_stored_and_is_cleaned_like_float32() -> None:
    """read_depth keeps half-float EXR depth as float16 (scale 1) with the same values and the
    same invalid pixels as the float32 reading; a scale makes it float32."""
    rng = np.random.default_rng(1)
    depth = rng.uniform(50, 900, (40, 60)).astype(np.float16).astype(np.float32)
    depth[0, :8] = [0.0, -0.0, -3.0, np.nan, np.inf, -np.inf, np.float16(6e-8), 65504.0]  # a half subnormal, the largest half
    data = images.encode_depth_exr(depth)
    kept = images.read_depth(data, "exr")
    assert kept.dtype == np.float16
    expected = images.clean_depth(depth)
    np.testing.assert_array_equal(kept.astype(np.float32), expected)
    assert np.array_equal(kept[0, :8].astype(np.float32), [0, 0, 0, 0, 0, 0, np.float16(6e-8), 65504])
    assert not np.signbit(kept).any()  # -0 and negatives become +0, the one invalid value
    assert images.has_valid_depth(kept) and not images.has_valid_depth(images.clean_depth(depth[0, 1:6].copy()))
    scaled = images.read_depth(data, "exr", scale=0.5)
    assert scaled.dtype == np.float32
    np.testing.assert_array_equal(scaled, images.clean_depth(depth * np.float32(0.5)))

@pytest.mark.parametrize("suffix", [".zip", ".tar.gz", ".tar"])
def test_roundtrip_archives(tmp_path: Path, suffix: str) -> None:
    b = make_bundle()
    path = write_bundle_archive(b, tmp_path / f"b{suffix}")
    assert_same(b, load_bundle(path))
    assert_same(b, load_bundle(path.read_bytes()))


def test_archive_with_single_top_level_folder() -> None:
    m, f = parts()
    data = zip_files({f"scene/{k}": v for k, v in with_manifest(m, f).items()} | {"__MACOSX/._x": b"junk"})
    assert_same(make_bundle(), load_bundle(data))


def test_load_from_parts_accepts_dict_str_bytes_and_warns_on_extra_files() -> None:
    m, f = parts()
    for manifest in (m, json.dumps(m), json.dumps(m).encode()):
        assert_same(make_bundle(), load_bundle_from_parts(manifest, f))
    b = load_bundle_from_parts(m, {**f, "./notes.txt": b"hi"})
    assert any("notes.txt" in w for w in b.warnings)


def test_opengl_pose_and_range_depth_are_converted() -> None:
    m, f = parts(make_bundle(1))
    cv = np.array(m["views"][0]["pose"]["matrix"])
    m["views"][0]["pose"] = {"matrix": (cv @ np.diag([1.0, -1, -1, 1])).tolist(), "convention": "opengl"}
    ref = make_bundle(1).views[0]
    # Store the ray distance; the loader must give back the z-depth.
    u = (np.arange(W) - W / 2) / 40.0
    v = (np.arange(H) - H / 2) / 41.0
    rng = ref.depth * np.sqrt(u[None, :] ** 2 + v[:, None] ** 2 + 1)
    f["r.npy"] = images.encode_npy(rng.astype(np.float32))
    m["views"][0]["depth"] = {"file": "r.npy", "format": "npy", "kind": "range"}
    view = load_bundle_from_parts(m, f).views[0]
    np.testing.assert_allclose(view.pose, ref.pose, atol=1e-12)
    np.testing.assert_allclose(view.depth, ref.depth, rtol=1e-5)


def test_rgb_mask_with_palette_and_unknown_colour() -> None:
    m, f = parts(make_bundle(1))
    ids = make_bundle(1).views[0].mask
    palette = {3: (255, 0, 0), 7: (0, 0, 255)}
    rgb = images.encode_mask_png_rgb(ids, palette)
    arr = np.array(Image.open(io.BytesIO(rgb)))
    arr[0, 1] = (1, 2, 3)  # a colour nobody declared
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    f["rgb.png"] = buf.getvalue()
    m["views"][0]["mask"] = {"file": "rgb.png", "format": "png_rgb", "palette": {str(k): list(c) for k, c in palette.items()}}
    b = load_bundle_from_parts(m, f)
    np.testing.assert_array_equal(b.views[0].mask, ids)
    assert any("1 pixels have colours not in the palette" in w for w in b.warnings)


def test_invalid_depth_values_become_zero() -> None:
    m, f = parts(make_bundle(1))
    d = make_bundle(1).views[0].depth.copy()
    d[1, 1], d[2, 2], d[3, 3] = np.nan, np.inf, -5.0
    f[m["views"][0]["depth"]["file"]] = images.encode_depth_exr(d)
    out = load_bundle_from_parts(m, f).views[0].depth
    assert out[1, 1] == out[2, 2] == out[3, 3] == 0.0 and np.isfinite(out).all()


def point_bundle() -> SceneBundle:
    rng = np.random.default_rng(1)
    b = make_bundle(2)
    for v in b.views:
        v.intrinsics = v.depth = v.mask = None
    lengths = np.array([5, 0, 7])
    b.point_segments = PointSegments(
        points=rng.normal(size=(12, 3)),
        lengths=lengths,
        view=np.array([0, 1, 1]),
        instance=np.array([3, 4, 5]),
        object=np.array([1, 1, 2]),
    )
    return b


def test_point_segments_roundtrip(tmp_path: Path) -> None:
    b = point_bundle()
    out = load_bundle(write_bundle_archive(b, tmp_path / "p.zip"))
    ps, ref = out.point_segments, b.point_segments
    assert ps is not None and out.views[0].depth is None
    for k in ("points", "lengths", "view", "instance", "object"):
        np.testing.assert_array_equal(getattr(ps, k), getattr(ref, k))
    assert any("no points" in w for w in out.warnings)


# --------------------------------------------------------------------------- bad inputs
def test_missing_manifest(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    expect_error(lambda: load_bundle(tmp_path / "empty"), "manifest", "no manifest.json")
    expect_error(lambda: load_bundle(zip_files({"a/x.png": b"1"})), "no manifest.json")
    expect_error(lambda: load_bundle(tmp_path / "nothing-here"), "source")


def test_bad_json_and_non_object() -> None:
    _, f = parts()
    expect_error(lambda: load_bundle_from_parts(b'{"units": "cm",', f), "manifest: manifest is not valid JSON", "line 1")
    expect_error(lambda: load_bundle_from_parts(b"[1, 2]", f), "must be a JSON object")
    expect_error(lambda: load_bundle_from_parts(b"\xff\xfe", f), "UTF-8")
    expect_error(lambda: load_bundle_from_parts(b'{"units": ' + b"9" * 5000 + b"}", f), "not valid JSON")
    expect_error(lambda: load_bundle_from_parts(b"[" * 100_000, f), "manifest")


def test_unknown_units_and_extra_keys() -> None:
    m, f = parts()
    m["units"] = "ft"
    m["views"][1]["depth"]["colour"] = "blue"
    err = expect_error(lambda: load_bundle_from_parts(m, f), "units: Input should be 'm', 'cm' or 'mm'")
    assert Problem(loc="views[1:cam1].depth.colour", msg="Extra inputs are not permitted") in err.problems


def test_non_rigid_and_nan_pose() -> None:
    m, f = parts()
    bad = np.eye(4)
    bad[0, 0] = 2.0
    m["views"][0]["pose"]["matrix"] = bad.tolist()
    m["views"][1]["pose"]["matrix"][1][3] = float("nan")
    text = json.dumps(m)  # json writes NaN literally; the parser accepts it, the schema must not
    assert "NaN" in text
    err = expect_error(lambda: load_bundle_from_parts(text, f), "not a proper rotation")
    locs = {p.loc for p in err.problems}
    assert "views[0:cam0].pose.matrix" in locs
    assert any(loc.startswith("views[1:cam1].pose.matrix") for loc in locs)


def test_missing_file_traversal_and_absolute_paths_all_reported() -> None:
    m, f = parts()
    m["views"][0]["depth"]["file"] = "nope.exr"
    m["views"][0]["mask"]["file"] = "../secret.png"
    m["views"][1]["depth"]["file"] = "/etc/passwd"
    m["views"][1]["mask"]["file"] = "C:\\x.png"
    err = expect_error(lambda: load_bundle_from_parts(m, f), "4 problems")
    by_loc = {p.loc: p.msg for p in err.problems}
    assert "not found" in by_loc["views[0:cam0].depth.file"]
    assert "'..'" in by_loc["views[0:cam0].mask.file"]
    assert "absolute" in by_loc["views[1:cam1].depth.file"]
    assert "absolute" in by_loc["views[1:cam1].mask.file"]


def test_upload_part_names_are_checked() -> None:
    m, f = parts()
    expect_error(lambda: load_bundle_from_parts(m, {**f, "../../x": b""}), "files['../../x']", "leaves the bundle")


def test_symlink_hardlink_and_device_in_tar() -> None:
    m, f = parts()
    members: list = [(k, v) for k, v in with_manifest(m, f).items()]
    for name, kind in (("evil", tarfile.SYMTYPE), ("hard", tarfile.LNKTYPE), ("dev", tarfile.CHRTYPE)):
        info = tarfile.TarInfo(name)
        info.type = kind
        info.linkname = "/etc/passwd"
        members.append(info)
    err = expect_error(lambda: load_bundle(tar_bytes(members)), "links are not allowed", "only regular files")
    assert len(err.problems) == 3


def test_tar_member_traversal_and_zip_absolute_member() -> None:
    m, f = parts()
    members = [(k, v) for k, v in with_manifest(m, f).items()] + [("../../etc/x", b"1")]
    expect_error(lambda: load_bundle(tar_bytes(members, "w:gz")), "archive['../../etc/x']", "leaves the bundle")
    expect_error(lambda: load_bundle(zip_files({**with_manifest(m, f), "/abs.txt": b"1"})), "absolute path")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for k, v in with_manifest(m, f).items():
            zf.writestr(k, v)
        link = zipfile.ZipInfo("link.png")
        link.create_system = 3
        link.external_attr = (0o120777 << 16)  # S_IFLNK
        zf.writestr(link, "/etc/passwd")
    expect_error(lambda: load_bundle(buf.getvalue()), "archive['link.png']", "symlink members are not allowed")


def test_symlink_out_of_bundle_directory(tmp_path: Path) -> None:
    out = write_bundle(make_bundle(), tmp_path / "b")
    secret = tmp_path / "secret.png"
    secret.write_bytes((out / "mask/00_cam0.png").read_bytes())
    (out / "mask/00_cam0.png").unlink()
    os.symlink(secret, out / "mask/00_cam0.png")
    expect_error(lambda: load_bundle(out), "views[0:cam0].mask.file", "outside the bundle directory")


def test_zip_bomb_ratio_and_size_limits() -> None:
    m, f = parts()
    limits = BundleLimits(ratio_check_min_bytes=1024 * 1024)
    # a member the manifest does not name is never decompressed: harmless, only a warning
    ignored = zip_files(with_manifest(m, f) | {"pad.bin": bytes(64 * 1024 * 1024)})
    loaded = load_bundle(ignored, limits=BundleLimits(max_total_bytes=1024 * 1024))
    assert any("pad.bin" in w for w in loaded.warnings), loaded.warnings
    # a named member is ratio-checked on its own and in total
    mk = m["views"][0]["mask"]["file"]
    bomb = zip_files(with_manifest(m, {**f, mk: bytes(4 * 1024 * 1024)}))
    err = expect_error(lambda: load_bundle(bomb, limits=limits), "compression ratio", "zip bomb")
    assert any(p.loc == f"archive[{mk!r}]" for p in err.problems), err.problems
    # declared sizes over the byte budget are refused before anything is decompressed
    expect_error(lambda: load_bundle(bomb, limits=BundleLimits(max_total_bytes=1024 * 1024)), "expands to")
    # the same in a gzip'd tar: the decompressed stream itself is capped
    tgz = tar_bytes([(k, v) for k, v in with_manifest(m, f).items()] + [("pad.bin", bytes(4 * 1024 * 1024))], "w:gz")
    expect_error(lambda: load_bundle(tgz, limits=limits), "compression ratio")
    expect_error(lambda: load_bundle(tgz, limits=BundleLimits(max_total_bytes=1024 * 1024)), "archive")


class _ReadLog(io.BytesIO):
    """An in-memory file that records the byte ranges read from it."""

    def __init__(self, data: bytes) -> None:
        super().__init__(data)
        self.ranges: list[tuple[int, int]] = []

    def read(self, size: int | None = -1) -> bytes:
        start = self.tell()
        data = super().read(size)
        self.ranges.append((start, start + len(data)))
        return data

    def readinto(self, b) -> int:  # noqa: ANN001
        start = self.tell()
        n = super().readinto(b)
        self.ranges.append((start, start + n))
        return n


@pytest.mark.parametrize("pad_first", [True, False])
def test_members_the_manifest_does_not_name_are_never_read_from_a_plain_tar(pad_first) -> None:
    # Before or after the manifest, an unnamed member's 1 MiB are seeked over, not read.
    from shadowcorr.io._archives import read_archive

    m, f = parts()
    pad = ("pad.bin", bytes(range(256)) * 4096)
    members = list(with_manifest(m, f).items())
    data = tar_bytes([pad, *members] if pad_first else [*members, pad])
    with tarfile.open(fileobj=io.BytesIO(data)) as tf:
        info = tf.getmember("pad.bin")
        pad_range = (info.offset_data, info.offset_data + info.size)
    fh = _ReadLog(data)
    files, skipped = read_archive(fh, len(data), BundleLimits())
    assert skipped == ["pad.bin"] and set(files) == set(with_manifest(m, f))
    touched = sum(min(b, pad_range[1]) - max(a, pad_range[0]) for a, b in fh.ranges
                  if a < pad_range[1] and b > pad_range[0])
    assert touched <= 1, fh.ranges  # tarfile reads a member's last byte to tell a truncated file
    assert_same(make_bundle(), load_bundle(data))  # and it loads
    # A gzip'd tar is one compressed stream: the member is decompressed on the way, never kept.
    files, skipped = read_archive(io.BytesIO(tar_bytes([pad, *members], "w:gz")), len(data), BundleLimits())
    assert skipped == ["pad.bin"] and set(files) == set(with_manifest(m, f))


def test_too_many_files_and_bytes_in_upload() -> None:
    m, f = parts()
    expect_error(lambda: load_bundle_from_parts(m, f, limits=BundleLimits(max_files=2)), "files: 4 files; the limit is 2")
    expect_error(lambda: load_bundle_from_parts(m, f, limits=BundleLimits(max_total_bytes=100)), "the limit is 100")
    expect_error(lambda: load_bundle(zip_files(with_manifest(m, f)), limits=BundleLimits(max_files=2)), "limit is 2")


def test_too_many_views() -> None:
    m, f = parts(make_bundle(3))
    expect_error(lambda: load_bundle_from_parts(m, f, limits=BundleLimits(max_views=2)), "views: 3 views; the limit is 2")


def test_truncated_png_and_exr() -> None:
    m, f = parts()
    mk = m["views"][0]["mask"]["file"]
    dk = m["views"][1]["depth"]["file"]
    f[mk] = f[mk][: len(f[mk]) // 2]
    f[dk] = f[dk][:400]
    err = expect_error(lambda: load_bundle_from_parts(m, f), "views[0:cam0].mask.file", "views[1:cam1].depth.file")
    assert len(err.problems) == 2


def test_garbage_files_and_non_archive() -> None:
    m, f = parts()
    f[m["views"][0]["depth"]["file"]] = b"GIF89a not an exr"
    f[m["views"][0]["mask"]["file"]] = b"not a png"
    expect_error(lambda: load_bundle_from_parts(m, f), "not an OpenEXR file", "not a PNG file")
    expect_error(lambda: load_bundle(b"hello world" * 100), "not a .zip or .tar")


def test_size_mismatch_vs_intrinsics_and_pixel_limit() -> None:
    m, f = parts()
    m["views"][0]["intrinsics"]["width"] = W + 1
    err = expect_error(lambda: load_bundle_from_parts(m, f), f"image is {W}x{H}", f"intrinsics say {W + 1}x{H}")
    assert {p.loc for p in err.problems} == {"views[0:cam0].depth.file", "views[0:cam0].mask.file"}
    m, f = parts()
    expect_error(lambda: load_bundle_from_parts(m, f, limits=BundleLimits(max_pixels_per_view=100)), "exceeds the limit")


def test_png_header_declaring_a_huge_image_is_refused_before_decoding() -> None:
    m, f = parts()
    png = bytearray(f[m["views"][0]["mask"]["file"]])
    png[16:24] = (100_000).to_bytes(4, "big") * 2  # IHDR width/height ...
    png[29:33] = zlib.crc32(bytes(png[12:29])).to_bytes(4, "big")  # ... with a valid CRC
    f[m["views"][0]["mask"]["file"]] = bytes(png)
    expect_error(lambda: load_bundle_from_parts(m, f), "views[0:cam0].mask.file")
    with pytest.raises(BundleError, match="more than the limit"):
        images.read_mask_png(bytes(png), max_pixels=4096 * 4096)


def test_rgb_mask_without_palette() -> None:
    m, f = parts()
    rgb = images.encode_mask_png_rgb(make_bundle().views[0].mask, {3: (255, 0, 0), 7: (0, 0, 255)})
    f[m["views"][0]["mask"]["file"]] = rgb
    expect_error(lambda: load_bundle_from_parts(m, f), "views[0:cam0].mask.file", "format 'png_rgb' with a palette")
    m["views"][0]["mask"]["format"] = "png_rgb"
    expect_error(lambda: load_bundle_from_parts(m, f), "views[0:cam0].mask", "needs a 'palette'")
    m["views"][0]["mask"]["palette"] = {"3": [255, 0, 300], "7": [0, 0, 255]}
    expect_error(lambda: load_bundle_from_parts(m, f), "views[0:cam0].mask", "0..255")
    m["views"][0]["mask"]["palette"] = {"3": [0, 0, 255], "7": [0, 0, 255]}
    expect_error(lambda: load_bundle_from_parts(m, f), "used by ids 3 and 7")


def test_npy_object_dtype_and_wrong_dtypes() -> None:
    m, f = parts(make_bundle(1), depth_format="npy", mask_format="npy")
    obj = np.empty((H, W), dtype=object)
    buf = io.BytesIO()
    np.save(buf, obj, allow_pickle=True)
    f[m["views"][0]["depth"]["file"]] = buf.getvalue()
    f[m["views"][0]["mask"]["file"]] = images.encode_npy(np.zeros((H, W), np.float32))
    expect_error(lambda: load_bundle_from_parts(m, f), "object array", "integer instance ids")
    f[m["views"][0]["depth"]["file"]] = images.encode_npy(np.zeros((H, W, 2), np.float32))
    f[m["views"][0]["mask"]["file"]] = images.encode_npy(-np.ones((H, W), np.int16))
    expect_error(lambda: load_bundle_from_parts(m, f), "2-D (height, width)", "negative instance ids")
    f[m["views"][0]["depth"]["file"]] = images.encode_npy(np.ones((H, W), np.float32))[:-10]
    expect_error(lambda: load_bundle_from_parts(m, f), "truncated")


def test_bad_point_segments() -> None:
    b = point_bundle()
    m, f = parts(b)
    ps = b.point_segments
    pts = ps.points.copy()
    pts[2, 1] = np.nan
    bad = io.BytesIO()
    np.savez(bad, points=pts, lengths=ps.lengths + 1, view=np.array([0, 5, 1]), instance=ps.instance)
    f["segments.npz"] = bad.getvalue()
    expect_error(lambda: load_bundle_from_parts(m, f), "segments.points: points must be finite")
    np.savez(bad := io.BytesIO(), points=ps.points, lengths=ps.lengths + 1, view=np.array([0, 5, 1]), instance=ps.instance)
    f["segments.npz"] = bad.getvalue()
    err = expect_error(lambda: load_bundle_from_parts(m, f), "lengths sum to 15 but there are 12 points", "segments.view")
    assert len(err.problems) == 2
    obj = np.empty(3, dtype=object)
    np.savez(bad := io.BytesIO(), points=ps.points, lengths=obj, view=ps.view, instance=ps.instance)
    f["segments.npz"] = bad.getvalue()
    expect_error(lambda: load_bundle_from_parts(m, f), "segments.lengths", "object array")


def test_duplicate_view_names_and_missing_fields() -> None:
    m, f = parts()
    m["views"][1]["name"] = "cam0"
    del m["views"][0]["intrinsics"]
    err = expect_error(lambda: load_bundle_from_parts(m, f))
    assert any("missing intrinsics" in p.msg or "unique" in p.msg for p in err.problems)


def test_error_str_lists_every_problem() -> None:
    err = BundleError([Problem(loc="a", msg="x"), Problem(loc="views[0:c].depth.file", msg="y")])
    assert str(err) == "2 problems in bundle: a: x; views[0:c].depth.file: y"
    assert err.to_dicts() == [{"loc": "a", "msg": "x"}, {"loc": "views[0:c].depth.file", "msg": "y"}]


def test_missing_file_and_undecodable_file_in_other_view_reported_together() -> None:
    m, f = parts()
    m["views"][0]["depth"]["file"] = "gone.exr"
    f[m["views"][1]["mask"]["file"]] = b"\x89PNG\r\n\x1a\n broken"
    err = expect_error(lambda: load_bundle_from_parts(m, f), "views[0:cam0].depth.file", "views[1:cam1].mask.file")
    assert len(err.problems) == 2
