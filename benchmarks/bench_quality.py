"""Quality of every correspondence method across camera rigs, sensor noise and segmenter errors.

(Over 500 lines on purpose: one runnable script - its condition catalogue, parallel runner and
report are one benchmark definition that `tests/test_bench_quality.py` runs as a whole.)

    python benchmarks/bench_quality.py --quick                      # minutes: a subset, 3 scenes per cell
    python benchmarks/bench_quality.py                              # the full table, 30 scenes per cell
    python benchmarks/bench_quality.py --methods shadowcorr,projection --conditions 'syn:4v*,real:*'
    python benchmarks/bench_quality.py --methods 'fused,fused(fusion_split_views=0)' --quick   # a setting's effect
    python benchmarks/bench_quality.py --list                       # the conditions and what they are

Rows are conditions, columns are methods.  A condition is a scene source and rig (synthetic
scenes from ``shadowcorr.synth`` on several rigs, or the real sample scene with several camera
subsets) optionally followed by ``+perturbation`` (``shadowcorr.synth.perturb``: depth noise,
holes, pose errors, mask erosion/dilation/splits/merges/drops), applied in memory to the
clean scene with a fixed seed.  Each method runs through the public API,
``shadowcorr.correspond(bundle, model, config=ShadowCorrConfig().with_options(method=m))``
(a variant column, ``fused(key=value;...)``, changes those settings too); a method this
installation does not accept is skipped with one line.

Synthetic scenes use generator seeds training never saw (dataset seed 9001; the shipped
model was trained, validated and tested on 1001, 2002 and 3003) and are cached under
``--cache`` (one folder per rig config and MuJoCo release), so reruns only evaluate.  The rigs
of one scene index share the same rock field (the generator draws cameras from their own
stream).  MuJoCo settles the rocks, and another release settles a seed into another field: the
``synth`` extra pins the release the tables were made with.

Output: one Markdown table per metric (mean ± std over scenes; the real scene's noisy rows
over perturbation seeds) on stdout and in ``OUT/table.md``; every (scene, condition,
method) run in ``OUT/records.jsonl``; the aggregated numbers in ``OUT/summary.json``.
Times are the CPU time of each ``correspond`` call on one torch thread (on a shared machine
the wall time, recorded too with the library's ``timings_ms["total"]``, measures the other
load as much as the method).
"""

from __future__ import annotations

import argparse
import fnmatch
import hashlib
import json
import math
import multiprocessing as mp
import os
import re
import sys
import time
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "examples" / "ue_sample"  # ships with the repository
REAL_SET = "2001"

#: Generator seed of the benchmark's synthetic scenes (training used 1001, 2002, 3003).
SYNTH_SEED = 9001
#: Mixed into every perturbation seed, so perturbations never reuse a generator stream.
PERTURB_SEED = 77
DEFAULT_METHODS = ("shadowcorr", "meanshift", "projection", "fused")
#: Flag threshold for the support -> "is this segment wrong?" precision/recall columns, for the
#: methods whose support is a vote share; ``fused`` uses its calibration's own threshold.
SUPPORT_FLAG = 0.6
#: Equal-width bins of the reliability table (expected calibration error of the support).
SUPPORT_BINS = 10

