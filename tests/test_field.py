"""The field-robot scene distribution (``shadowcorr.synth.field``).

Sampling is checked over many draws without rendering (ranges covered, every draw a
valid ``SynthConfig``, seeds reproducible); rendering is checked on a few tiny scenes
(2-3 cameras at 320x180, 4-6 coarse rocks, the numpy rasteriser) where every
perturbation kind must leave the ground truth exact, and through the ``synth --field``
CLI, whose dataset must record what every scene drew.
"""

from __future__ import annotations

import argparse
import json
import math
import os

import numpy as np
import pytest
from pydantic import ValidationError

from shadowcorr.synth.physics import headless_gl_platform

if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", headless_gl_platform())

from shadowcorr.bundle import SceneBundle  # noqa: E402
from shadowcorr.synth import SynthConfig, perturb, scene_seed  # noqa: E402
from shadowcorr.synth.field import (  # noqa: E402
    PERTURBATION_ORDER,
    FieldDistribution,
    PerturbationDistribution,
    PerturbationStep,
    apply_perturbations,
    generate_field_scene,
    sample_for_seed,
    synthesize_field,
)

#: Tiny scenes: cheap to render, but with touching rocks, ground depth and 2-3 views.
TINY = dict(
    cameras=(2, 3), resolutions=((320, 180),), hfov_deg=(55.0, 65.0), n_rocks=(4, 6), min_diameter=(30.0, 50.0),
    size_ratio=(1.5, 2.5), ring_radius=(500.0, 700.0), field_share=(0.25, 0.3), cluster_prob=(0.6, 0.8),
    camera_height_bands=((250.0, 400.0, 1.0),), rock_subdivisions=2, terrain_resolution=64,
    renderer="raster", background_depth="terrain",
)
ALL_ON = {name: {"prob": 1.0} for name in PERTURBATION_ORDER}


