"""Pose refinement: recovered pose error, time, and average purity with and without it.

Every camera of a scene is rotated by exactly LEVEL degrees about a random axis through
its centre and moved by LEVEL x 2.5 cm in a random direction (2 deg <-> 5 cm), on
synthetic scenes (``shadowcorr.synth``, exact ground truth) of one or more of the quality
benchmark's rigs (``--synth-rigs``: by default the 4-view rig and the one with cameras 80 cm
high, whose views share only grazing ground) and on the real sample scene (several camera
subsets).  Printed per kind of scene (the real scene, each rig):

* the pose error against the truth before and after refinement (median, p90, max over
  views): relative to the common motion of all cameras, which no image can reveal (the
  figure refinement is asked to bring under 0.1 deg and 1 cm), and absolute;
* CPU time of ``refine_poses`` per scene, on one thread (``time.process_time``; the
  machine may be shared, so wall time and the load average are printed too);
* the average purity of ``correspond`` with ``refine_poses`` off and on, per error level.

    python benchmarks/bench_poses.py --synth-scenes 4 --seeds 2
    python benchmarks/bench_poses.py --synth-scenes 4 --seeds 2 --no-purity --docs   # the docs' accuracy table
    python benchmarks/bench_poses.py --synth-rigs syn:4v,syn:2v-opposite --subsets ''  # other rigs, no real scene

``--docs`` also writes the pose errors and what became of every view as a Markdown table
(default ``docs/benchmarks/tables/poses-accuracy.md``, included by the documentation's pose
refinement page), with the release and the command, so that no figure is typed by hand.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from shadowcorr import ShadowCorrConfig, __version__, correspond, load_model
from shadowcorr.bundle import SceneBundle, unit_scale
from shadowcorr.convert import load_ue_scene
from shadowcorr.evaluation import pose_errors
from shadowcorr.stages import refine_poses
from shadowcorr.synth import SynthConfig, generate_scene
from shadowcorr.synth.noise import perturbed_pose

CM_PER_DEGREE = 2.5
REPO = Path(__file__).resolve().parents[1]
DOCS_TABLE = REPO / "docs" / "benchmarks" / "tables" / "poses-accuracy.md"
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_quality import SYNTH_RIGS  # noqa: E402  (the rig catalogue)


def perturbed(bundle: SceneBundle, level_deg: float, seed: int) -> SceneBundle:
    rng = np.random.default_rng(seed)
    shift = CM_PER_DEGREE * level_deg * unit_scale("cm", bundle.units)
    views = [dataclasses.replace(v, pose=perturbed_pose(rng, v.pose, level_deg, shift)) for v in bundle.views]
    return dataclasses.replace(bundle, views=views)


def stats(values: list[float]) -> str:
    a = np.asarray(values)
    return f"{np.median(a):6.3f} {np.percentile(a, 90):6.3f} {a.max():6.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--synth-scenes", type=int, default=4, help="synthetic scenes per rig (seeds 3003, 3004, ...)")
    parser.add_argument("--synth-rigs", default="syn:4v,syn:4v-low",
                        help=f"comma-separated rigs of the quality benchmark, of {', '.join(SYNTH_RIGS)}")
    parser.add_argument("--seeds", type=int, default=2, help="pose perturbations per scene and level")
    parser.add_argument("--levels", type=float, nargs="+", default=[0.0, 0.5, 1.0, 1.5, 2.0])
    parser.add_argument("--subsets", default="0,2,4,6;1,3,5,7;0,1,2,3;0,2,4,6,1,3,5,7",
                        help="camera subsets of the real sample scene, ';'-separated")
    parser.add_argument("--no-purity", action="store_true", help="only pose errors and time")
    parser.add_argument("--docs", nargs="?", const=str(DOCS_TABLE), default=None, metavar="PATH",
                        help=f"also write the pose errors to PATH (default {DOCS_TABLE.relative_to(REPO)})")
    args = parser.parse_args()
    rigs = [r for r in args.synth_rigs.split(",") if r]
    unknown = [r for r in rigs if r not in SYNTH_RIGS]
    if unknown:
        parser.error(f"unknown rig(s) {', '.join(unknown)}; known: {', '.join(SYNTH_RIGS)}")
    torch.set_num_threads(1)

    scenes: list[tuple[str, str, SceneBundle]] = []  # (kind: "real" or the rig, name, bundle)
    for subset in filter(None, args.subsets.split(";")):
        cams = [int(c) for c in subset.split(",")]
        scenes.append(("real", f"real {subset}", load_ue_scene(REPO / "examples" / "ue_sample", "2001", cams)))
    for rig in rigs:
        for k in range(args.synth_scenes):
            t0 = time.perf_counter()
            scenes.append((rig, f"{rig} {3003 + k}", generate_scene(SynthConfig(**SYNTH_RIGS[rig][1]), 3003 + k)))
            print(f"generated {rig} {3003 + k} in {time.perf_counter() - t0:.1f} s", flush=True)
    kinds = list(dict.fromkeys(kind for kind, _, _ in scenes))
    if not kinds:
        parser.error("nothing to measure: give --subsets of the real scene or --synth-rigs")

    model = None if args.no_purity else load_model()
    on, off = ShadowCorrConfig(refine_poses=True), ShadowCorrConfig(refine_poses=False)
    # (kind, level, rel_deg[], rel_cm[], abs_deg[], abs_cm[], before_deg[], before_cm[], cpu_ms, wall_ms, p_off, p_on,
    #  statuses)
    rows = []
    for kind, name, truth in scenes:
        true_poses = np.stack([v.pose for v in truth.views])
        to_cm = unit_scale(truth.units, "cm")
        for level in args.levels:
            for seed in range(args.seeds if level > 0 else 1):
                noisy = perturbed(truth, level, seed)
                c0, w0 = time.process_time(), time.perf_counter()
                refined, reports = refine_poses(noisy, on)
                cpu, wall = (time.process_time() - c0) * 1e3, (time.perf_counter() - w0) * 1e3
                est = np.stack([v.pose for v in refined.views])
                noisy_poses = np.stack([v.pose for v in noisy.views])
                rel = pose_errors(est, true_poses, common_motion=True)
                ab = pose_errors(est, true_poses)
                before = pose_errors(noisy_poses, true_poses, common_motion=True)
                p_off = p_on = float("nan")
                if model is not None:
                    p_off = correspond(noisy, model, off, metrics=True).metrics["average_purity"]
                    p_on = correspond(noisy, model, on, metrics=True).metrics["average_purity"]
                statuses = [r.status for r in reports]
                rows.append((kind, level, rel[0], rel[1] * to_cm, ab[0], ab[1] * to_cm, before[0], before[1] * to_cm,
                             cpu, wall, p_off, p_on, statuses))
                bad = [s for s in statuses if s != "corrected"]
                print(f"{name:<24} {level:3.1f} deg seed {seed}: rel error max {rel[0].max():.3f} deg "
                      f"{rel[1].max() * to_cm:.2f} cm, cpu {cpu:5.0f} ms, purity off {p_off:6.2f} on {p_on:6.2f}"
                      + (f"  not corrected: {bad}" if bad else ""), flush=True)

    def gather(select, column):
        return [x for r in rows if select(r) for x in np.atleast_1d(r[column])]

    print("\npose error over views, median / p90 / max   (relative = after removing the common motion)")
    width = max(len(k) for k in kinds)
    print(f"{'scenes':<{width}} {'level':>5}  {'before rel deg':>20}  {'after rel deg':>20}  {'after rel cm':>20}  {'after abs deg':>20}  {'after abs cm':>20}")
    for kind in kinds:
        for level in args.levels:
            sel = lambda r, k=kind, lv=level: r[0] == k and r[1] == lv  # noqa: E731
            if not any(sel(r) for r in rows):
                continue
            print(f"{kind:<{width}} {level:5.1f}  {stats(gather(sel, 6)):>20}  {stats(gather(sel, 2)):>20}  "
                  f"{stats(gather(sel, 3)):>20}  {stats(gather(sel, 4)):>20}  {stats(gather(sel, 5)):>20}")

    print("\nrefine_poses time per scene (one thread), median / p90 / max, ms")
    for label, sel in (("4-view 1080p", lambda r: len(r[12]) == 4), ("8-view 1080p", lambda r: len(r[12]) == 8)):
        if any(sel(r) for r in rows):
            print(f"{label:<14} cpu {stats(gather(sel, 8))}   wall {stats(gather(sel, 9))}")
    print("load average (1, 5, 15 min): " + ", ".join(f"{x:.1f}" for x in os.getloadavg()))

    if model is not None:
        print("\naverage purity, mean over scenes and seeds: refine_poses off -> on")
        for kind in kinds:
            line = []
            for level in args.levels:
                sel = lambda r, k=kind, lv=level: r[0] == k and r[1] == lv  # noqa: E731
                if any(sel(r) for r in rows):
                    line.append(f"{level:.1f} deg: {np.mean(gather(sel, 10)):6.2f} -> {np.mean(gather(sel, 11)):6.2f}")
            if line:
                print(f"{kind:<{width}} " + "   ".join(line))
    kept = sum(s != "corrected" for r in rows for s in r[12])
    print(f"\nviews not corrected: {kept} of {sum(len(r[12]) for r in rows)}")
    if args.docs:
        path = Path(args.docs)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(docs_table(args, rows, kinds, sum(kind == "real" for kind, _, _ in scenes)))
        print(f"wrote {path}")


def docs_table(args: argparse.Namespace, rows: list[tuple], kinds: list[str], real_subsets: int) -> str:
    """The pose errors before and after refinement per kind of scene (the real scene, each rig)
    and error level, with the statuses of the views, as Markdown."""
    def cell(values: list[float], digits: int) -> str:
        a = np.asarray(values)
        return " / ".join(f"{x:.{digits}f}" for x in (np.median(a), np.percentile(a, 90), a.max()))

    command = (f"python benchmarks/bench_poses.py --synth-scenes {args.synth_scenes} --seeds {args.seeds} "
               f"--synth-rigs {args.synth_rigs}" + (" --no-purity" if args.no_purity else "") + " --docs")
    rigs = [k for k in kinds if k != "real"]
    lines = [
        f"ShadowCorr {__version__}; {platform.machine()}, torch {torch.__version__}. "
        + (f"The real sample scene with {real_subsets} camera subsets ({args.subsets.replace(';', ' / ')}) and "
           if real_subsets else "")
        + f"{args.synth_scenes} synthetic scenes (seeds 3003-{3002 + args.synth_scenes}) on each of the rigs "
        + ", ".join(f"`{rig}` ({SYNTH_RIGS[rig][0]})" for rig in rigs)
        + f", {args.seeds} perturbations per scene and level: `{command}`.  Errors relative to the common motion "
        "of all cameras; median / p90 / max over the views.",
        "",
        "| scenes | every camera rotated / moved by | before: rotation ° | after: rotation ° | after: camera centre cm | views: status |",
        "|---|---|---|---|---|---|",
    ]
    for kind in kinds:
        for level in args.levels:
            sel = [r for r in rows if r[0] == kind and r[1] == level]
            if not sel:
                continue
            gather = lambda column: [x for r in sel for x in np.atleast_1d(r[column])]  # noqa: E731
            statuses = Counter(s for r in sel for s in r[12])
            status = ", ".join(f"{n} {s}" for s, n in sorted(statuses.items(), key=lambda kv: -kv[1]))
            label = "real" if kind == "real" else f"`{kind}`"
            lines.append(f"| {label} | {level:g}° / {CM_PER_DEGREE * level:g} cm | {cell(gather(6), 3)} | "
                         f"{cell(gather(2), 3)} | {cell(gather(3), 2)} | {status} |")
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