# ---------------------------------------------------------------- conditions
#: Synthetic rigs: SynthConfig fields over the defaults (4 cameras 90 degrees apart, 329 cm high,
#: pitch 21-27 degrees, 1920x1080, f = 1615 px).
SYNTH_RIGS: dict[str, tuple[str, dict[str, Any]]] = {
    "syn:4v": ("4 views 90° apart (default rig)", {}),
    "syn:3v-arc90": ("3 views on a 90° arc", {"cameras": 3, "arc_deg": 90.0}),
    "syn:8v": ("8 views 45° apart", {"cameras": 8}),
    "syn:2v-opposite": ("2 opposite views", {"cameras": 2}),
    "syn:4v-low": ("4 views, cameras 80 cm high, pitch 3-9°", {"camera_height": 80.0, "pitch_deg": (3.0, 9.0)}),
    "syn:4v-high": ("4 views, cameras 700 cm high, pitch 40-46°", {"camera_height": 700.0, "pitch_deg": (40.0, 46.0)}),
    "syn:6v-uneven": ("6 views at 0, 35, 100, 160, 235, 290°",
                      {"cameras": 6, "azimuths_deg": (0.0, 35.0, 100.0, 160.0, 235.0, 290.0)}),
    "syn:4v-720p": ("4 views, 1280x720, f = 900 px", {"width": 1280, "height": 720, "focal_px": 900.0}),
}
#: Real sample scene (set 2001): camera subsets of its 8-camera ring (45 degrees apart).
REAL_RIGS: dict[str, tuple[str, tuple[int, ...]]] = {
    "real:0246": ("real scene, cameras 0,2,4,6", (0, 2, 4, 6)),
    "real:012": ("real scene, cameras 0,1,2", (0, 1, 2)),
    "real:all8": ("real scene, all 8 cameras", tuple(range(8))),
    "real:04": ("real scene, cameras 0,4 (opposite)", (0, 4)),
    "real:013467": ("real scene, 6 uneven cameras 0,1,3,4,6,7", (0, 1, 3, 4, 6, 7)),
}
#: Perturbations: name -> (description, function name in shadowcorr.synth.perturb, keyword arguments).
PERTURBATIONS: dict[str, tuple[str, str, dict[str, Any]]] = {
    "depth0.5%": ("depth noise σ = 0.5 % of depth at 7.5 m (∝ z²)", "depth_noise", {"fraction": 0.005}),
    "depth1%": ("depth noise σ = 1 % of depth at 7.5 m (∝ z²)", "depth_noise", {"fraction": 0.01}),
    "depth2%": ("depth noise σ = 2 % of depth at 7.5 m (∝ z²)", "depth_noise", {"fraction": 0.02}),
    "holes10%": ("10 % of valid depth pixels invalid, in ~16 px blobs", "depth_holes", {"fraction": 0.10}),
    "rot0.25": ("each camera rotated 0.25° (random axis)", "pose_error", {"rotation_deg": 0.25}),
    "rot0.5": ("each camera rotated 0.5°", "pose_error", {"rotation_deg": 0.5}),
    "rot1": ("each camera rotated 1°", "pose_error", {"rotation_deg": 1.0}),
    "rot2": ("each camera rotated 2°", "pose_error", {"rotation_deg": 2.0}),
    "trans1cm": ("each camera moved 1 cm (random direction)", "pose_error", {"translation_cm": 1.0}),
    "trans5cm": ("each camera moved 5 cm", "pose_error", {"translation_cm": 5.0}),
    "erode2": ("masks eroded 2 px", "morph_masks", {"px": -2}),
    "erode5": ("masks eroded 5 px", "morph_masks", {"px": -5}),
    "dilate2": ("masks dilated 2 px", "morph_masks", {"px": 2}),
    "dilate5": ("masks dilated 5 px", "morph_masks", {"px": 5}),
    "split20%": ("20 % of masks split by a line", "split_masks", {"share": 0.20}),
    "merge10%": ("10 % of touching mask pairs merged", "merge_touching", {"share": 0.10}),
    "drop10%": ("10 % of masks dropped", "drop_masks", {"share": 0.10}),
    # sensor artefacts
    "depth1%corr4px": ("depth noise σ = 1 % at 7.5 m, correlated over 4 px (a stereo window)", "depth_noise",
                       {"fraction": 0.01, "correlation_px": 4.0}),
    "mixed-edges": ("mixed pixels: every depth-edge pixel floats between the rock and what is behind it",
                    "mixed_pixels", {"share": 1.0}),
    # the single errors the combined rows are made of (where not above already)
    "pose0.5/1.25cm": ("each camera rotated 0.5° and moved 1.25 cm", "pose_error",
                       {"rotation_deg": 0.5, "translation_cm": 1.25}),
    "pose1/2.5cm": ("each camera rotated 1° and moved 2.5 cm", "pose_error", {"rotation_deg": 1.0, "translation_cm": 2.5}),
    "pose2/5cm": ("each camera rotated 2° and moved 5 cm", "pose_error", {"rotation_deg": 2.0, "translation_cm": 5.0}),
    "erode3": ("masks eroded 3 px", "morph_masks", {"px": -3}),
    "split5%": ("5 % of masks split by a line", "split_masks", {"share": 0.05}),
    "split10%": ("10 % of masks split by a line", "split_masks", {"share": 0.10}),
    "merge5%": ("5 % of touching mask pairs merged", "merge_touching", {"share": 0.05}),
    "drop5%": ("5 % of masks dropped", "drop_masks", {"share": 0.05}),
    "holes2%": ("2 % of valid depth pixels invalid, in ~16 px blobs", "depth_holes", {"fraction": 0.02}),
    "holes5%": ("5 % of valid depth pixels invalid, in ~16 px blobs", "depth_holes", {"fraction": 0.05}),
}
#: Combined errors, as a rover's data has them all at once: name -> (description, the single
#: perturbations above applied in this order: the segmenter's merges and splits on whole
#: masks, then erosion and misses, then the depth sensor, then the poses).  The report sets
#: each row's loss beside the sum of its parts' losses, so compounding shows.
COMBINED: dict[str, tuple[str, tuple[str, ...]]] = {
    "mild": ("mild field errors: depth 0.5 %, poses 0.5° / 1.25 cm, masks eroded 2 px, 5 % split, 5 % merged, "
             "5 % dropped", ("merge5%", "split5%", "erode2", "drop5%", "depth0.5%", "pose0.5/1.25cm")),
    "field": ("field errors: depth 1 %, poses 1° / 2.5 cm, eroded 3 px, 10 % split, 5 % merged, 5 % dropped, "
              "2 % holes", ("merge5%", "split10%", "erode3", "drop5%", "depth1%", "holes2%", "pose1/2.5cm")),
    "harsh": ("harsh field errors: depth 2 %, poses 2° / 5 cm, eroded 5 px, 20 % split, 10 % merged, 10 % dropped, "
              "5 % holes", ("merge10%", "split20%", "erode5", "drop10%", "depth2%", "holes5%", "pose2/5cm")),
}
#: Perturbations that use no randomness: the real scene's repeats would all be the same run.
DETERMINISTIC = frozenset(name for name, (_, fn, _) in PERTURBATIONS.items() if fn == "morph_masks")
#: The rigs the single perturbations are applied to (by default); combined rows run on every rig.
NOISE_RIGS = ("syn:4v", "real:0246")
QUICK_PERTURBATIONS = ("depth1%", "rot1", "erode5", "split20%", "merge10%", "mild", "field")
QUICK_RIGS = ("syn:4v", *REAL_RIGS)


@dataclass(frozen=True)
class Condition:
    """One row: a rig (synthetic or real) and an optional perturbation."""

    rig: str
    perturbation: str | None = None

    @property
    def name(self) -> str:
        return self.rig if self.perturbation is None else f"{self.rig}+{self.perturbation}"

    @property
    def description(self) -> str:
        rig = (SYNTH_RIGS.get(self.rig) or REAL_RIGS[self.rig])[0]
        if self.perturbation is None:
            return rig
        return f"{rig}; {(PERTURBATIONS.get(self.perturbation) or COMBINED[self.perturbation])[0]}"


def all_conditions(quick: bool, noise_rigs: Sequence[str] = NOISE_RIGS) -> list[Condition]:
    """Every row of the table, in print order: synthetic rigs, their single errors, real rigs,
    their single errors; then the combined errors on every rig."""
    rigs = [r for r in (*SYNTH_RIGS, *REAL_RIGS) if not quick or r in QUICK_RIGS]
    perturbations = QUICK_PERTURBATIONS if quick else (*PERTURBATIONS, *COMBINED)
    singles = [p for p in perturbations if p in PERTURBATIONS]
    combined = [p for p in perturbations if p in COMBINED]
    rows = []
    for kind in ("syn:", "real:"):
        for rig in (r for r in rigs if r.startswith(kind)):
            rows.append(Condition(rig))
        for rig in (r for r in rigs if r.startswith(kind) and r in noise_rigs):
            rows.extend(Condition(rig, p) for p in singles)
    for kind in ("syn:", "real:"):
        for rig in (r for r in rigs if r.startswith(kind)):
            rows.extend(Condition(rig, p) for p in combined)
    return rows


