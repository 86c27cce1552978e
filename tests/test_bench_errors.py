"""The wrong-segment breakdown (benchmarks/bench_errors.py): its classes on a hand-made labelling,
and a real run whose classes add up to the quality benchmark's own count of wrong segments."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from tests.harness import load_bench_quality, load_benchmark


def test_each_kind_of_wrong_segment_gets_its_class():
    errors = load_benchmark("bench_errors")
    bench = load_bench_quality()
    # Rock 0: two segments in object 0, and a piece of view 0 alone in object 5.
    # Rock 1: object 1 holds its two segments of view 0; its segment of view 1 sits alone in object 2.
    # Rocks 2 and 3 share object 3 (rock 3 holds most of it), segment 7 being a mask drawn over both.
    # Segment 10 of rock 0 sits in rock 3's object.
    truth = np.array([0, 0, 0, 1, 1, 1, 2, 3, 3, 3, 0])
    labels = np.array([0, 0, 5, 1, 2, 1, 3, 3, 3, 3, 3])
    view = np.array([0, 1, 0, 0, 1, 0, 1, 0, 1, 1, 1])
    wrong = bench.wrong_segments(truth, labels)
    assert np.flatnonzero(wrong).tolist() == [2, 4, 6, 10]
    drawn = np.zeros(truth.size, dtype=bool)
    drawn[7] = True
    found = np.zeros(truth.size, dtype=bool)
    assert errors.classify(truth, labels, view, wrong, drawn, found) == [
        "piece_own_view", "piece_other_views", "merged_missed", "joined_wrong"]
    found[7] = True
    assert errors.classify(truth, labels, view, wrong, drawn, found)[2] == "merged_found"
    assert errors.classify(truth, labels, view, wrong, np.zeros_like(drawn), found)[2] == "chained"


def test_a_real_run_counts_the_quality_benchmarks_wrong_segments(tmp_path, capsys):
    errors = load_benchmark("bench_errors")
    bench = sys.modules["bench_quality"]  # the module bench_errors reads its scoring from (ships examples/ue_sample)
    condition = "real:04+merge10%"
    out = tmp_path / "errors.md"
    assert errors.main(["--conditions", condition, "--real-repeats", "1", "--workers", "1", "--show",
                        "--docs", str(out)]) == 0
    printed = capsys.readouterr().out
    written = out.read_text()
    assert f"--docs {out}" in written and "--real-repeats 1" in written, "the command that made the table"
    row = next(line for line in written.splitlines() if line.startswith(f"| `{condition}`"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "1", "one run: one seed of the real scene"
    total = int(cells[2].split()[0])
    per_class = [int(c.split()[0]) for c in cells[3:] if c != "–"]
    assert sum(per_class) == total and len(cells) == 3 + len(errors.CLASSES)
    assert printed.count(f"{condition} scene 0 segment") == total, "--show lists every wrong segment"

    # The same run through the quality benchmark itself: the same wrong segments.
    [task] = bench.build_tasks(bench.select(bench.all_conditions(False, ["real:04"]), condition), ["fused"], {},
                               Path(bench.SAMPLE), 1, bench.SYNTH_SEED)
    bench._init_worker(None, 1)
    [record] = bench.run_task(task).records
    assert record["wrong_segments"] == total
    assert total > 0, "10 % of touching masks merged: some segment lands in the wrong place"
