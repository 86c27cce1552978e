"""Rendering of results: segment colours, ground-truth marks, maps, files and the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from shadowcorr import ShadowCorrConfig, correspond
from shadowcorr.bundle import PointSegments, SceneBundle, View
from shadowcorr.cli import main
from shadowcorr.io import write_bundle
from shadowcorr.render import (
    PALETTE,
    STATUS_CORRECT,
    STATUS_SPLIT,
    STATUS_UNKNOWN,
    STATUS_WRONG,
    RenderConfig,
    object_colour,
    render_result,
    segment_status,
)
from shadowcorr.render.maps import MapScene, choose_frame, render_maps
from shadowcorr.render.palette import CORRECT, SPLIT, WARNING_STRIPES, WRONG
from shadowcorr.result import ObjectSummary, Result, SegmentLabel
from shadowcorr.stages import extract_segments, find_blobs

from .scenes import look_at, sphere_scene

W, H = 320, 180
EXTRA = (slice(8, 32), slice(8, 32))  # a second blob of instance 1 in cam0: segment (cam0, 1, component k)


@pytest.fixture(scope="module")
def bundle() -> SceneBundle:
    """Three spheres seen by four cameras; cam0 also holds a far blob of sphere 1's id and an ignored speck."""
    b = sphere_scene([[-120, 0, 0], [0, 0, 0], [120, 0, 0]], [45, 50, 40], cameras=4, width=W, height_px=H)
    view = b.views[0]
    depth, mask = view.depth.copy(), view.mask.copy()
    mask[EXTRA] = 1
    depth[EXTRA] = 900.0
    mask[150:155, 300:305] = 2  # 25 px: below min_blob_pixels, never a segment
    depth[150:155, 300:305] = 900.0
    b.views[0] = View(view.name, view.pose, view.intrinsics, depth, mask)
    return b


def hand_result(bundle: SceneBundle) -> Result:
    """Objects = sphere id - 1, except: cam0's extra blob of sphere 1 is put in object 2
    (wrong, support 0.3), and cam3's view of sphere 3 is an object of its own (split)."""
    seg = extract_segments(bundle, ShadowCorrConfig())
    labels = []
    for i in range(seg.num_segments):
        view, inst, comp = seg.view_names[seg.view[i]], int(seg.instance[i]), int(seg.component[i])
        obj, support = inst - 1, 0.95
        if view == "cam0" and inst == 1 and _contains(bundle, view, inst, comp, EXTRA):
            obj, support = 2, 0.3
        if view == "cam3" and inst == 3:
            obj = 3
        labels.append(SegmentLabel(segment=i, view=view, instance=inst, component=comp,
                                   num_points=int(seg.lengths[i]), object=obj, support=support))
    objects = []
    for k in sorted({s.object for s in labels}):
        members = [s.segment for s in labels if s.object == k]
        objects.append(ObjectSummary(object=k, segments=members, views=sorted({labels[m].view for m in members}),
                                     centroid=None, bbox_min=None, bbox_max=None, num_voxels=0))
    return Result(scene="spheres", units="cm", method="shadowcorr", segments=labels, objects=objects)


def _blob_mask(bundle: SceneBundle, view_name: str, instance: int, component: int) -> np.ndarray:
    """The pixels of one segment, cut the way the engine cuts them."""
    view = next(v for v in bundle.views if v.name == view_name)
    blobs = find_blobs(view.mask, True, 50)
    (blob,) = np.flatnonzero((blobs.instance == instance) & (blobs.component == component))
    return blobs.labels == blob  # numbered from 0


def _contains(bundle: SceneBundle, view: str, inst: int, comp: int, window: tuple[slice, slice]) -> bool:
    return bool(_blob_mask(bundle, view, inst, comp)[window].all())


@pytest.fixture(scope="module")
def result(bundle: SceneBundle) -> Result:
    return hand_result(bundle)