def select(conditions: list[Condition], patterns: str | None) -> list[Condition]:
    """Conditions whose name matches one of the comma-separated glob ``patterns`` (all if None)."""
    if not patterns:
        return conditions
    pats = [p.strip() for p in patterns.split(",") if p.strip()]
    return [c for c in conditions if any(fnmatch.fnmatchcase(c.name, p) for p in pats)]


# ---------------------------------------------------------------- methods
def split_methods(text: str) -> list[str]:
    """The ``--methods`` list: commas separate methods, except inside a variant's parentheses."""
    return [m.strip() for m in re.split(r",(?![^(]*\))", text) if m.strip()]


def method_config(method: str):
    """The configuration of a method column: a method name, or a variant with changed settings,
    e.g. ``fused(fusion_cannot_link=0.8;fusion_split_views=0)`` (values read as JSON, else text)."""
    from shadowcorr import ShadowCorrConfig

    name, _, rest = method.partition("(")
    options: dict[str, Any] = {"method": name.strip()}
    for item in filter(None, (i.strip() for i in rest.rstrip(")").split(";"))):
        key, _, value = item.partition("=")
        try:
            options[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            options[key.strip()] = value.strip()
    return ShadowCorrConfig().with_options(**options)


def accepted_methods(requested: Iterable[str]) -> list[str]:
    """The requested methods this installation's ``ShadowCorrConfig`` accepts; one line per skipped one."""
    from pydantic import ValidationError

    ok = []
    for m in requested:
        try:
            method_config(m)
        except ValidationError as err:
            print(f"skipping method {m!r}: not accepted by this shadowcorr's ShadowCorrConfig "
                  f"({err.errors()[0]['loc']}: {err.errors()[0]['msg']})")
            continue
        ok.append(m)
    return ok


# ---------------------------------------------------------------- synthetic scenes
def synth_config(rig: str, overrides: dict[str, Any]) -> Any:
    """SynthConfig of a synthetic rig: the benchmark-wide ``overrides`` then the rig's own fields."""
    from shadowcorr.synth import SynthConfig

    return SynthConfig.model_validate({**overrides, **SYNTH_RIGS[rig][1]})


def rig_cache_dir(cache: Path, rig: str, config: Any, seed: int) -> Path:
    """One folder per (rig, generator config, seed, MuJoCo release): a changed config never reuses
    stale scenes, nor do scenes settled by another physics release (the same seed settles into
    another field there).

    The key holds only the fields set away from their defaults, so a generator that gains a
    new knob (with a default) keeps finding the scenes already generated."""
    from shadowcorr.synth.physics import physics_version

    key = json.dumps({"config": config.model_dump(mode="json", exclude_defaults=True), "seed": seed,
                      "physics": physics_version()}, sort_keys=True)
    digest = hashlib.sha256(key.encode()).hexdigest()[:10]
    return cache / f"{rig.replace(':', '_')}-{digest}"


def ensure_scenes(cache: Path, rig: str, config: Any, n: int, seed: int, workers: int) -> list[Path]:
    """The first ``n`` scenes of the rig's dataset, generated only where missing."""
    from shadowcorr.synth import generate_dataset

    out = rig_cache_dir(cache, rig, config, seed)
    paths = [out / f"scene_{i:05d}" for i in range(n)]
    missing = [p for p in paths if not (p / "manifest.json").exists()]
    if missing:
        print(f"generating {len(missing)} scene(s) of {rig} into {out} ...", flush=True)
        t0 = time.perf_counter()
        generate_dataset(config, n, out, seed=seed, workers=workers, progress=False, resume=True)
        print(f"  done in {time.perf_counter() - t0:.0f} s", flush=True)
    return paths


# ---------------------------------------------------------------- evaluation
@dataclass
class Task:
    """All runs on one clean scene: it is loaded once, then perturbed and labelled per condition."""

    rig: str
    scene: str  # cached bundle directory (synthetic) or the dataset folder (real)
    scene_index: int
    scene_name: str  # the bundle's name: synth_<generator seed of the scene> or ue_set2001
    conditions: list[tuple[str, str | None, int]]  # (condition name, perturbation, perturbation seed)
    methods: list[str]
    cameras: tuple[int, ...] | None = None  # real scene only
    done: frozenset[tuple[str, str]] = frozenset()  # (condition, method) runs kept from an earlier run
    records: list[dict[str, Any]] = field(default_factory=list)

    @property
    def views(self) -> int:
        return len(self.cameras) if self.cameras else SYNTH_RIGS[self.rig][1].get("cameras", 4)


def run_key(record: dict[str, Any]) -> tuple:
    """What identifies one run across invocations: condition, scene, perturbation seed, method."""
    return record["condition"], record["scene_name"], record["perturbation_seed"], record["method"]


def perturbation_seed(scene_key: str, perturbation: str, repeat: int) -> int:
    """Fixed seed of one perturbation of one scene (stable across runs and machines)."""
    return int(np.random.SeedSequence([PERTURB_SEED, zlib.crc32(scene_key.encode()),
                                       zlib.crc32(perturbation.encode()), repeat]).generate_state(1)[0])


def _object_image(view: Any, ground_truth: str) -> np.ndarray:
    """(H, W) true object under every pixel of a view's mask (-1: none), from its ground truth."""
    if ground_truth == "instance":
        return np.where(view.mask > 0, view.mask, -1).astype(np.int64)
    table = view.instance_objects or {}
    ids = np.unique(view.mask)
    lookup = np.array([table.get(int(i), -1) if i > 0 else -1 for i in ids], dtype=np.int64)
    return lookup[np.searchsorted(ids, view.mask)]


def _merged_masks(before: Any, after: Any, final: Any) -> dict[str, dict[int, set[int]]]:
    """Per view: the masks of ``final`` that descend from a mask ``merge_touching`` fused
    (``before`` -> ``after``), each with the objects it was drawn over.  A later split or
    erosion keeps most of a mask's pixels under its parent's id, so each final mask descends
    from the fused mask under most of its pixels."""
    from shadowcorr.stages import majority_vote

    out: dict[str, dict[int, set[int]]] = {}
    for old, new, last in zip(before.views, after.views, final.views):
        objects = _object_image(old, before.ground_truth)
        fresh = new.mask > old.mask.max()  # merge_touching gives every fused mask a fresh id
        drawn: dict[int, set[int]] = {}
        under = fresh & (objects >= 0)
        for mask_id, obj in np.unique(np.stack([new.mask[under], objects[under]]).astype(np.int64), axis=1).T:
            drawn.setdefault(int(mask_id), set()).add(int(obj))
        both = (last.mask > 0) & (new.mask > 0)
        parent = majority_vote(new.mask[both].astype(np.int64), last.mask[both].astype(np.int64),
                               int(last.mask.max()) + 1)[0]
        found = {k: drawn[p] for k, p in enumerate(parent.tolist()) if len(drawn.get(p, ())) > 1}
        if found:
            out[last.name] = found
    return out


def perturb(bundle: Any, perturbation: str, seed: int, merged: dict | None = None) -> Any:
    """The bundle under one perturbation, single or combined (its parts in order, one stream).

    ``merged``, when given, receives the masks that a merge drew over several objects (per view
    name: mask id -> those objects; for :func:`segment_truth`)."""
    from shadowcorr.synth import perturb as perturbations

    rng = np.random.default_rng(seed)
    fused = None
    for part in COMBINED[perturbation][1] if perturbation in COMBINED else (perturbation,):
        _, fn, kwargs = PERTURBATIONS[part]
        before, bundle = bundle, getattr(perturbations, fn)(bundle, rng, **kwargs)
        if fn == "merge_touching":
            fused = (before, bundle)
    if merged is not None and fused is not None and bundle.ground_truth != "none":
        merged.update(_merged_masks(*fused, bundle))
    return bundle


def segment_truth(bundle: Any, result: Any, clean: Any = None, merged: dict | None = None,
                  config: Any = None) -> np.ndarray:
    """True object of every result segment (-1 = none), from the bundle's ground truth (scoring only).

    The bundle's truth is per mask: the object the mask was drawn for; a merged mask's is the
    object owning most of its pixels.  A segment is one blob of a mask, and a merged mask's blob
    can lie on the other rock: erosion or a split line cuts the mask where the rocks touch, and
    a split half keeps its parent's truth.  Scored against the mask's rock, the blob a method
    rightly gives to its own rock counts wrong.  So, given ``clean`` (the bundle before the
    perturbation: the same images, exact masks) and ``merged`` (from :func:`perturb`), a segment
    of a merged mask is scored by the object under most of its own pixels, one of those the
    merge drew the mask over (``shadowcorr.synth.perturb.merge_touching`` already gives the
    pieces it finds apart their own truth).  Every other mask keeps its truth: a dilated mask
    spills over its neighbours and still names its rock.  ``config`` cuts the masks into blobs
    as the run did.
    """
    views = {v.name: v for v in bundle.views}
    if bundle.ground_truth == "instance":
        truth = np.array([s.instance for s in result.segments], dtype=np.int64)
    else:
        truth = np.array([(views[s.view].instance_objects or {}).get(s.instance, -1) for s in result.segments],
                         dtype=np.int64)
    if clean is None or not merged:
        return truth
    from shadowcorr import ShadowCorrConfig
    from shadowcorr.stages import majority_vote, view_blobs

    config = config or ShadowCorrConfig()
    exact = {v.name: v for v in clean.views}
    owners: dict[str, tuple[np.ndarray, dict[tuple[int, int], int]]] = {}  # per view: blob -> object, blob index
    for k, seg in enumerate(result.segments):
        masks = merged.get(seg.view, {})
        if seg.instance not in masks or truth[k] < 0:
            continue
        if seg.view not in owners:
            blobs = view_blobs(views[seg.view], config)
            objects = _object_image(exact[seg.view], clean.ground_truth)
            on = (blobs.labels >= 0) & (objects >= 0)
            owners[seg.view] = (majority_vote(objects[on], blobs.labels[on].astype(np.int64), blobs.lengths.size)[0],
                                {(int(i), int(c)): b for b, (i, c) in enumerate(zip(blobs.instance, blobs.component))})
        owner, blob_of = owners[seg.view]
        b = blob_of.get((seg.instance, seg.component))
        if b is not None and int(owner[b]) in masks[seg.instance]:
            truth[k] = owner[b]
    return truth


def majorities(truth: np.ndarray, pred: np.ndarray) -> tuple[dict[int, int], dict[int, int]]:
    """Per object its majority rock, and per rock its majority object, over the segments with
    truth (ties: the lowest id)."""
    scored = truth >= 0
    if not scored.any():
        return {}, {}
    t, p = truth[scored], pred[scored]
    pairs, counts = np.unique(np.stack([t, p], axis=1), axis=0, return_counts=True)
    order = np.lexsort((-counts, pairs[:, 1]))  # per object: largest rock first
    obj_major = {int(o): int(r) for r, o in pairs[order][np.unique(pairs[order][:, 1], return_index=True)[1]]}
    order = np.lexsort((-counts, pairs[:, 0]))  # per rock: largest object first
    rock_major = {int(r): int(o) for r, o in pairs[order][np.unique(pairs[order][:, 0], return_index=True)[1]]}
    return obj_major, rock_major


def wrong_segments(truth: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """Segments in the wrong place: their object's majority rock is another rock, or they are
    not in their rock's majority object (a merge or a split), or unlabelled (< 0).  Segments
    without truth: False."""
    scored = truth >= 0
    wrong = np.zeros(truth.size, dtype=bool)
    if not scored.any():
        return wrong
    obj_major, rock_major = majorities(truth, pred)
    wrong[scored] = [o < 0 or obj_major[int(o)] != int(r) or rock_major[int(r)] != int(o)
                     for r, o in zip(truth[scored], pred[scored])]
    return wrong


def support_threshold(method: str) -> float:
    """Below which support a segment is flagged as worth checking."""
    if method.partition("(")[0].strip() == "fused":
        from shadowcorr.stages import support_calibration

        return support_calibration().check_below
    return SUPPORT_FLAG


def support_flag_scores(result: Any, method: str, truth: np.ndarray) -> dict[str, Any]:
    """How well ``support < support_threshold(method)`` finds the wrong segments (counts for precision
    and recall), and per support bin the segments, their summed support and how many sit right
    (for the expected calibration error); ``truth`` from :func:`segment_truth`."""
    wrong = wrong_segments(truth, np.array(result.labels, dtype=np.int64))
    support = np.array([s.support for s in result.segments], dtype=np.float64)
    scored = truth >= 0
    flagged = (support < support_threshold(method)) & scored
    which = np.minimum((support * SUPPORT_BINS).astype(int), SUPPORT_BINS - 1)[scored]
    bins = [np.bincount(which, minlength=SUPPORT_BINS).tolist(),
            np.bincount(which, weights=support[scored], minlength=SUPPORT_BINS).tolist(),
            np.bincount(which, weights=(~wrong[scored]).astype(float), minlength=SUPPORT_BINS).tolist()]
    return {"wrong_segments": int(wrong.sum()), "flagged_segments": int(flagged.sum()),
            "flagged_wrong": int((flagged & wrong).sum()), "support_bins": bins}


def calibration_error(bins: Sequence[Sequence[Sequence[float]]]) -> float:
    """Expected calibration error of the support over runs' ``support_bins``: the segments' share
    in each bin times |share sitting right - mean support| there, summed."""
    count, total, right = (np.sum([b[i] for b in bins], axis=0) for i in range(3))
    n = count.sum()
    if n == 0:
        return math.nan
    used = count > 0
    return float(np.sum(count[used] / n * np.abs(right[used] / count[used] - total[used] / count[used])))


_MODEL = None


def _init_worker(model_path: str | None, threads: int) -> None:
    """Per worker process: threads, then the model, loaded once."""
    global _MODEL
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(threads)
    import torch

    import shadowcorr

    from shadowcorr.synth.spheres import sphere_scene

    torch.set_num_threads(threads)
    _MODEL = shadowcorr.load_model(model_path)
    # Warm-up (lazy imports, first-call allocations) so the first scene's time is not inflated.
    shadowcorr.correspond(sphere_scene([[0, 0, 40], [90, 0, 40]], [40, 45]), _MODEL, metrics=False)


def task_bundles(task: Task, skip: Callable[[str], bool] = lambda name: False) -> Iterable[tuple]:
    """The task's clean scene, loaded once, and per condition (except those ``skip`` names)
    ``(name, perturbation, seed, clean, bundle, merged)``: the bundle under the condition's
    perturbation and the masks its merges drew over several rocks (see :func:`perturb`)."""
    import shadowcorr
    from shadowcorr.convert import load_ue_scene

    clean = load_ue_scene(task.scene, REAL_SET, task.cameras) if task.cameras else shadowcorr.load_bundle(task.scene)
    for name, perturbation, seed in task.conditions:
        if skip(name):
            continue
        merged: dict[str, dict[int, set[int]]] = {}
        bundle = clean if perturbation is None else perturb(clean, perturbation, seed, merged)
        yield name, perturbation, seed, clean, bundle, merged


def run_task(task: Task) -> Task:
    """Load the scene, then every (condition, method) run on it; one record each."""
    import shadowcorr
    from shadowcorr.evaluation import segment_metrics

    for name, perturbation, seed, clean, bundle, merged in task_bundles(task, skip=lambda name: all(
            (name, m) in task.done for m in task.methods)):
        methods = [m for m in task.methods if (name, m) not in task.done]
        for method in methods:
            base = {"condition": name, "rig": task.rig, "perturbation": perturbation, "scene": task.scene_index,
                    "scene_name": task.scene_name, "perturbation_seed": seed if perturbation else None,
                    "method": method}
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                result = shadowcorr.correspond(bundle, _MODEL, config=method_config(method), metrics=True)
            except Exception as err:  # a method failing on one scene is a finding, not a crash of the table
                task.records.append({**base, "error": f"{type(err).__name__}: {err}"})
                continue
            wall, cpu = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
            # The library's metrics give the voxel ARI; the segment metrics are taken again on the
            # benchmark's truth, which scores a merged mask's blobs by the rock under them.
            truth = segment_truth(bundle, result, clean, merged, method_config(method))
            scores = {**(result.metrics or {}), **segment_metrics(truth, np.array(result.labels, dtype=np.int64))}
            task.records.append({
                **base, **scores, **support_flag_scores(result, method, truth),
                "time_ms": result.timings_ms.get("total", wall), "wall_ms": wall, "cpu_ms": cpu,
            })
    return task


def build_tasks(conditions: list[Condition], methods: list[str], scenes: dict[str, list[Path]],
                real_dir: Path, real_repeats: int, dataset_seed: int, kept: Iterable[tuple] = ()) -> list[Task]:
    """One task per clean synthetic scene, and per (real rig, perturbation repeat); runs whose
    ``run_key`` is in ``kept`` are left out (and tasks left with nothing to do)."""
    from shadowcorr.synth import scene_seed

    kept = set(kept)
    by_rig: dict[str, list[Condition]] = {}
    for c in conditions:
        by_rig.setdefault(c.rig, []).append(c)
    tasks = []
    for rig, conds in by_rig.items():
        if rig in SYNTH_RIGS:
            for i, path in enumerate(scenes[rig]):
                runs = [(c.name, c.perturbation, perturbation_seed(f"{rig}/{i}", c.perturbation or "", 0)) for c in conds]
                tasks.append(Task(rig, str(path), i, f"synth_{scene_seed(dataset_seed, i)}", runs, methods))
        else:
            cams = REAL_RIGS[rig][1]
            for k in range(real_repeats):  # clean and deterministic rows once, random perturbations per seed
                runs = [(c.name, c.perturbation, perturbation_seed(rig, c.perturbation or "", k))
                        for c in conds if k == 0 or (c.perturbation is not None and c.perturbation not in DETERMINISTIC)]
                if runs:
                    tasks.append(Task(rig, str(real_dir), k, f"ue_set{REAL_SET}", runs, methods, cameras=cams))
    for t in tasks:
        t.done = frozenset((name, m) for name, pert, seed in t.conditions for m in methods
                           if (name, t.scene_name, seed if pert else None, m) in kept)
    return [t for t in tasks if len(t.done) < len(t.conditions) * len(methods)]


def evaluate(tasks: list[Task], workers: int, model_path: str | None, threads: int,
             on_done: Callable[[Task], None], run: Callable[[Task], Task] | None = None) -> None:
    """Run the tasks (in a spawned process pool when ``workers`` > 1), largest first: ``run``
    (default :func:`run_task`; a module-level function, which reads the worker's ``_MODEL``) fills
    each task's records."""
    run = run or run_task
    tasks = sorted(tasks, key=lambda t: -len(t.conditions) * t.views)  # cost grows with runs and views
    if workers <= 1:
        _init_worker(model_path, threads)
        for t in tasks:
            on_done(run(t))
        return
    with mp.get_context("spawn").Pool(workers, initializer=_init_worker, initargs=(model_path, threads)) as pool:
        for t in pool.imap_unordered(run, tasks):
            on_done(t)


# ---------------------------------------------------------------- table
METRICS: tuple[tuple[str, str, str], ...] = (
    # key, title, number format
    ("average_purity", "average purity (%)", "{:.2f}"),
    ("rock_purity", "rock purity (%)", "{:.2f}"),
    ("cluster_purity", "cluster purity (%)", "{:.2f}"),
    ("voxel_ari", "voxel ARI (where defined)", "{:.4f}"),
    ("perfect_one_to_one_share", "perfect one-to-one rocks (%)", "{:.1f}"),
    ("cpu_ms", "CPU time per scene (ms, one thread: the wall time on an idle core)", "{:.0f}"),
)


#: What summary.json keeps per cell: the table's metrics and the wall times.
SUMMARY_KEYS = frozenset({m[0] for m in METRICS} | {"time_ms", "wall_ms"})


def summarize_cells(records: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, Any]]]:
    """``{condition: {method: {metric: {mean, std, n}, "errors": k, "flag_precision", "flag_recall"}}}``."""
    from shadowcorr.evaluation import summarize

    cells: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for r in records:
        cells.setdefault(r["condition"], {}).setdefault(r["method"], []).append(r)
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for cond, per_method in cells.items():
        for method, recs in per_method.items():
            ok = [r for r in recs if "error" not in r]
            stats: dict[str, Any] = {k: v for k, v in summarize(ok).items() if k in SUMMARY_KEYS}
            flagged = sum(r["flagged_segments"] for r in ok)
            wrong = sum(r["wrong_segments"] for r in ok)
            hit = sum(r["flagged_wrong"] for r in ok)
            stats["flag_precision"] = 100.0 * hit / flagged if flagged else math.nan
            stats["flag_recall"] = 100.0 * hit / wrong if wrong else math.nan
            stats["flag_counts"] = {"flagged": flagged, "hit": hit, "wrong": wrong}
            bins = [r["support_bins"] for r in ok if "support_bins" in r]
            stats["support_bins"] = np.sum(bins, axis=0).tolist() if bins else None
            stats["support_ece"] = calibration_error(bins)
            stats["errors"] = len(recs) - len(ok)
            stats["runs"] = len(recs)
            out.setdefault(cond, {})[method] = stats
    return out


