"""Fit the calibrated support of ``fused`` (``shadowcorr/models/support.json``).

    python scripts/fit_support.py                 # generate, run, fit, write the model file
    python scripts/fit_support.py --out /tmp/support.json --scenes 6

Generated scenes (dataset seed 5005: neither the shipped network's training seeds nor the
quality benchmark's 9001) on the quality benchmark's eight synthetic rigs are labelled by
``fused`` clean, under single errors and under the combined errors of the quality benchmark
(the first ``--scenes`` of each rig), and under the combined errors alone (the next ones, up to
``--combined-scenes``: the flag is for data with every error at once, and its wrong segments
are what the fit needs most).  For every segment with ground truth the features of
:data:`shadowcorr.stages.SUPPORT_FEATURES` and whether it sits in the wrong place (the
benchmark's ``wrong_segments`` on its ``segment_truth``, which scores a merged mask's blobs by
the rock under their own pixels) are recorded.  The model is fitted on two thirds of the scenes
and checked on the rest (all of them, and the clean, single-error and combined-error runs
apart): expected calibration error (10 bins), AUROC and the precision / recall of "support
below the threshold" as a flag for wrong segments.  It is ``--trees`` boosted regression trees
(scikit-learn's histogram gradient boosting, log loss, at most 7 leaves of at least 100
segments each, no early stopping, so the fit does not depend on the order of the runs): which
evidence matters depends on the rest of it, e.g. a thin share of its view's points means little
alone and much when another mask of that view sits in the group.  They ship as plain node
tables; with ``--trees 0`` the model is a logistic regression on the standardised features.
The threshold is the highest support at which the flag still has ``--precision`` on the fitted
scenes' combined-error runs, read from out-of-fold supports (three folds of those scenes: trees
fit their own scenes closer than new ones).  Per-run features are cached in ``--work`` with
their names (saved every 50 runs), so an interrupted run resumes, a rerun only fits, and a fit on
fewer features reuses them; ``--runs-only`` fills the cache and fits nothing.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.harness import load_bench_quality  # noqa: E402

SEED = 5005
RIGS = ("syn:4v", "syn:3v-arc90", "syn:8v", "syn:4v-low", "syn:6v-uneven", "syn:2v-opposite", "syn:4v-high",
        "syn:4v-720p")
CONDITIONS = (None, "split20%", "merge10%", "erode5", "drop10%", "depth2%", "rot2", "mild", "field", "harsh")
COMBINED = ("mild", "field", "harsh")


_MODEL = None
_BENCH = None  # the quality benchmark's catalogue and scoring, loaded once per worker


def _init() -> None:
    global _MODEL, _BENCH
    _BENCH = load_bench_quality()
    import torch

    import shadowcorr

    torch.set_num_threads(1)
    _MODEL = shadowcorr.load_model()


def _run(job: tuple[str, str, int, str | None]) -> tuple[str, np.ndarray, np.ndarray]:
    """Features and wrongness of every scored segment of one (scene, condition)."""
    from shadowcorr import ShadowCorrConfig, load_bundle, prepare
    from shadowcorr.stages import embed, group_by_evidence, support_features

    bench = _BENCH
    key, path, index, condition = job
    clean = bundle = load_bundle(path)
    merged: dict = {}
    if condition is not None:
        bundle = bench.perturb(bundle, condition, bench.perturbation_seed(f"fit/{path}", condition, 0), merged)
    config = ShadowCorrConfig()
    scene = prepare(bundle, config)
    (embeddings,) = embed(_MODEL, [scene])
    groups = group_by_evidence(scene, embeddings, config)
    features = support_features(groups, config)
    # The truth the quality benchmark scores with (read here only to score): each mask's, but a
    # merged mask's blobs by the rock under their own pixels.
    cut = SimpleNamespace(segments=[SimpleNamespace(view=scene.view_names[v], instance=i, component=c) for v, i, c in
                                    zip(scene.segment_view.tolist(), scene.segment_instance.tolist(),
                                        scene.segment_component.tolist())])
    truth = bench.segment_truth(bundle, cut, clean, merged, config)
    wrong = bench.wrong_segments(truth, groups.labels)
    scored = truth >= 0
    return key, features[scored], wrong[scored]


def expected_calibration_error(p_correct: np.ndarray, correct: np.ndarray, bins: int = 10) -> float:
    """Sum over equal-width bins of the bin's share times |accuracy - mean predicted probability|."""
    which = np.minimum((p_correct * bins).astype(int), bins - 1)
    total = 0.0
    for b in range(bins):
        inside = which == b
        if inside.any():
            total += inside.mean() * abs(correct[inside].mean() - p_correct[inside].mean())
    return float(total)


def flag_scores(support: np.ndarray, wrong: np.ndarray, below: float) -> tuple[float, float]:
    flagged = support < below
    hit = int((flagged & wrong).sum())
    return hit / max(int(flagged.sum()), 1), hit / max(int(wrong.sum()), 1)