def _draws(distribution: FieldDistribution, n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    return [distribution.sample(rng) for _ in range(n)]


# --------------------------------------------------------------------------- validation
@pytest.mark.parametrize("bad", [
    dict(cameras=(5, 3)), dict(cameras=(0, 4)), dict(n_rocks=(0, 5)), dict(n_rocks=(10, 300)),
    dict(camera_height_bands=()), dict(camera_height_bands=((100.0, 50.0, 1.0),)),
    dict(camera_height_bands=((60.0, 100.0, 0.0),)), dict(ring_radius=(300.0, 1600.0)),
    dict(field_share=(0.2, 0.95)), dict(resolutions=()), dict(resolutions=((4, 4),)), dict(hfov_deg=(50.0, 180.0)),
    dict(min_diameter=(0.0, 10.0)), dict(size_ratio=(0.5, 2.0)), dict(min_diameter=(500.0, 600.0)),
    dict(cluster_prob=(0.2, 1.2)), dict(full_ring_prob=1.5), dict(bogus=1), dict(renderer="vulkan"),
    dict(perturbations={"clean_prob": -0.1}), dict(perturbations={"morph_masks": {"px": [0, 0]}}),
    dict(perturbations={"split_masks": {"share": [0.3, 0.1]}}), dict(perturbations={"drop_masks": {"share": [0, 2]}}),
    dict(perturbations={"depth_noise": {"prob": 2.0}}), dict(perturbations={"spurious_blobs": {"count": [-1, 2]}}),
    dict(perturbations={"pose_error": {"bogus": 1}}),
])
def test_invalid_distributions_are_refused(bad):
    with pytest.raises(ValidationError):
        FieldDistribution(**bad)


def test_distribution_round_trips_as_json():
    d = FieldDistribution(**TINY)
    assert FieldDistribution.model_validate_json(d.model_dump_json()) == d
    assert PerturbationStep(name="split_masks", args={"share": 0.1}).name == "split_masks"
    with pytest.raises(ValidationError):
        PerturbationStep(name="relabel_everything")


# --------------------------------------------------------------------------- sampling
def test_samples_cover_the_ranges():
    d = FieldDistribution()
    draws = _draws(d, 600)
    cfgs = [s.config for s in draws]
    assert all(isinstance(c, SynthConfig) for c in cfgs)
    cams = [c.cameras for c in cfgs]
    assert min(cams) == 2 and max(cams) == 12 and len(set(cams)) == 11
    heights = np.array([c.camera_height for c in cfgs])
    assert np.all(((60 <= heights) & (heights <= 100)) | ((150 <= heights) & (heights <= 450))
                  | ((600 <= heights) & (heights <= 750)))
    low, high = (heights <= 100).mean(), (heights >= 600).mean()
    assert 0.2 < low < 0.4 and 0.15 < high < 0.35, "bands drawn by weight (0.3 / 0.45 / 0.25)"
    for c in cfgs:
        aim = math.degrees(math.atan2(c.camera_height, c.radius))
        assert c.pitch_deg[0] <= max(aim, 0.5) <= c.pitch_deg[1] and c.pitch_deg[1] - c.pitch_deg[0] <= 6.0 + 1e-9
        assert 300 <= c.radius <= 1100 and 0 <= c.radius_jitter <= 0.08
        assert len(c.azimuths_deg) == c.cameras and c.azimuths_deg[0] == 0.0 and 0 <= c.start_deg < 360
        hfov = 2 * math.degrees(math.atan(c.width / (2 * c.focal_px)))
        assert 50 - 1e-6 <= hfov <= 90 + 1e-6
        assert c.rock_diameter[1] <= c.field_radius + 1e-6, "rocks stay inside the ring"
        assert 0.25 * c.radius - 1e-6 <= c.field_radius <= 0.55 * c.radius + 1e-6
        assert c.n_rocks[0] == c.n_rocks[1] and 1 <= c.n_rocks[0] <= 40
        assert 0 <= c.cluster_prob <= 0.7 and 0 <= c.stack_prob <= 0.5
        assert 0 <= c.sink_depth <= 0.15 * c.rock_diameter[0] + 1e-6
        assert c.depth_noise == 0 and c.mask_dilate_px == 0, "errors come from the recipe, not the generator's knobs"
    arcs = np.array([c.arc_deg for c in cfgs])
    assert 0.4 < (arcs == 360).mean() < 0.6 and arcs[arcs < 360].min() < 90 and arcs[arcs < 360].max() > 270
    assert {(c.width, c.height) for c in cfgs} == {(640, 480), (1280, 720), (1920, 1080)}
    smallest = np.array([c.rock_diameter[0] for c in cfgs])
    largest = np.array([c.rock_diameter[1] for c in cfgs])
    assert smallest.min() < 12 and largest.max() > 300, "far below and above today's 36-157 cm"
    rocks = np.array([c.n_rocks[0] for c in cfgs])
    assert rocks.min() <= 5 and rocks.max() >= 35
    uneven = [np.ptp(np.diff(c.azimuths_deg)) for c in cfgs if c.cameras > 2]
    assert max(uneven) > 10, "some rigs are uneven"


def test_perturbation_recipes_cover_the_ranges():
    p = PerturbationDistribution()
    rng = np.random.default_rng(1)
    recipes = [p.sample(rng) for _ in range(2000)]
    assert 0.12 < np.mean([not r for r in recipes]) < 0.25, "clean scenes stay in the mix"
    args: dict[str, list[dict]] = {}
    for r in recipes:
        names = [s.name for s in r]
        assert names == [n for n in PERTURBATION_ORDER if n in names], "applied in the fixed order"
        for s in r:
            args.setdefault(s.name, []).append(s.args)
    assert set(args) == set(PERTURBATION_ORDER)
    share = {n: len(v) / len(recipes) for n, v in args.items()}
    assert 0.35 < share["depth_noise"] < 0.5 and 0.2 < share["split_masks"] < 0.32, "each with its probability"

    def values(name: str, key: str) -> np.ndarray:
        return np.array([a[key] for a in args[name]], dtype=np.float64)

    for name, key, lo, hi in [("depth_noise", "fraction", 0, 0.02), ("depth_holes", "fraction", 0, 0.1),
                              ("pose_error", "rotation_deg", 0, 2), ("pose_error", "translation_cm", 0, 5),
                              ("split_masks", "share", 0, 0.2), ("merge_touching", "share", 0, 0.1),
                              ("drop_masks", "share", 0, 0.1), ("spurious_blobs", "count", 1, 6),
                              ("spurious_blobs", "on_rocks", 0, 0.5)]:
        v = values(name, key)
        assert v.min() >= lo and v.max() <= hi and v.min() < lo + 0.1 * (hi - lo) and v.max() > hi - 0.1 * (hi - lo)
    assert all(a["up_to"] for a in args["pose_error"]), "each camera's pose error is its own, up to the scene's"
    px = values("morph_masks", "px")
    assert set(px) == set(range(-5, 0)) | set(range(1, 6)), "erosion and dilation up to 5 px, never 0"
    radii = np.array([a["radius_px"] for a in args["spurious_blobs"]])
    assert np.all((2 <= radii) & (radii <= 8)) and np.all(radii[:, 0] <= radii[:, 1])


def test_sampling_is_deterministic_per_seed():
    d = FieldDistribution()
    a, b = sample_for_seed(d, 5), sample_for_seed(d, 5)
    assert a == b and a != sample_for_seed(d, 6)
    assert json.loads(json.dumps(a)) == a, "the record is plain JSON"
    assert SynthConfig.model_validate(a["config"]).model_dump(mode="json") == a["config"]
    # each kind's coin and strength come from its own draws: switching one kind off changes nothing else
    quiet = FieldDistribution(perturbations={"clean_prob": 0.0, "split_masks": {"prob": 0.0, "share": [0.0, 0.2]}})
    loud = FieldDistribution(perturbations={"clean_prob": 0.0, "split_masks": {"prob": 1.0, "share": [0.0, 0.2]}})
    for seed in range(20):
        q, l_ = sample_for_seed(quiet, seed), sample_for_seed(loud, seed)
        assert q["config"] == l_["config"]
        assert q["perturbations"] == [s for s in l_["perturbations"] if s["name"] != "split_masks"]


# --------------------------------------------------------------------------- rendered scenes
@pytest.fixture(scope="module")
def clean_scene():
    """A clean tiny field scene (every perturbation drawn, none applied: clean_prob = 1)."""
    pytest.importorskip("mujoco")
    d = FieldDistribution(**TINY, perturbations={"clean_prob": 1.0, **ALL_ON})
    return synthesize_field(d, 21)


def _object_image(bundle: SceneBundle, vi: int) -> np.ndarray:
    """True object per pixel (0 = background, -1 = an id without truth)."""
    view = bundle.views[vi]
    if bundle.ground_truth == "instance":
        return view.mask.astype(np.int64)
    table = view.instance_objects or {}
    ids, inverse = np.unique(view.mask, return_inverse=True)
    lookup = np.array([0 if i == 0 else table.get(int(i), -1) for i in ids], dtype=np.int64)
    return lookup[inverse.reshape(view.mask.shape)]


def _check_truth(clean: SceneBundle, out: SceneBundle, *, majority: bool) -> None:
    """Every mask id of ``out`` maps to the rock whose pixels it covers in ``clean`` (the rock
    with most of them when ``majority``, else the only one), or, if it covers only
    background, to a spurious object of its own."""
    spurious = []
    for vi, (c, v) in enumerate(zip(clean.views, out.views)):
        before, after = _object_image(clean, vi), _object_image(out, vi)
        for i in np.unique(v.mask[v.mask > 0]):
            pixels = v.mask == i
            obj = np.unique(after[pixels])
            assert obj.size == 1 and obj[0] >= 0, f"view {vi} id {i}: exactly one known object"
            rocks, counts = np.unique(before[pixels & (before > 0)], return_counts=True)
            if rocks.size == 0:  # only background under it: a dilated rim never forms an id, a blob does
                assert obj[0] >= perturb.SPURIOUS_OBJECT_BASE
                spurious.append(int(obj[0]))
            elif majority:
                assert obj[0] == rocks[np.argmax(counts)]
            else:
                assert rocks.tolist() == [obj[0]], f"view {vi} id {i} covers rocks {rocks.tolist()}"
    assert len(spurious) == len(set(spurious)), "background blobs never share an object"


@pytest.mark.parametrize("step", [
    PerturbationStep(name="depth_noise", args={"fraction": 0.02}),
    PerturbationStep(name="depth_holes", args={"fraction": 0.1, "blob_px": 8.0}),
    PerturbationStep(name="pose_error", args={"rotation_deg": 2.0, "translation_cm": 5.0, "up_to": True}),
    PerturbationStep(name="merge_touching", args={"share": 1.0}),
    PerturbationStep(name="morph_masks", args={"px": -3}),
    PerturbationStep(name="morph_masks", args={"px": 3}),
    PerturbationStep(name="split_masks", args={"share": 0.5}),
    PerturbationStep(name="drop_masks", args={"share": 0.3}),
    PerturbationStep(name="spurious_blobs", args={"count": 6, "radius_px": [2.0, 5.0], "on_rocks": 0.5}),
], ids=lambda s: f"{s.name}{s.args.get('px', '')}")
def test_ground_truth_exact_after_each_perturbation(clean_scene, step):
    clean = clean_scene.bundle
    out = apply_perturbations(clean, (step,), 3)
    assert len(out.views) == len(clean.views)
    _check_truth(clean, out, majority=step.name == "merge_touching")
    changed = [not np.array_equal(a.mask, b.mask) or not np.array_equal(a.depth, b.depth)
               or not np.array_equal(a.pose, b.pose) for a, b in zip(clean.views, out.views)]
    assert any(changed), "the perturbation did something"
    if step.name in ("merge_touching", "split_masks", "spurious_blobs"):
        assert out.ground_truth == "mapped"
    root = np.random.SeedSequence(3)
    first, second = apply_perturbations(clean, (step,), root), apply_perturbations(clean, (step,), root)
    for a, b, c in zip(first.views, second.views, out.views):  # an int seed and its SeedSequence: the same streams
        assert np.array_equal(a.mask, b.mask) and np.array_equal(a.depth, b.depth) and np.array_equal(a.pose, b.pose)
        assert np.array_equal(a.mask, c.mask) and np.array_equal(a.depth, c.depth) and np.array_equal(a.pose, c.pose)


def test_generated_scene_applies_its_recipe_reproducibly(clean_scene):
    d = FieldDistribution(**TINY, perturbations={"clean_prob": 0.0, **ALL_ON, "merge_touching": {"prob": 0.0}})
    bundle, record = generate_field_scene(d, 21)
    assert record == sample_for_seed(d, 21)
    assert [s["name"] for s in record["perturbations"]] == [n for n in PERTURBATION_ORDER if n != "merge_touching"]
    # the same seed draws the same scene as the clean fixture, then perturbs it: truth stays exact
    assert record["config"] == clean_scene.truth["field"]["config"]
    _check_truth(clean_scene.bundle, bundle, majority=False)
    again, _ = generate_field_scene(d, 21)
    for a, b in zip(bundle.views, again.views):
        assert np.array_equal(a.mask, b.mask) and np.array_equal(a.depth, b.depth) and np.array_equal(a.pose, b.pose)
        assert a.instance_objects == b.instance_objects


def test_training_preparation_sees_exact_truth(clean_scene):
    """Prepared for training, a perturbed field scene has truth on every segment; ground blobs
    are segments of objects of their own (ids from SPURIOUS_OBJECT_BASE)."""
    from shadowcorr.evaluation import voxel_truth
    from shadowcorr.pipeline import prepare
    from shadowcorr.train.dataset import training_pipeline

    blobs = {"prob": 1.0, "count": [6, 6], "on_rocks": [0.0, 0.0]}
    d = FieldDistribution(**TINY, perturbations={"clean_prob": 0.0, **ALL_ON, "spurious_blobs": blobs})
    bundle, _ = generate_field_scene(d, 21)
    scene = prepare(bundle, training_pipeline())
    truth = scene.segment_truth
    assert truth is not None and np.all(truth >= 0), "no segment without ground truth"
    rocks = len(clean_scene.truth["rocks"])
    assert np.any((truth >= 1) & (truth <= rocks)) and np.any(truth >= perturb.SPURIOUS_OBJECT_BASE)
    assert set(np.unique(voxel_truth(scene))) <= set(np.unique(truth))


def test_cli_writes_a_field_dataset(tmp_path):
    pytest.importorskip("mujoco")
    from shadowcorr.io import load_bundle
    from shadowcorr.synth.cli import add_synth_parser, run_synth

    parser = argparse.ArgumentParser()
    add_synth_parser(parser.add_subparsers(dest="command"))
    spec = tmp_path / "field.json"
    spec.write_text(json.dumps({**TINY, "perturbations": {"clean_prob": 0.0, "spurious_blobs": {"prob": 1.0}}}))
    out = tmp_path / "ds"
    args = parser.parse_args(["synth", "--scenes", "2", "--seed", "4", "--out", str(out), "--field-config", str(spec),
                              "--quiet"])
    assert run_synth(args) == 0
    record = json.loads((out / "dataset.json").read_text())
    distribution = FieldDistribution.model_validate(record["field"])
    assert "config" not in record and record["n_scenes"] == 2 and len(record["scenes"]) == 2
    for i, entry in enumerate(record["scenes"]):
        assert entry["seed"] == scene_seed(4, i)
        drawn = sample_for_seed(distribution, entry["seed"])
        assert {k: entry[k] for k in drawn} == drawn, "the record is what the seed draws"
        assert "spurious_blobs" in [s["name"] for s in entry["perturbations"]]
        truth = json.loads((out / entry["dir"] / "synth_truth.json").read_text())
        assert truth["field"] == drawn and truth["seed"] == drawn["scene_seed"]
        bundle = load_bundle(out / entry["dir"])
        assert bundle.ground_truth == "mapped" and len(bundle.views) == entry["config"]["cameras"]
        assert not bundle.warnings, "every mask id has ground truth"
    # the fixed-config flags do not mix with --field
    with pytest.raises(ValueError, match="--cameras"):
        run_synth(parser.parse_args(["synth", "--scenes", "1", "--out", str(out), "--field", "--cameras", "3"]))