def _load(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def test_every_segment_pixel_has_its_object_colour(bundle, result, tmp_path):
    cfg = RenderConfig(alpha=1.0, annotate=False, outline_px=2)
    files = render_result(bundle, result, tmp_path, config=cfg)
    assert len(result.segments) >= 12
    for view in bundle.views:
        image = _load(tmp_path / f"view_{view.name}_objects.png")
        assert image.shape == (H, W, 3)
        covered = np.zeros((H, W), dtype=bool)
        for s in (s for s in result.segments if s.view == view.name):
            pixels = _blob_mask(bundle, view.name, s.instance, s.component)
            assert (image[pixels] == object_colour(s.object)).all(), (view.name, s.instance, s.component)
            covered |= pixels
        # Everything else (background, the ignored speck) stays grey depth shading.
        rest = image[~covered]
        assert (rest[:, 0] == rest[:, 1]).all() and (rest[:, 1] == rest[:, 2]).all()
    assert tmp_path / "contact_sheet.png" in files


def test_fills_blend_the_object_colour_over_grey(bundle, result, tmp_path):
    render_result(bundle, result, tmp_path, config=RenderConfig(alpha=0.5, annotate=False, outline_px=0))
    image = _load(tmp_path / "view_cam1_objects.png").astype(np.float64)
    for s in (s for s in result.segments if s.view == "cam1"):
        pixels = image[_blob_mask(bundle, "cam1", s.instance, s.component)]
        grey = pixels - 0.5 * np.asarray(object_colour(s.object))  # = 0.5 * depth shading, the same in R, G, B
        assert np.ptp(grey, axis=1).max() <= 1.0 + 1e-9


def test_ground_truth_images_mark_wrong_and_split_segments(bundle, result, tmp_path):
    render_result(bundle, result, tmp_path, config=RenderConfig(alpha=1.0, annotate=False, outline_px=0))
    expected = {"wrong": 0, "split": 0, "correct": 0}
    for s in result.segments:
        pixels = _blob_mask(bundle, s.view, s.instance, s.component)
        image = _load(tmp_path / f"view_{s.view}_truth.png")
        if s.support < 0.5:  # the extra blob of sphere 1, put in sphere 3's object
            kind, colour = "wrong", WRONG
        elif s.view == "cam3" and s.instance == 3:
            kind, colour = "split", SPLIT
        else:
            kind, colour = "correct", CORRECT
        assert (image[pixels] == colour).all(), (s.view, s.instance, kind)
        expected[kind] += 1
    assert expected["wrong"] == 1 and expected["split"] == 1


def test_low_support_segments_get_hazard_stripes(bundle, result, tmp_path):
    render_result(bundle, result, tmp_path)  # defaults: annotated, low support < 0.6
    image = _load(tmp_path / "view_cam0_objects.png")
    for s in (s for s in result.segments if s.view == "cam0"):
        pixels = image[_blob_mask(bundle, "cam0", s.instance, s.component)]
        stripes = sum(int((pixels == c).all(axis=1).sum()) for c in WARNING_STRIPES)
        if s.support < 0.6:
            assert stripes > 20
        else:
            assert stripes == 0


def test_files_sizes_and_contact_sheet(bundle, result, tmp_path):
    files = render_result(bundle, result, tmp_path / "out")
    names = sorted(p.name for p in files)
    views = [v.name for v in bundle.views]
    assert names == sorted([f"view_{v}_objects.png" for v in views] + [f"view_{v}_truth.png" for v in views]
                           + ["map_top.png", "map_side.png", "contact_sheet.png"])
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == names
    for p in files:
        with Image.open(p) as im:
            if p.name.startswith("view_"):
                assert im.size == (W, H)
            else:
                assert min(im.size) >= 200
    with Image.open(tmp_path / "out" / "contact_sheet.png") as sheet, Image.open(tmp_path / "out" / "map_top.png") as top:
        assert sheet.width >= 2 * W and sheet.height > top.height / 2 + 2 * H


def test_no_truth_images_without_ground_truth(bundle, result, tmp_path):
    plain = SceneBundle(units=bundle.units, views=bundle.views, name="x", ground_truth="none")
    files = render_result(plain, result, tmp_path)
    assert not [p for p in files if p.name.endswith("_truth.png")]
    assert (tmp_path / "contact_sheet.png").exists()


def test_result_of_another_bundle_is_refused(bundle, result, tmp_path):
    other = result.model_copy(update={"segments": [s.model_copy(update={"view": "nope"}) for s in result.segments]})
    with pytest.raises(ValueError, match="views the bundle does not have"):
        render_result(bundle, other, tmp_path)


def test_segment_status_definition():
    #           object 0: rocks 5,5,7 -> majority 5 ; object 1: rock 7 ; object 2: rocks 8,9 tie -> 8
    truth = np.array([5, 5, 7, 7, 7, 8, 9, -1])
    objects = np.array([0, 0, 0, 1, 1, 2, 2, 1])
    status = segment_status(truth, objects)
    # Rock 7 lives in objects 0 (1 segment, wrong there) and 1 (2 segments, its main object).
    assert status.tolist() == [STATUS_CORRECT, STATUS_CORRECT, STATUS_WRONG, STATUS_CORRECT, STATUS_CORRECT,
                               STATUS_CORRECT, STATUS_WRONG, STATUS_UNKNOWN]
    # A rock split over two pure objects: the smaller part is 'split', ties go to the smaller object id.
    assert segment_status(np.array([1, 1, 1, 2]), np.array([4, 4, 3, 5])).tolist() == [
        STATUS_CORRECT, STATUS_CORRECT, STATUS_SPLIT, STATUS_CORRECT]
    assert segment_status(np.array([1, 1]), np.array([6, 3])).tolist() == [STATUS_SPLIT, STATUS_CORRECT]


def test_palette_is_fixed_and_distinct():
    assert len(PALETTE) >= 20 and len(set(PALETTE)) == len(PALETTE)
    assert object_colour(3) == PALETTE[3] and object_colour(3 + len(PALETTE)) == PALETTE[3]
    colours = np.asarray(PALETTE, dtype=float)
    gaps = np.linalg.norm(colours[:, None] - colours[None], axis=-1) + np.eye(len(PALETTE)) * 1e9
    assert gaps.min() > 40  # no two entries nearly the same
    assert all(max(c) - min(c) > 25 for c in PALETTE)  # none grey: it would vanish on the depth shading


def test_map_frame_follows_the_cameras_up():
    z_up = [look_at(np.array([500.0, 0, 300]), np.zeros(3)), look_at(np.array([0, 500.0, 300]), np.zeros(3))]
    frame = choose_frame(np.stack(z_up))
    assert (frame.right, frame.forward, frame.up, frame.up_sign) == (0, 1, 2, 1.0)
    y_up = [look_at(np.array([500.0, 300, 0]), np.zeros(3), up=(0, 1, 0)),
            look_at(np.array([0, 300, -500.0]), np.zeros(3), up=(0, 1, 0))]
    frame = choose_frame(np.stack(y_up))
    assert frame.up == 1 and frame.up_sign == 1.0
    right, forward, up = np.eye(3)[frame.right], np.eye(3)[frame.forward], np.eye(3)[frame.up]
    assert np.allclose(np.cross(right, forward), up)  # seen from above, not mirrored
    assert choose_frame(np.stack(z_up), "-y").up_name == "-y"


def test_maps_use_one_scale_for_both_axes_and_both_views():
    rng = np.random.default_rng(0)
    disk = rng.normal(size=(4000, 3)) * [6.0, 6.0, 3.0]
    points = np.concatenate([disk + [0, 0, 10], disk + [200, 100, 10]])
    cams = np.array([[-60.0, -40, 80], [260, 140, 80]])
    poses = np.stack([look_at(c, np.array([100.0, 50, 0])) for c in cams])
    scene = MapScene(points=points, point_object=np.repeat([0, 1], 4000), object_ids=np.array([0, 1]),
                     object_centres=np.full((2, 3), np.nan), camera_centres=cams, camera_axes=poses[:, :3, 2],
                     camera_names=["a", "b"], units="cm")
    top, side = render_maps(scene, choose_frame(poses), map_size=600)
    assert top.width == side.width

    def centre(image: Image.Image, channel: int) -> np.ndarray:
        a = np.asarray(image).astype(int)
        others = np.delete(a, channel, axis=-1)
        hit = (a[..., channel] > others.max(axis=-1) + 60)
        ys, xs = np.nonzero(hit)
        return np.array([np.median(xs), np.median(ys)])

    red, green = centre(top, 0), centre(top, 1)  # PALETTE[0] is red, PALETTE[1] green
    dx, dy = green - red
    assert dx / 200 == pytest.approx(-dy / 100, rel=0.03)  # page y grows downwards
    side_dx = centre(side, 1)[0] - centre(side, 0)[0]
    assert side_dx == pytest.approx(dx, abs=2)


def test_cli_renders_a_result_of_correspond(bundle, tmp_path, capsys):
    bundle_dir = write_bundle(bundle, tmp_path / "bundle", depth_format="npy")
    result = correspond(bundle)
    result_path = tmp_path / "result.json"
    result_path.write_text(json.dumps(result.model_dump(mode="json")))
    out = tmp_path / "pictures"
    assert main(["render", str(bundle_dir), str(result_path), "--out", str(out), "--low-support", "0.5"]) == 0
    printed = capsys.readouterr().out.split()
    assert (out / "contact_sheet.png").exists() and str(out / "contact_sheet.png") in printed
    # The engine's own result: every segment is found in the masks and drawn in its colour.
    image = _load(out / "view_cam2_objects.png")
    for s in (s for s in result.segments if s.view == "cam2"):
        pixels = image[_blob_mask(bundle, "cam2", s.instance, s.component)].astype(float)
        chroma = pixels - pixels.mean(axis=1, keepdims=True)
        colour = np.asarray(object_colour(s.object), float)
        target = colour - colour.mean()
        cosine = chroma @ target / (np.linalg.norm(chroma, axis=1) * np.linalg.norm(target) + 1e-9)
        assert np.mean(cosine > 0.95) > 0.5  # labels and outlines cover the rest
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**result.model_dump(mode="json"),
                               "segments": [{**s.model_dump(), "view": "zzz"} for s in result.segments]}))
    assert main(["render", str(bundle_dir), str(bad), "--out", str(out)]) == 2