def format_cell(stats: dict[str, Any] | None, key: str, fmt: str) -> str:
    """``mean ± std`` of one metric of one cell ("–" when undefined; "(n=k)" when fewer scenes had it)."""
    if not stats or key not in stats or stats[key]["n"] == 0:
        return "–"
    s = stats[key]
    text = f"{fmt.format(s['mean'])} ± {fmt.format(s['std'])}"
    if s["n"] < stats["runs"] - stats["errors"]:
        text += f" (n={s['n']})"
    if stats["errors"]:
        text += f" [{stats['errors']} failed]"
    return text


def level_table(summary: dict[str, dict[str, dict[str, Any]]], rows: list[Condition], methods: list[str]
                ) -> list[str]:
    """Markdown: per error level (clean, then each combined level) and method, the average purity's
    lowest and highest over the rigs and its mean over them (rigs of the level that ran)."""
    levels = [None, *COMBINED]
    out = []
    for level in levels:
        chosen = [c for c in rows if c.perturbation == level]
        if not chosen:
            continue
        cells = []
        for m in methods:
            values = [summary[c.name][m]["average_purity"]["mean"] for c in chosen
                      if m in summary[c.name] and "average_purity" in summary[c.name][m]]
            cells.append(f"{min(values):.2f}–{max(values):.2f} ({np.mean(values):.2f})" if values else "–")
        out.append(f"| {level or 'clean'} | {len(chosen)} | " + " | ".join(cells) + " |")
    if not out:
        return []
    return (["### average purity by error level: lowest–highest over the rigs (mean over them)", "",
             "| errors | rigs | " + " | ".join(methods) + " |", "|---|---|" + "---|" * len(methods)] + out + [""])