def tree_tables(model: Any) -> Any:
    """A fitted ``HistGradientBoostingClassifier`` (binary) as :class:`SupportTrees` node tables,
    and its baseline logit."""
    from shadowcorr.stages import SupportTrees

    nodes = [predictors[0].nodes for predictors in model._predictors]
    t, n = len(nodes), max(len(tree) for tree in nodes)
    feature, left, right = (np.zeros((t, n), np.int64) for _ in range(3))
    threshold, value = np.zeros((t, n)), np.zeros((t, n))
    depth = 0
    for i, tree in enumerate(nodes):
        leaf, index = tree["is_leaf"].astype(bool), np.arange(len(tree))
        feature[i, :len(tree)] = np.where(leaf, 0, tree["feature_idx"])
        threshold[i, :len(tree)] = np.where(leaf, 0.0, tree["num_threshold"])
        left[i, :len(tree)] = np.where(leaf, index, tree["left"])
        right[i, :len(tree)] = np.where(leaf, index, tree["right"])
        value[i, :len(tree)] = np.where(leaf, tree["value"], 0.0)
        left[i, len(tree):] = right[i, len(tree):] = np.arange(len(tree), n)
        depth = max(depth, int(tree["depth"].max()))
    return SupportTrees(feature, threshold, left, right, value, depth), float(np.ravel(model._baseline_prediction)[0])


def model_text(data: dict) -> str:
    """The model file: one key a line, the trees' node tables one tree a line."""
    lines = [f" {json.dumps(key)}: {json.dumps(value)}" for key, value in data.items() if key != "trees"]
    if "trees" in data:
        tables = [f"  {json.dumps(key)}: " + (json.dumps(value) if not isinstance(value, list) else
                                              "[\n   " + ",\n   ".join(json.dumps(row) for row in value) + "\n  ]")
                  for key, value in data["trees"].items()]
        lines.append(' "trees": {\n' + ",\n".join(tables) + "\n }")
    return "{\n" + ",\n".join(lines) + "\n}\n"