def test_point_segment_bundles_get_maps_and_a_sheet(bundle, result, tmp_path):
    seg = extract_segments(bundle, ShadowCorrConfig())
    points = PointSegments(points=seg.points, lengths=seg.lengths, view=seg.view, instance=seg.instance,
                           object=seg.instance.copy())
    views = [View(v.name, v.pose) for v in bundle.views]
    as_points = SceneBundle(units="cm", views=views, name="pts", ground_truth="instance", point_segments=points)
    # Components of point segments are numbered in listing order: the hand result's extra
    # blob of sphere 1 keeps its key only if listed in the same order, which extract_segments does.
    files = render_result(as_points, result, tmp_path)
    assert sorted(p.name for p in files) == ["contact_sheet.png", "map_side.png", "map_top.png"]
    top = _load(tmp_path / "map_top.png")
    for k in {s.object for s in result.segments}:
        assert (np.abs(top.astype(int) - object_colour(k)).sum(axis=-1) < 120).any(), k  # every object is on the map


def test_one_outlying_object_does_not_stretch_the_map():
    rng = np.random.default_rng(1)
    blob = rng.normal(size=(300, 3)) * [3.0, 3.0, 2.0]
    centres = [[0.0, 0.0], [100.0, 100.0]] + [list(rng.uniform(0, 100, 2)) for _ in range(18)] + [[3000.0, 0.0]]
    points = np.concatenate([blob + [cx, cy, 5.0] for cx, cy in centres])
    point_object = np.repeat(np.arange(len(centres)), len(blob))
    cams = np.array([[-150.0, -150, 120], [250, 250, 120]])
    poses = np.stack([look_at(c, np.array([50.0, 50, 0])) for c in cams])
    scene = MapScene(points=points, point_object=point_object, object_ids=np.arange(len(centres)),
                     object_centres=np.array([[cx, cy, 5.0] for cx, cy in centres]), camera_centres=cams,
                     camera_axes=poses[:, :3, 2], camera_names=["a", "b"], units="cm")
    top, _ = render_maps(scene, choose_frame(poses), map_size=600)
    a = np.asarray(top).astype(float)

    def median_x(obj: int) -> float:  # pixels of the object's colour, at any shade
        colour = np.asarray(object_colour(obj), float)
        cosine = a @ colour / (np.linalg.norm(a, axis=-1) * np.linalg.norm(colour) + 1e-9)
        return float(np.median(np.nonzero(cosine > 0.9995)[1]))

    red_x, green_x = median_x(0), median_x(1)
    # 100 units between them: about 600 px * 100 / (field + margins) when the outlier at x = 3000
    # is left out of the frame; about 20 px if it stretched the map.
    assert green_x - red_x > 300
