"""Tests of the synthetic scene generator (``shadowcorr.synth``).

Scenes here are small (7-8 rocks in a tight field, 320x180 px with the focal length scaled by the same
1/6, coarser meshes and ground) so the whole file runs in well under a minute on two
cores.  They check the physical claims (rocks touch, rest on the ground), the geometry
claims (depth + pose + intrinsics put every masked pixel on its rock's surface, the
OpenCV convention), the mask/depth validity rules, reproducibility (seed-only, not
worker-count dependent) and the bundle round trip with ground truth.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import ConvexHull, cKDTree

from shadowcorr.io import load_bundle, write_bundle
from shadowcorr.synth import SynthConfig, generate_dataset, generate_scene, scene_seed, synthesize
from shadowcorr.synth.cameras import make_rig
from shadowcorr.synth.cli import add_synth_parser, config_from_args
from shadowcorr.synth.noise import boundary_noise, morph_mask, noisy_depth, noisy_pose
from shadowcorr.synth.rocks import make_rock

from .optional import needs_mujoco

SMALL = dict(
    n_rocks=(7, 8),
    rock_subdivisions=3,
    field_radius=120.0,
    terrain_half_size=1000.0,
    terrain_resolution=128,
    width=320,
    height=180,
    focal_px=1615.0 / 6,
    renderer="raster",
    background_depth="invalid",
)
DATASET_SEED = 7
N_SCENES = 4


def _surface_samples(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Points uniformly on a triangle mesh (area-weighted triangles, uniform barycentrics)."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(tri), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return np.einsum("nk,nkd->nd", w, tri[pick])


@pytest.fixture(scope="module")
def config() -> SynthConfig:
    return SynthConfig(**SMALL)


@pytest.fixture(scope="module")
def scenes(config):
    """The scenes of a 4-scene dataset with seed 7, generated in this process."""
    return [synthesize(config, scene_seed(DATASET_SEED, i)) for i in range(N_SCENES)]


# --------------------------------------------------------------------------- config, rocks, rig
def test_config_defaults_and_validation():
    c = SynthConfig()
    assert (c.cameras, c.radius, c.camera_height, c.width, c.height, c.focal_px) == (4, 750, 329, 1920, 1080, 1615)
    assert c.n_rocks == (18, 20) and c.rock_diameter == (36, 157) and c.units == "cm"
    assert c.pitch_deg == (21, 27) and c.arc_deg == 360 and c.sink_depth == 5
    for bad in (dict(n_rocks=(5, 3)), dict(cameras=0), dict(arc_deg=400), dict(depth_noise=-1),
                dict(renderer="vulkan"), dict(bogus=1), dict(min_views=9)):
        with pytest.raises(ValueError):
            SynthConfig(**bad)


def test_rocks_are_irregular_and_sized():
    rng = np.random.default_rng(0)
    ratios, aspects = [], []
    for d in (36.0, 80.0, 157.0) * 4:
        r = make_rock(rng, d, subdivisions=3)
        centred = r.vertices - r.vertices.mean(0)
        sv = np.linalg.svd(centred, compute_uv=False)
        _, _, vt = np.linalg.svd(centred, full_matrices=False)
        assert np.ptp(centred @ vt[0]) == pytest.approx(d, rel=1e-6)  # diameter along the main axis
        assert r.volume > 0  # closed, outward-wound mesh
        ratios.append(r.volume / ConvexHull(r.vertices).volume)
        aspects.append(sv[2] / sv[0])
    # Dents: clearly less volume than the convex hull; shapes range from flat to chunky.
    assert np.mean(ratios) < 0.97 and min(ratios) < 0.95
    assert min(aspects) < 0.45 and max(aspects) > 0.5


@pytest.mark.parametrize("arc,expected_span", [(360.0, 270.0), (180.0, 180.0), (90.0, 90.0)])
def test_rig_follows_the_real_layout(arc, expected_span):
    cams = make_rig(np.random.default_rng(3), arc_deg=arc, start_deg=10.0)
    az = []
    for c in cams:
        r = c.pose[:3, :3]
        assert np.allclose(r.T @ r, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)
        pos, fwd = c.pose[:3, 3], r[:, 2]
        assert 750 * 0.95 <= np.hypot(*pos[:2]) <= 750 * 1.05 and pos[2] == pytest.approx(329.0)
        assert 21.0 <= np.degrees(np.arcsin(-fwd[2])) <= 27.0  # pitched down
        horiz = -pos[:2] / np.linalg.norm(pos[:2])
        assert np.dot(fwd[:2] / np.linalg.norm(fwd[:2]), horiz) > 0.9999  # yaw at the centre
        assert abs(r[2, 0]) < 1e-12  # no roll: image x axis stays horizontal
        assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (1615, 1615, 960, 540, 1920, 1080)
        az.append(np.degrees(np.arctan2(pos[1], pos[0])))
    span = (np.array(az) - az[0]) % 360
    assert span.max() == pytest.approx(expected_span)


# --------------------------------------------------------------------------- physics
@needs_mujoco
def test_rocks_touch_and_rest_on_the_ground(scenes):
    with_contact = 0
    rng = np.random.default_rng(0)
    for s in scenes:
        t = s.truth
        assert t["settled"]
        # Another MuJoCo release settles the same seed elsewhere: the record says which one did.
        assert t["physics"] == f"mujoco {importlib.metadata.version('mujoco')}"
        assert len(t["rocks"]) in (7, 8)
        assert any(r["on_ground"] for r in t["rocks"])
        if not t["contacts"]:
            continue
        # Physics reports the contact on collision hulls; the rendered meshes must really
        # touch too: some contacting pair closer than 1 unit (dense surface samples).
        gaps = []
        for a, b in t["contacts"]:
            pa = _surface_samples(s.rocks[a - 1].vertices @ s.rotations[a - 1].T + s.translations[a - 1],
                                  s.rocks[a - 1].faces, 20000, rng)
            pb = _surface_samples(s.rocks[b - 1].vertices @ s.rotations[b - 1].T + s.translations[b - 1],
                                  s.rocks[b - 1].faces, 20000, rng)
            gaps.append(cKDTree(pa).query(pb)[0].min())
        if min(gaps) < 1.0:
            with_contact += 1
    assert with_contact >= N_SCENES - 1, "touching rocks must occur in most scenes"


@needs_mujoco
def test_rocks_are_sunk_into_the_ground(scenes):
    """Ground-resting rocks reach below the visible ground by about the sink depth."""
    from shadowcorr.synth.terrain import make_terrain

    s = scenes[0]
    rng_terrain = np.random.default_rng(np.random.SeedSequence(s.truth["seed"]).spawn(5)[0])
    terrain = make_terrain(rng_terrain, half_size=1000.0, resolution=128)
    depths = []
    for i, r in enumerate(s.truth["rocks"]):
        if r["on_ground"] and not any(i + 1 in c for c in s.truth["contacts"]):
            w = s.rocks[i].vertices @ s.rotations[i].T + s.translations[i]
            depths.append((terrain.height_at(w[:, 0], w[:, 1]) - w[:, 2]).max())
    assert depths and 2.0 < np.median(depths) < 10.0


# --------------------------------------------------------------------------- rendering
@needs_mujoco
def test_masks_match_depth(scenes):
    for s in scenes:
        for v in s.bundle.views:
            rock = v.mask > 0
            valid = np.isfinite(v.depth) & (v.depth > 0)
            assert rock.any()
            assert np.array_equal(rock, valid)  # background_depth="invalid": ground is invalid too
            assert set(np.unique(v.mask)) <= set(range(len(s.rocks) + 1))


@needs_mujoco
def test_ground_depth_kept_and_sky_invalid(config):
    s = synthesize(config.model_copy(update={"background_depth": "terrain"}), scene_seed(DATASET_SEED, 0))
    for v in s.bundle.views:
        valid = v.depth > 0
        assert np.all(valid[v.mask > 0])
        assert valid[v.mask == 0].mean() > 0.5  # the ground has depth ...
        assert not valid[0].all()  # ... but the top row reaches beyond it: no far-plane values
        assert v.depth.max() < 2 * 1000.0 + 800.0


@needs_mujoco
def test_pose_and_depth_follow_opencv_convention(scenes):
    """Back-projecting each mask through depth + declared pose lands on that rock's
    surface, and the rock centroid projects into its own mask."""
    rng = np.random.default_rng(1)
    hits = total = 0
    for s in scenes:
        trees = [
            cKDTree(_surface_samples(r.vertices @ R.T + t, r.faces, 30000, rng))
            for r, R, t in zip(s.rocks, s.rotations, s.translations)
        ]
        for v in s.bundle.views:
            k = v.intrinsics
            vv, uu = np.nonzero(v.mask > 0)
            d = v.depth[vv, uu].astype(np.float64)
            pc = np.stack([(uu - k.cx) * d / k.fx, (vv - k.cy) * d / k.fy, d], axis=1)
            pw = pc @ v.pose[:3, :3].T + v.pose[:3, 3]
            ids = v.mask[vv, uu]
            for rid in np.unique(ids):
                dist = trees[rid - 1].query(pw[ids == rid])[0]
                assert np.percentile(dist, 95) < 1.5, f"view {v.name} rock {rid}: {np.percentile(dist, 95):.2f}"
                # Centroid projection with the pinhole model.
                c = (s.translations[rid - 1] - v.pose[:3, 3]) @ v.pose[:3, :3]
                u, w = k.fx * c[0] / c[2] + k.cx, k.fy * c[1] / c[2] + k.cy
                if (ids == rid).sum() >= 30:
                    total += 1
                    ui, wi = int(round(u)), int(round(w))
                    hits += 0 <= wi < k.height and 0 <= ui < k.width and v.mask[wi, ui] == rid
    assert total > 20 and hits / total > 0.8  # the rest are centroids hidden behind another rock


@needs_mujoco
def test_gl_and_raster_renderers_agree(config):
    from shadowcorr.synth.render import gl_available

    if not gl_available():
        pytest.skip("no headless OpenGL here (MUJOCO_GL=egl needs libegl1 libegl-mesa0 libgl1-mesa-dri)")
    seed = scene_seed(DATASET_SEED, 1)
    a = synthesize(config.model_copy(update={"renderer": "gl"}), seed).bundle
    b = synthesize(config, seed).bundle
    for va, vb in zip(a.views, b.views):
        assert (va.mask == vb.mask).mean() > 0.999
        both = (va.mask > 0) & (va.mask == vb.mask)
        assert np.median(np.abs(va.depth[both] - vb.depth[both])) < 0.01


# --------------------------------------------------------------------------- reproducibility, I/O
@needs_mujoco
def test_reproducible_from_seed(config, scenes):
    again = generate_scene(config, scene_seed(DATASET_SEED, 0))
    for a, b in zip(again.views, scenes[0].bundle.views):
        assert np.array_equal(a.mask, b.mask) and np.array_equal(a.depth, b.depth)
        assert np.array_equal(a.pose, b.pose)
    other = generate_scene(config.model_copy(update={"cameras": 2}), scene_seed(DATASET_SEED, 0))
    assert len(other.views) == 2  # the camera stream is separate: same rocks, other rig
    assert scene_seed(DATASET_SEED, 0) != scene_seed(DATASET_SEED, 1) != scene_seed(DATASET_SEED + 1, 0)


@needs_mujoco
def test_dataset_in_parallel_matches_and_round_trips(config, scenes, tmp_path):
    """Two workers write the same scenes as in-process generation; bundles load back
    with their ground truth intact."""
    paths = generate_dataset(config, 2, tmp_path / "ds", seed=DATASET_SEED, workers=2, progress=False)
    assert [p.name for p in paths] == ["scene_00000", "scene_00001"]
    record = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    assert record["seed"] == DATASET_SEED and SynthConfig.model_validate(record["config"]) == config
    assert [s["seed"] for s in record["scenes"]] == [scene_seed(DATASET_SEED, i) for i in range(2)]
    for p, s in zip(paths, scenes):
        loaded = load_bundle(p)
        assert loaded.ground_truth == "instance" and loaded.units == "cm"
        assert [v.name for v in loaded.views] == [v.name for v in s.bundle.views]
        for lv, v in zip(loaded.views, s.bundle.views):
            assert np.array_equal(lv.mask, v.mask)
            assert np.array_equal(lv.depth, v.depth)  # float32 EXR is lossless
            assert np.allclose(lv.pose, v.pose) and lv.intrinsics == v.intrinsics
        truth = json.loads((p / "synth_truth.json").read_text())
        assert truth["seed"] == s.truth["seed"] and truth["contacts"] == s.truth["contacts"]


@needs_mujoco
def test_write_bundle_formats_round_trip(scenes, tmp_path):
    bundle = scenes[2].bundle
    out = write_bundle(bundle, tmp_path / "npy", depth_format="npy", mask_format="npy")
    loaded = load_bundle(out)
    for lv, v in zip(loaded.views, bundle.views):
        assert np.array_equal(lv.mask, v.mask) and np.array_equal(lv.depth, v.depth)


# --------------------------------------------------------------------------- realism knobs
def test_noise_primitives():
    rng = np.random.default_rng(0)
    depth = np.zeros((50, 60), np.float32)
    depth[10:40, 10:50] = 800.0
    noisy = noisy_depth(rng, depth, 2.0, 0.0)
    assert np.all(noisy[depth == 0] == 0) and np.std(noisy[depth > 0] - 800.0) == pytest.approx(2.0, rel=0.1)
    assert np.all(np.isin(noisy_depth(rng, depth, 0.0, 0.5)[depth > 0], [800.0]))
    pose = np.eye(4)
    p = noisy_pose(rng, pose, 1.0, 0.5)
    assert np.allclose(p[:3, :3].T @ p[:3, :3], np.eye(3)) and not np.allclose(p, pose)
    ids = np.zeros((20, 20), np.int32)
    ids[5:10, 5:10], ids[5:10, 10:15] = 1, 2
    grown, eroded = morph_mask(ids, 2), morph_mask(ids, -1)
    assert (grown == 1).sum() > (ids == 1).sum() and np.all(grown[ids > 0] == ids[ids > 0])
    assert (eroded == 1).sum() < (ids == 1).sum() and set(np.unique(eroded)) <= {0, 1, 2}
    jag = boundary_noise(rng, ids, 1.0)
    from scipy import ndimage

    interior = ndimage.minimum_filter(ids, 3, mode="nearest") == ndimage.maximum_filter(ids, 3, mode="nearest")
    assert (jag != ids).any() and np.array_equal(jag[interior], ids[interior])


@needs_mujoco
def test_realism_knobs_in_a_scene(config, scenes, tmp_path):
    noisy_cfg = config.model_copy(update=dict(
        depth_noise=1.0, pose_noise_translation=2.0, pose_noise_rotation_deg=0.3,
        mask_dilate_px=1, drop_view_prob=0.6, min_views=2,
    ))
    s = synthesize(noisy_cfg, scene_seed(DATASET_SEED, 0))
    exact = scenes[0].bundle
    assert 2 <= len(s.bundle.views) <= 4
    assert sum(c["dropped"] for c in s.truth["cameras"]) == 4 - len(s.bundle.views)
    by_name = {v.name: v for v in exact.views}
    for v in s.bundle.views:
        e = by_name[v.name]
        assert (v.mask > 0).sum() > (e.mask > 0).sum()  # dilated
        assert not np.allclose(v.pose, e.pose)  # declared pose is off, image is not
        both = (v.depth > 0) & (e.depth > 0)
        assert 0.5 < np.std(v.depth[both] - e.depth[both]) < 1.5
    load_bundle(write_bundle(s.bundle, tmp_path / "noisy"))  # noisy poses are still valid rigid poses


# --------------------------------------------------------------------------- CLI and packaging
def test_cli_options_map_to_config(tmp_path):
    parser = argparse.ArgumentParser()
    add_synth_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(
        ["synth", "--scenes", "3", "--cameras", "8", "--seed", "4", "--out", str(tmp_path), "--workers", "2",
         "--radius", "600", "--arc-deg", "180", "--depth-noise", "0.5", "--rocks", "6,8", "--pose-noise-deg", "0.1"]
    )
    cfg = config_from_args(args)
    assert (cfg.cameras, cfg.radius, cfg.arc_deg, cfg.depth_noise, cfg.n_rocks) == (8, 600, 180, 0.5, (6, 8))
    assert cfg.pose_noise_rotation_deg == 0.1 and args.workers == 2 and args.seed == 4
    with pytest.raises(ValueError):
        config_from_args(parser.parse_args(["synth", "--scenes", "1", "--out", "x", "--cameras", "0"]))


@needs_mujoco
def test_cli_runs_end_to_end(tmp_path):
    from shadowcorr.synth.cli import run_synth

    parser = argparse.ArgumentParser()
    add_synth_parser(parser.add_subparsers(dest="command"))
    cfg_file = tmp_path / "cfg.json"
    cfg_file.write_text(json.dumps({k: v for k, v in SMALL.items()}))
    args = parser.parse_args(["synth", "--scenes", "1", "--out", str(tmp_path / "o"), "--config", str(cfg_file),
                              "--cameras", "2", "--quiet"])
    assert run_synth(args) == 0
    assert len(load_bundle(tmp_path / "o" / "scene_00000").views) == 2


def test_library_imports_without_mujoco():
    code = "import sys; sys.modules['mujoco'] = None; import shadowcorr, shadowcorr.synth, shadowcorr.synth.cli; print('ok')"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr


def test_rig_at_explicit_uneven_azimuths():
    offsets = (0.0, 35.0, 100.0, 160.0, 235.0, 290.0)
    cams = make_rig(np.random.default_rng(0), n_cameras=6, start_deg=20.0, azimuths_deg=offsets, radius_jitter=0.0)
    azimuths = [np.degrees(np.arctan2(c.pose[1, 3], c.pose[0, 3])) % 360 for c in cams]
    assert np.allclose(azimuths, [(20.0 + a) % 360 for a in offsets])
    with pytest.raises(ValueError, match="azimuths_deg"):
        SynthConfig(cameras=4, azimuths_deg=offsets)
