"""``shadowcorr batch``: both engines label like ``shadowcorr correspond``, and runs resume.

The Ray engine runs on a real local Ray instance with 2 CPUs (started once for the
module; the runs join it).  The dataset is small on purpose: three synthetic rock fields
(physics-settled, 4 views of 320x180), one sphere scene as a .zip archive, and one
broken bundle that must become a ``failed`` line without stopping the others.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from shadowcorr.cli import main
from tests.optional import needs_mujoco, needs_ray
from tests.scenes import sphere_scene

SMALL_ROCKS = dict(
    n_rocks=(4, 5), rock_subdivisions=3, field_radius=100.0, terrain_half_size=1000.0, terrain_resolution=96,
    width=320, height=180, focal_px=1615.0 / 6, renderer="raster", background_depth="invalid", settle_max_time=2.0,
)
BROKEN = "zz_broken"  # sorts last, so --limit picks good scenes first


def _records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _labels(records: list[dict]) -> dict[str, list[int]]:
    return {r["scene"]: [s["object"] for s in r["result"]["segments"]] for r in records if r["status"] == "ok"}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    from shadowcorr.io import write_bundle_archive
    from shadowcorr.synth import SynthConfig, scene_seed, synthesize, write_scene

    root = tmp_path_factory.mktemp("batch_dataset")
    config = SynthConfig(**SMALL_ROCKS)
    for i in range(3):
        write_scene(synthesize(config, scene_seed(11, i)), root / "rocks" / f"field_{i}", config)
    rng = np.random.default_rng(3)
    spheres = sphere_scene([[0.0, 0.0, 45.0], [150.0, 30.0, 45.0], [60.0, 160.0, 45.0]], list(rng.uniform(38, 48, 3)),
                           width=160, height_px=90)
    write_bundle_archive(spheres, root / "spheres.zip")
    (root / BROKEN).mkdir()
    (root / BROKEN / "manifest.json").write_text('{"format": "shadowcorr-bundle", "version": 1, "views": []}')
    return root


@pytest.fixture(scope="module")
def reference(dataset, tmp_path_factory) -> dict[str, list[int]]:
    """Labels from ``shadowcorr correspond`` on each good scene."""
    out = tmp_path_factory.mktemp("correspond")
    scenes = {"rocks/field_0": dataset / "rocks" / "field_0", "rocks/field_1": dataset / "rocks" / "field_1",
              "rocks/field_2": dataset / "rocks" / "field_2", "spheres.zip": dataset / "spheres.zip"}
    labels = {}
    for name, path in scenes.items():
        result_file = out / (path.name + ".json")
        assert main(["correspond", str(path), "--out", str(result_file)]) == 0
        labels[name] = [s["object"] for s in json.loads(result_file.read_text())["segments"]]
    assert any(len(set(v)) < len(v) for v in labels.values()), "some scene must merge segments into one object"
    return labels


@pytest.fixture(scope="module")
def ray_instance():
    """One local Ray instance with 2 CPUs for the module; ``batch --engine ray`` joins it."""
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def _check_run(records: list[dict], reference: dict[str, list[int]]) -> None:
    assert _labels(records) == reference
    (broken,) = [r for r in records if r["scene"] == BROKEN]
    assert broken["status"] == "failed" and broken["error"]["type"] == "BundleError"
    assert broken["error"]["problems"], "the bundle's problems are listed"
    for r in records:
        if r["status"] == "ok":
            timings = r["result"]["timings_ms"]
            assert {"load", "segments", "network", "grouping", "total"} <= set(timings)
            assert r["latency_ms"] > 0 and r["result"]["metrics"]["average_purity"] > 0


@needs_mujoco  # the rock fields are settled by MuJoCo
def test_local_engine_labels_like_correspond_and_resumes(dataset, reference, tmp_path, capsys):
    out = tmp_path / "local.jsonl"
    # An "interrupted" first run: two scenes only.
    assert main(["batch", str(dataset), "--out", str(out), "--workers", "2", "--limit", "2", "--no-progress"]) == 0
    first = _records(out)
    assert [r["status"] for r in first] == ["ok", "ok"]
    # A torn last line, as a run killed mid-write leaves it: skipped and terminated, not glued to the next record.
    with open(out, "a") as fh:
        fh.write('{"scene": "rocks/fiel')
    code = main(["batch", str(dataset), "--out", str(out), "--workers", "2", "--no-progress"])
    assert code == 1  # the broken bundle failed
    records = _records_skipping_torn(out)
    done_first = {r["scene"] for r in first}
    second = records[len(first):]
    assert {r["scene"] for r in second} == set(reference) - done_first | {BROKEN}, "finished scenes are not redone"
    _check_run(records, reference)
    text = capsys.readouterr()
    assert "2 already done" in text.err and "unreadable line" in text.err
    assert "already done (skipped)  2" in text.out

    # Everything ok is skipped; only the failed scene runs again.
    before = len(_records_skipping_torn(out))
    assert main(["batch", str(dataset), "--out", str(out), "--workers", "2", "--no-progress"]) == 1
    again = _records_skipping_torn(out)[before:]
    assert [r["scene"] for r in again] == [BROKEN]


def _records_skipping_torn(path: Path) -> list[dict]:
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


@needs_mujoco
@needs_ray
def test_ray_engine_labels_like_correspond_and_resumes(dataset, reference, ray_instance, tmp_path, capsys):
    """Both Ray plans: the staged one (prepare tasks, an actor batching two scenes per forward
    pass) is "interrupted" after three scenes, and the fused one (each scene one task) resumes."""
    out = tmp_path / "ray.jsonl"
    args = ["batch", str(dataset), "--out", str(out), "--engine", "ray", "--no-progress"]
    assert main(args + ["--ray-plan", "staged", "--batch-size", "2", "--limit", "3"]) == 0
    first = _records(out)
    assert sorted(r["scene"] for r in first) == ["rocks/field_0", "rocks/field_1", "rocks/field_2"]
    assert "staged plan, 1 network actor(s) of batch 2" in capsys.readouterr().err
    assert main(args) == 1
    records = _records(out)
    assert sorted(r["scene"] for r in records[len(first):]) == ["spheres.zip", BROKEN], "finished scenes are not redone"
    _check_run(records, reference)
    assert "3 already done, running 2 on the ray engine, 2 workers, fused plan" in capsys.readouterr().err


@needs_mujoco
def test_ray_engine_without_ray_names_the_extra(dataset, tmp_path):
    code = (
        "import sys; sys.modules['ray'] = None\n"
        "from shadowcorr.cli import main\n"
        f"sys.exit(main(['batch', {str(dataset)!r}, '--out', {str(tmp_path / 'r.jsonl')!r}, '--engine', 'ray']))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert 'pip install "shadowcorr[ray]"' in proc.stderr
    assert not (tmp_path / "r.jsonl").exists()


def test_cli_offers_every_engine_and_ray_plan_the_runner_knows():
    import argparse

    from shadowcorr_batch.cli import add_batch_parser
    from shadowcorr_batch.runner import ENGINES

    from shadowcorr_batch.ray_engine import RAY_PLANS, resolve_plan

    parser = add_batch_parser(argparse.ArgumentParser().add_subparsers())
    choices = {a.dest: tuple(a.choices) for a in parser._actions if a.choices}
    assert choices["engine"] == ENGINES and choices["ray_plan"] == RAY_PLANS
    assert resolve_plan("auto", "cpu") == "fused" and resolve_plan("auto", "cuda") == "staged"
    assert resolve_plan("staged", "cpu") == "staged"
    with pytest.raises(ValueError, match="unknown Ray plan"):
        resolve_plan("pipelined", "cpu")


def test_batch_runs_each_scene_on_one_thread_unless_asked():
    # The workers fill the cores with one scene each; a scene on every core per worker would
    # oversubscribe them.  A single scene (`correspond`) gets every core by default.
    import argparse

    from shadowcorr_batch.cli import add_batch_parser, options_from_args
    from shadowcorr.cli import build_parser, config_from_args

    parser = add_batch_parser(argparse.ArgumentParser().add_subparsers())
    assert options_from_args(parser.parse_args(["data", "--out", "r.jsonl"])).config.num_threads == 1
    assert options_from_args(parser.parse_args(["data", "--out", "r.jsonl", "--threads", "2"])).config.num_threads == 2
    assert config_from_args(build_parser().parse_args(["correspond", "x"])).num_threads == 0
