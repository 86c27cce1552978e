"""The quality benchmark's harness on a tiny configuration: small synthetic scenes (numpy
rasteriser, 192x108 px), two methods, a perturbed row, the real scene's noisy row; the
table and summary it writes must agree with its per-run records."""

from __future__ import annotations

import json
import math
import re
from types import SimpleNamespace

import numpy as np
import pytest

from tests.harness import load_bench_quality
from tests.optional import needs_mujoco

TINY = {  # 4-5 rocks of 60-140 cm seen from 400 cm at 192x108 px: each rock a few hundred pixels
    "n_rocks": [4, 5], "rock_diameter": [60.0, 140.0], "rock_subdivisions": 3, "field_radius": 100.0,
    "terrain_half_size": 1000.0, "terrain_resolution": 64, "radius": 400.0, "camera_height": 175.0,
    "width": 192, "height": 108, "focal_px": 1615.0 / 10, "renderer": "raster", "background_depth": "invalid",
    "settle_max_time": 3.0,
}
CONDITIONS = "syn:4v,syn:4v+split20%,syn:4v+mild,syn:2v-opposite,real:04+drop10%"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    bench = load_bench_quality()
    tmp = tmp_path_factory.mktemp("bench_quality")
    argv = ["--scenes", "2", "--real-repeats", "2", "--workers", "1", "--methods", "shadowcorr,meanshift,no_such_method",
            "--conditions", CONDITIONS, "--noise-rigs", "syn:4v,real:04", "--synth", json.dumps(TINY),
            "--cache", str(tmp / "cache"), "--out", str(tmp / "out")]
    return bench, argv, tmp


@needs_mujoco  # the synthetic scenes are settled by MuJoCo
def test_tables_agree_with_records(run, capsys):
    bench, argv, tmp = run
    assert bench.main(argv) == 0
    printed = capsys.readouterr().out
    assert "skipping method 'no_such_method'" in printed

    records = [json.loads(line) for line in (tmp / "out" / "records.jsonl").read_text().splitlines()]
    summary = json.loads((tmp / "out" / "summary.json").read_text())
    table = (tmp / "out" / "table.md").read_text()
    assert table in printed, "the printed table is the written one"
    methods = ["shadowcorr", "meanshift"]
    assert summary["methods"] == methods

    # 4 synthetic rows x 2 scenes + the real noisy row x 2 seeds, each by 2 methods
    runs = {(r["condition"], r["scene"], r["method"]) for r in records}
    assert len(records) == len(runs) == (4 * 2 + 2) * 2
    assert not [r for r in records if "error" in r]
    real = [r for r in records if r["rig"] == "real:04"]
    assert len({r["perturbation_seed"] for r in real}) == 2, "each repeat of the real scene has its own seed"
    split = [r for r in records if r["condition"] == "syn:4v+split20%"]
    clean = {(r["scene"], r["method"]): r for r in records if r["condition"] == "syn:4v"}
    for r in split:  # a split adds masks, so segments
        assert r["num_segments"] > clean[(r["scene"], r["method"])]["num_segments"]

    for r in records:
        assert 0 <= r["average_purity"] <= 100 and r["time_ms"] > 0 and r["cpu_ms"] > 0
        assert r["average_purity"] == pytest.approx((r["rock_purity"] + r["cluster_purity"]) / 2)

    avg_table = table.split("### average purity (%)")[1].split("###")[0]
    for cond in summary["conditions"]:
        row = re.search(rf"^\| {re.escape(cond)} \| (\d+) \| (.*) \|$", avg_table, re.M)
        assert row, cond
        cells = [c.strip() for c in row.group(2).split("|")]
        for method, cell in zip(methods, cells):
            values = [r[k] for r in records for k in ["average_purity"]
                      if r["condition"] == cond and r["method"] == method]
            assert int(row.group(1)) == len(values)
            mean, std = float(np.mean(values)), float(np.std(values))
            assert cell == f"{mean:.2f} ± {std:.2f}"
            stats = summary["cells"][cond][method]
            assert stats["average_purity"]["mean"] == pytest.approx(mean)
            assert stats["average_purity"]["std"] == pytest.approx(std)
            for key in ("time_ms", "cpu_ms"):
                times = [r[key] for r in records if r["condition"] == cond and r["method"] == method]
                assert stats[key]["mean"] == pytest.approx(np.mean(times))
            flagged = sum(r["flagged_segments"] for r in records if r["condition"] == cond and r["method"] == method)
            hit = sum(r["flagged_wrong"] for r in records if r["condition"] == cond and r["method"] == method)
            expected = 100.0 * hit / flagged if flagged else math.nan
            assert stats["flag_precision"] == pytest.approx(expected, nan_ok=True)

    # per error level: the lowest and highest rig and the mean over the rigs, from the same cells
    level_table = table.split("### average purity by error level")[1].split("###")[0]
    for level in ("clean", "mild"):
        chosen = [c for c in summary["conditions"] if (c.partition("+")[2] or "clean") == level]
        row = re.search(rf"^\| {level} \| (\d+) \| (.*) \|$", level_table, re.M)
        assert row and int(row.group(1)) == len(chosen), level
        for method, cell in zip(methods, (c.strip() for c in row.group(2).split("|"))):
            means = [summary["cells"][c][method]["average_purity"]["mean"] for c in chosen]
            assert cell == f"{min(means):.2f}–{max(means):.2f} ({np.mean(means):.2f})"

    # the combined row's loss against the clean row (its parts did not run: no sum beside it)
    row = re.search(r"^\| syn:4v\+mild \| (.*) \|$", table.split("### combined errors")[1], re.M)
    for method, cell in zip(methods, (c.strip() for c in row.group(1).split("|"))):
        cells = summary["cells"]
        loss = cells["syn:4v"][method]["average_purity"]["mean"] - cells["syn:4v+mild"][method]["average_purity"]["mean"]
        assert cell == f"{loss:.2f}"