def fit_calibration(x: np.ndarray, wrong: np.ndarray, trees: int, fitted_on: str) -> Any:
    """The model on (x, wrong), its threshold still unset (0.5)."""
    from sklearn.ensemble import HistGradientBoostingClassifier
    from sklearn.linear_model import LogisticRegression

    from shadowcorr.stages import SUPPORT_FEATURES, SupportCalibration

    f = len(SUPPORT_FEATURES)
    if trees:
        model = HistGradientBoostingClassifier(max_iter=trees, learning_rate=0.05, max_leaf_nodes=7,
                                               min_samples_leaf=100, early_stopping=False).fit(x, ~wrong)
        tables, baseline = tree_tables(model)
        return SupportCalibration(SUPPORT_FEATURES, np.zeros(f), np.ones(f), np.zeros(f), baseline, 0.5, fitted_on,
                                  tables)
    mean, scale = x.mean(axis=0), np.maximum(x.std(axis=0), 1e-9)
    model = LogisticRegression(C=1.0, max_iter=1000).fit((x - mean) / scale, ~wrong)
    return SupportCalibration(SUPPORT_FEATURES, mean, scale, model.coef_[0], float(model.intercept_[0]), 0.5, fitted_on)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", type=int, default=12, help="generated scenes per rig under every condition")
    p.add_argument("--combined-scenes", type=int, default=24,
                   help="generated scenes per rig under the combined errors (the first --scenes of them included)")
    p.add_argument("--trees", type=int, default=300, help="boosted trees (0: a logistic regression)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--runs-only", action="store_true", help="compute the runs' features, fit nothing")
    p.add_argument("--precision", type=float, default=0.55,
                   help="the flag's precision the threshold keeps on the fitted scenes' combined-error runs (55 %%: "
                   "the quality benchmark's scenes are harder than the fitted ones, and there it should hold 50 %%)")
    p.add_argument("--work", default=str(REPO / "out" / "fit_support"), help="scene cache and per-run features")
    p.add_argument("--out", default=str(REPO / "shadowcorr" / "models" / "support.json"))
    args = p.parse_args(argv)
    from sklearn.metrics import roc_auc_score

    from shadowcorr.stages import SUPPORT_FEATURES

    bench = load_bench_quality()
    work = Path(args.work)
    runs_path = work / "runs.npz"
    done: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    if runs_path.exists():  # cached runs whose features were computed under these names
        with np.load(runs_path) as z:
            names = z["feature_names"].tolist() if "feature_names" in z.files else []
            if set(SUPPORT_FEATURES) <= set(names):
                columns = [names.index(name) for name in SUPPORT_FEATURES]
                for key in {k.rsplit("|", 1)[0] for k in z.files if "|" in k}:
                    done[key] = (z[key + "|features"][:, columns], z[key + "|wrong"])
    jobs = []
    for rig in RIGS:
        paths = bench.ensure_scenes(work / "scenes", rig, bench.synth_config(rig, {}),
                                    max(args.scenes, args.combined_scenes), SEED, args.workers)
        for index, path in enumerate(paths):
            for condition in CONDITIONS if index < args.scenes else COMBINED:
                key = f"{rig}/{index}/{condition or 'clean'}"
                if key not in done:
                    jobs.append((key, str(path), index, condition))
    t0 = time.perf_counter()
    print(f"{len(jobs)} runs to do, {len(done)} cached", flush=True)

    def save() -> None:  # every 50 runs, so an interrupted fit resumes
        work.mkdir(parents=True, exist_ok=True)
        np.savez(runs_path, feature_names=np.array(SUPPORT_FEATURES),
                 **{f"{k}|{part}": v for k, (f, w) in done.items() for part, v in (("features", f), ("wrong", w))})

    if jobs:
        with mp.get_context("spawn").Pool(args.workers, initializer=_init) as pool:
            for n, (key, features, wrong) in enumerate(pool.imap_unordered(_run, jobs), 1):
                done[key] = (features, wrong)
                if n % 50 == 0 or n == len(jobs):
                    print(f"  {n}/{len(jobs)} ({time.perf_counter() - t0:.0f} s)", flush=True)
                    save()

    if args.runs_only:
        return 0

    def stack(keys: list[str]) -> tuple[np.ndarray, np.ndarray]:
        return (np.concatenate([done[k][0] for k in keys]),
                np.concatenate([done[k][1] for k in keys]).astype(bool))

    wanted = [f"{rig}/{i}/{c or 'clean'}" for rig in RIGS for i in range(max(args.scenes, args.combined_scenes))
              for c in (CONDITIONS if i < args.scenes else COMBINED)]
    fit_keys = [k for k in wanted if int(k.split("/")[1]) % 3 != 2]
    check_keys = [k for k in wanted if int(k.split("/")[1]) % 3 == 2]
    x, wrong = stack(fit_keys)
    what = "boosted trees" if args.trees else "logistic regression"
    fitted_on = (f"fused on {len(RIGS)} rigs x {args.scenes} generated scenes (seed {SEED}) x {len(CONDITIONS)} "
                 f"conditions (clean, single and combined errors) and {args.combined_scenes - args.scenes} more scenes "
                 f"per rig under combined errors, {x.shape[0]} segments of which {int(wrong.sum())} wrong; {what}; "
                 f"scripts/fit_support.py")
    # The highest threshold whose flag keeps the precision on the fitted scenes' combined-error
    # runs (the field's data has every error at once, and the flag is for the field), read from
    # supports of a model fitted without the scenes they come from.
    combined = [k for k in fit_keys if k.split("/")[2] in COMBINED]
    support, wrong_c = [], []
    for fold in range(3):
        def in_fold(k: str) -> bool:
            return int(k.split("/")[1]) // 3 % 3 == fold
        held = fit_calibration(*stack([k for k in fit_keys if not in_fold(k)]), args.trees, "")
        xf, wf = stack([k for k in combined if in_fold(k)])
        support.append(held.probability(xf))
        wrong_c.append(wf)
    support, wrong_c = np.concatenate(support), np.concatenate(wrong_c)
    candidates = np.unique(np.round(support, 3))
    ok = [t for t in candidates if flag_scores(support, wrong_c, t)[0] >= args.precision and (support < t).any()]
    check_below = float(max(ok)) if ok else 0.5
    calibration = replace(fit_calibration(x, wrong, args.trees, fitted_on), check_below=check_below)

    print(f"\nfitted on {x.shape[0]} segments ({wrong.mean() * 100:.1f} % wrong); threshold: support < {check_below:.3f}")
    print("| scenes | segments | wrong % | ECE | AUROC | flag precision % | flag recall % |")
    print("|---|---|---|---|---|---|---|")
    kinds = (("fitted", fit_keys), ("held out", check_keys),
             ("held out, clean", [k for k in check_keys if k.endswith("/clean")]),
             ("held out, single errors", [k for k in check_keys if k.split("/")[2] not in ("clean", *COMBINED)]),
             ("held out, combined errors", [k for k in check_keys if k.split("/")[2] in COMBINED]))
    for name, keys in kinds:
        xs, ws = stack(keys)
        ps = calibration.probability(xs)
        precision, recall = flag_scores(ps, ws, check_below)
        auroc = f"{roc_auc_score(ws, -ps):.3f}" if 0 < ws.sum() < ws.size else "–"
        print(f"| {name} | {len(ws)} | {ws.mean() * 100:.1f} | {expected_calibration_error(ps, ~ws):.4f} | "
              f"{auroc} | {precision * 100:.1f} | {recall * 100:.1f} |")
    print("\ncoefficients (standardised features):" if not args.trees else "")
    if args.trees:
        tables = calibration.trees
        split = tables.left != np.arange(tables.left.shape[1])[None, :]
        used = np.bincount(tables.feature[split], minlength=len(SUPPORT_FEATURES))
        print("splits per feature:")
        for name, c in zip(SUPPORT_FEATURES, used):
            print(f"  {name:<22} {c}")
    else:
        for name, c in zip(SUPPORT_FEATURES, calibration.coef):
            print(f"  {name:<22} {c:+.3f}")
    Path(args.out).write_text(model_text(calibration.to_json()))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