def render_tables(summary: dict[str, dict[str, dict[str, Any]]], conditions: list[Condition],
                  methods: list[str], metrics: Sequence[str] | None = None) -> str:
    """Markdown: one table per metric, rows = conditions, columns = methods, plus the support-flag table.

    With ``metrics`` (keys of :data:`METRICS`), only those metrics' tables after the level table,
    and neither the flag nor the compounding tables (a documentation page that shows one figure).
    """
    rows = [c for c in conditions if c.name in summary]
    lines: list[str] = level_table(summary, rows, methods)
    for key, title, fmt in METRICS:
        if metrics is not None and key not in metrics:
            continue
        lines += [f"### {title}", "", "| condition | scenes | " + " | ".join(methods) + " |",
                  "|---|---|" + "---|" * len(methods)]
        for c in rows:
            cells = summary[c.name]
            n = max((cells[m]["runs"] for m in methods if m in cells), default=0)
            lines.append(f"| {c.name} | {n} | " + " | ".join(format_cell(cells.get(m), key, fmt) for m in methods) + " |")
        lines.append("")
    if metrics is not None:
        return "\n".join(lines + ["Conditions:", ""] + [f"- `{c.name}`: {c.description}" for c in rows]) + "\n"
    thresholds = ", ".join(f"{m} {support_threshold(m):.3g}" for m in methods)
    lines += [f"### support as a flag for wrong segments (support below: {thresholds}): precision / recall (%), "
              "and the support's expected calibration error", "",
              "| condition | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for c in rows:
        cells = summary[c.name]
        flag = [f"{cells[m]['flag_precision']:.0f} / {cells[m]['flag_recall']:.0f}, ECE {cells[m]['support_ece']:.3f}"
                if m in cells else "–" for m in methods]
        lines.append(f"| {c.name} | " + " | ".join(flag).replace("nan", "–") + " |")
    lines += pooled_flag_table(summary, rows, methods)
    lines += compounding_table(summary, rows, methods)
    lines += ["", "Conditions:", ""] + [f"- `{c.name}`: {c.description}" for c in rows]
    return "\n".join(lines) + "\n"


def pooled_flag_table(summary: dict[str, dict[str, dict[str, Any]]], rows: list[Condition], methods: list[str]
                      ) -> list[str]:
    """Markdown lines: the flag's precision / recall and the support's calibration error pooled over
    the clean rows, the single-error rows and the combined-error rows."""
    kinds = (("clean", lambda c: c.perturbation is None), ("single errors", lambda c: c.perturbation in PERTURBATIONS),
             ("combined errors", lambda c: c.perturbation in COMBINED))
    lines = ["", "| pooled rows | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for label, wanted in kinds:
        cells = []
        for m in methods:
            stats = [summary[c.name][m] for c in rows if wanted(c) and m in summary[c.name]]
            if not stats:
                cells.append("–")
                continue
            flagged, hit, wrong = (sum(s["flag_counts"][k] for s in stats) for k in ("flagged", "hit", "wrong"))
            precision = 100.0 * hit / flagged if flagged else math.nan
            recall = 100.0 * hit / wrong if wrong else math.nan
            ece = calibration_error([s["support_bins"] for s in stats if s["support_bins"] is not None])
            cells.append(f"{precision:.0f} / {recall:.0f}, ECE {ece:.3f}".replace("nan", "–"))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def compounding(summary: dict[str, dict[str, dict[str, Any]]], condition: Condition, method: str
                ) -> tuple[float, float | None] | None:
    """(average-purity loss of a combined row against its rig's clean row, the sum of its parts'
    losses where every part ran on that rig, else None); None without the clean row."""
    def purity(name: str) -> float | None:
        stats = summary.get(name, {}).get(method)
        return stats["average_purity"]["mean"] if stats and stats.get("average_purity", {}).get("n") else None

    clean, combined = purity(condition.rig), purity(condition.name)
    if clean is None or combined is None:
        return None
    parts = [purity(f"{condition.rig}+{p}") for p in COMBINED[condition.perturbation][1]]
    return clean - combined, None if None in parts else sum(clean - p for p in parts)


def compounding_table(summary: dict[str, dict[str, dict[str, Any]]], rows: list[Condition],
                      methods: list[str]) -> list[str]:
    """Markdown lines: each combined row's loss beside the sum of its single errors' losses."""
    combined = [c for c in rows if c.perturbation in COMBINED]
    if not combined:
        return []
    lines = ["", "### combined errors: average-purity loss against the clean row (sum of the parts' single losses)", "",
             "| condition | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for c in combined:
        cells = []
        for m in methods:
            got = compounding(summary, c, m)
            cells.append("–" if got is None else f"{got[0]:.2f}" + ("" if got[1] is None else f" ({got[1]:.2f})"))
        lines.append(f"| {c.name} | " + " | ".join(cells) + " |")
    return lines


# ---------------------------------------------------------------- documentation
#: Where the documentation's quality page includes the tables from (docs/benchmarks/quality.md).
DOCS_TABLE = REPO / "docs" / "benchmarks" / "tables" / "quality.md"


def write_docs_table(tables_md: str, path: Path = DOCS_TABLE) -> Path:
    """Write a run's rendered tables (the text of ``OUT/table.md``) where the documentation includes them."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(tables_md)
    return path


# ---------------------------------------------------------------- main
def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="3 scenes per cell, a subset of conditions (minutes)")
    p.add_argument("--scenes", type=int, default=None, help="synthetic scenes per cell (default 30, quick 3)")
    p.add_argument("--real-repeats", type=int, default=None,
                   help="perturbation seeds of the real scene's noisy rows (default 5, quick 2)")
    p.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                   help="comma-separated method names; a variant with changed settings is written "
                   "'fused(fusion_cannot_link=0.8;fusion_split_views=0)'")
    p.add_argument("--conditions", default=None, help="comma-separated globs over condition names, e.g. 'syn:*,real:0246'")
    p.add_argument("--noise-rigs", default=",".join(NOISE_RIGS), help="rigs the perturbations are applied to")
    p.add_argument("--workers", type=int, default=2, help="evaluation (and generation) processes")
    p.add_argument("--threads", type=int, default=1, help="torch threads per worker")
    p.add_argument("--cache", default=str(REPO / "out" / "bench_quality_cache"), help="generated scene cache")
    p.add_argument("--out", default=str(REPO / "out" / "bench_quality"), help="records.jsonl, summary.json, table.md")
    p.add_argument("--real", default=str(SAMPLE), help="folder of the real sample scene (Unreal layout, set 2001)")
    p.add_argument("--model", default=None, help="model file (default: the packaged model)")
    p.add_argument("--seed", type=int, default=SYNTH_SEED, help="generator dataset seed (default 9001)")
    p.add_argument("--synth", default="{}", help="JSON of SynthConfig fields applied to every synthetic rig "
                   "before the rig's own (e.g. '{\"renderer\": \"raster\"}')")
    p.add_argument("--generate-only", action="store_true", help="fill the scene cache, evaluate nothing")
    p.add_argument("--resume", action="store_true", help="keep the runs already in OUT/records.jsonl (same "
                   "condition, scene, perturbation seed and method; failed ones are run again) and run the rest")
    p.add_argument("--list", action="store_true", help="print the conditions and exit")
    p.add_argument("--docs", nargs="?", const=str(DOCS_TABLE), default=None, metavar="PATH",
                   help=f"also write the tables to PATH (default {DOCS_TABLE.relative_to(REPO)}, which the "
                   "documentation's quality page includes)")
    p.add_argument("--docs-from", metavar="OUT", default=None, help="write OUT/table.md of a finished run to "
                   "the --docs path and exit (evaluates nothing)")
    p.add_argument("--docs-metrics", default=None, metavar="KEYS",
                   help="comma-separated metrics (" + ", ".join(m[0] for m in METRICS) + ") the --docs file "
                   "keeps: their tables after the level table, without the flag and compounding tables")
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    docs_metrics = [k.strip() for k in args.docs_metrics.split(",")] if args.docs_metrics else None
    unknown = sorted(set(docs_metrics or ()) - {m[0] for m in METRICS})
    if unknown:
        print(f"unknown --docs-metrics: {', '.join(unknown)}", file=sys.stderr)
        return 2
    if args.docs_from:
        target = Path(args.docs) if args.docs else DOCS_TABLE
        text = (Path(args.docs_from) / "table.md").read_text()
        if docs_metrics:
            done = json.loads((Path(args.docs_from) / "summary.json").read_text())
            by_name = {c.name: c for c in all_conditions(False, [*SYNTH_RIGS, *REAL_RIGS])}
            header = text[:text.index("###")]  # the run's command and counts
            text = header + render_tables(done["cells"], [by_name[n] for n in done["conditions"]], done["methods"],
                                          docs_metrics)
        print(f"wrote {write_docs_table(text, target)}")
        return 0
    n_scenes = args.scenes if args.scenes is not None else (3 if args.quick else 30)
    repeats = args.real_repeats if args.real_repeats is not None else (2 if args.quick else 5)
    noise_rigs = [r.strip() for r in args.noise_rigs.split(",") if r.strip()]
    conditions = select(all_conditions(args.quick, noise_rigs), args.conditions)
    if args.list:
        for c in conditions:
            print(f"{c.name:<28} {c.description}")
        return 0
    if not conditions:
        print("no condition matches --conditions", file=sys.stderr)
        return 2
    t_start = time.perf_counter()
    overrides = json.loads(args.synth)
    scenes = {
        rig: ensure_scenes(Path(args.cache), rig, synth_config(rig, overrides), n_scenes, args.seed, args.workers)
        for rig in dict.fromkeys(c.rig for c in conditions) if rig in SYNTH_RIGS
    }
    t_generated = time.perf_counter()
    if args.generate_only:
        print(f"scene cache ready in {t_generated - t_start:.0f} s")
        return 0

    methods = accepted_methods(split_methods(args.methods))
    if not methods:
        print("no usable method", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    records_path = out / "records.jsonl"
    wanted = {c.name for c in conditions}
    old = [json.loads(line) for line in records_path.read_text().splitlines()] if args.resume and records_path.exists() else []
    records = [r for r in old if "error" not in r and r["condition"] in wanted and r["method"] in methods]
    kept = len(records)
    tasks = build_tasks(conditions, methods, scenes, Path(args.real), repeats, args.seed, map(run_key, records))
    todo = sum(len(t.conditions) * len(methods) - len(t.done) for t in tasks)
    print(f"{len(conditions)} conditions x {len(methods)} methods: {todo} runs in {len(tasks)} tasks"
          f"{f' ({len(records)} kept from {records_path})' if records else ''}, {args.workers} worker(s)", flush=True)
    with open(records_path, "w") as f:  # kept runs now, each task's runs as it finishes (an interrupted run resumes)
        f.writelines(json.dumps(r) + "\n" for r in records)

    def done(task: Task) -> None:
        records.extend(task.records)
        with open(records_path, "a") as f:
            f.writelines(json.dumps(r) + "\n" for r in task.records)
        print(f"  [{len(records)}] {task.rig} scene {task.scene_index} ({time.perf_counter() - t_generated:.0f} s)",
              flush=True)

    evaluate(tasks, args.workers, args.model, args.threads, done)
    t_end = time.perf_counter()

    order = {c.name: i for i, c in enumerate(conditions)}
    records.sort(key=lambda r: (order[r["condition"]], r["scene"], r["perturbation_seed"] or 0, methods.index(r["method"])))
    with open(records_path, "w") as f:
        f.writelines(json.dumps(r) + "\n" for r in records)
    summary = summarize_cells(records)
    command = "python benchmarks/bench_quality.py " + " ".join(argv if argv is not None else sys.argv[1:])
    cpu = sum(r.get("cpu_ms", 0.0) for r in records) / 1e3
    seconds = {"generation": round(t_generated - t_start, 1), "evaluation": round(t_end - t_generated, 1),
               "cpu_in_method_calls": round(cpu, 1)}
    (out / "summary.json").write_text(json.dumps(
        {"command": command, "methods": methods, "conditions": [c.name for c in conditions], "synth_seed": args.seed,
         "scenes_per_cell": n_scenes, "real_repeats": repeats, "seconds": seconds, "cells": summary},
        indent=1, allow_nan=True))
    table = render_tables(summary, conditions, methods)
    rows = [f"{n_scenes} synthetic scenes per cell (generator seed {args.seed})"] if scenes else []
    rows += [f"the real scene's random perturbations over {repeats} seeds"] if any(
        c.rig in REAL_RIGS and c.perturbation for c in conditions) else []
    # With --resume the wall time is this invocation's: say how many of the runs it made.
    made = f" for the {len(records) - kept} runs not kept from an earlier invocation ({kept} kept)" if kept else ""
    header = (f"Quality benchmark: `{command.strip()}`  \n{', '.join(rows + ['mean ± std'])}.  \n"
              f"Evaluation {t_end - t_generated:.0f} s wall{made} with {args.workers} worker(s) "
              f"({cpu:.0f} CPU s in the method calls of all {len(records)} runs: {cpu / args.workers:.0f} s "
              f"on {args.workers} idle cores), generation {t_generated - t_start:.0f} s\n\n")
    (out / "table.md").write_text(header + table)
    if args.docs:
        docs_table = table if docs_metrics is None else render_tables(summary, conditions, methods, docs_metrics)
        print(f"wrote {write_docs_table(header + docs_table, Path(args.docs))}")
    print()
    print(header + table)
    print(f"wrote {out / 'records.jsonl'}, {out / 'summary.json'}, {out / 'table.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