@needs_mujoco
def test_rerun_reuses_cache_and_records(run, capsys):
    bench, argv, tmp = run
    assert bench.main([*argv, "--generate-only"]) == 0
    assert "generating" not in capsys.readouterr().out
    before = (tmp / "out" / "records.jsonl").read_text()
    # --resume with every run already recorded: nothing runs, the same records and table come out
    assert bench.main([*argv, "--resume"]) == 0
    printed = capsys.readouterr().out
    assert "0 runs in 0 tasks (20 kept" in printed
    assert (tmp / "out" / "records.jsonl").read_text() == before


def test_wrong_segments_and_conditions():
    bench = load_bench_quality()
    truth = np.array([1, 1, 1, 2, 2, 2, 3, -1])
    pred = np.array([0, 0, 5, 0, 1, 1, 2, 0])  # rock 1 split (seg 2), rock 2's seg 3 merged into rock 1's object
    assert bench.wrong_segments(truth, pred).tolist() == [False, False, True, True, False, False, False, False]
    assert bench.wrong_segments(np.array([4, 4, 4]), np.array([-1, 3, 3])).tolist() == [True, False, False]
    names = [c.name for c in bench.all_conditions(quick=False)]
    assert len(names) == len(set(names))
    assert {"syn:4v", "syn:8v", "real:all8", "syn:4v+depth2%", "real:0246+merge10%"} <= set(names)
    # combined errors on every rig, each made of single perturbations of the catalogue
    assert {f"{rig}+{k}" for rig in (*bench.SYNTH_RIGS, *bench.REAL_RIGS) for k in bench.COMBINED} <= set(names)
    assert all(p in bench.PERTURBATIONS for _, parts in bench.COMBINED.values() for p in parts)
    assert [c.name for c in bench.select(bench.all_conditions(quick=True), "real:0*")][:2] == ["real:0246", "real:012"]


def test_a_merged_masks_blobs_are_scored_by_the_rock_under_them():
    bench = load_bench_quality()

    def bundle(mask, table):
        return SimpleNamespace(views=[SimpleNamespace(name="cam0", mask=mask, depth=None, instance_objects=table)],
                               ground_truth="mapped")

    exact = np.zeros((20, 40), np.int32)
    exact[2:18, 2:18], exact[2:18, 18:38] = 1, 2  # rocks 1 and 2 touch at column 18
    fused = np.where(exact > 0, 3, 0)  # a merge: one mask over both, rock 2 owns most of it
    cut = fused.copy()
    cut[:, 16:20] = 0  # erosion cuts it where the rocks touch: blob 0 (larger) on rock 2, blob 1 on rock 1
    clean, after_merge, final = bundle(exact, {1: 1, 2: 2}), bundle(fused, {3: 2}), bundle(cut, {3: 2})
    merged = bench._merged_masks(clean, after_merge, final)
    assert merged == {"cam0": {3: {1, 2}}}
    result = SimpleNamespace(segments=[SimpleNamespace(view="cam0", instance=3, component=c) for c in (0, 1)])
    assert bench.segment_truth(final, result).tolist() == [2, 2]  # the mask's truth
    assert bench.segment_truth(final, result, clean, merged).tolist() == [2, 1]  # each blob's own rock
    # a mask no merge drew over both (as a dilated mask spilling over its neighbour) keeps its truth
    assert bench.segment_truth(final, result, clean, {}).tolist() == [2, 2]
    # the mask's descendants are found through a later split: a fresh id on part of the mask
    split = cut.copy()
    split[:, :16] = np.where(cut[:, :16] > 0, 4, 0)
    assert bench._merged_masks(clean, after_merge, bundle(split, {3: 2, 4: 2})) == {"cam0": {3: {1, 2}, 4: {1, 2}}}
