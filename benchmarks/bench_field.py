"""What the field-robot distribution draws, and what one of its scenes costs to generate.

Usage: python benchmarks/bench_field.py [--draws 20] [--scenes 6] [--seed 0] [--field-config FILE]

Part 1 draws ``--draws`` scene recipes (no rendering) and prints one row per draw and the
spread (min / median / max) of cameras, camera height, ring radius, rocks and rock sizes,
and how often each perturbation was drawn.  Part 2 generates ``--scenes`` scenes in this
one process (``synthesize_field``: physics, rendering, perturbations; nothing written)
and prints CPU and wall seconds per scene.  BLAS/OpenMP are held to one thread, so the
CPU seconds are those of one core.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from shadowcorr.synth import scene_seed  # noqa: E402
from shadowcorr.synth.field import (  # noqa: E402
    PERTURBATION_ORDER,
    FieldDistribution,
    sample_for_seed,
    synthesize_field,
)


def _spread(values: list[float]) -> str:
    return f"{min(values):g} / {statistics.median(values):g} / {max(values):g}"


def recipes(distribution: FieldDistribution, n: int, seed: int) -> None:
    """Print the drawn recipes of scenes 0..n-1 of a dataset with ``seed``, and their spread."""
    rows = [sample_for_seed(distribution, scene_seed(seed, i)) for i in range(n)]
    print(f"{n} drawn scene recipes (dataset seed {seed}; no rendering)\n")
    print("| scene | cameras | height cm | ring cm | arc ° | image | hfov ° | rocks | diameters cm | perturbations |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for i, r in enumerate(rows):
        c = r["config"]
        hfov = 2 * math.degrees(math.atan(c["width"] / (2 * c["focal_px"])))
        steps = ", ".join(s["name"] for s in r["perturbations"]) or "(clean)"
        print(f"| {i} | {c['cameras']} | {c['camera_height']:.0f} | {c['radius']:.0f} | {c['arc_deg']:.0f} | "
              f"{c['width']}x{c['height']} | {hfov:.0f} | {c['n_rocks'][0]} | "
              f"{c['rock_diameter'][0]:.0f}-{c['rock_diameter'][1]:.0f} | {steps} |")
    cfgs = [r["config"] for r in rows]
    print("\nspread (min / median / max):")
    for label, values in [
        ("cameras", [c["cameras"] for c in cfgs]),
        ("camera height cm", [round(c["camera_height"]) for c in cfgs]),
        ("ring radius cm", [round(c["radius"]) for c in cfgs]),
        ("rocks", [c["n_rocks"][0] for c in cfgs]),
        ("smallest rock cm", [round(c["rock_diameter"][0], 1) for c in cfgs]),
        ("largest rock cm", [round(c["rock_diameter"][1], 1) for c in cfgs]),
        ("field radius cm", [round(c["field_radius"]) for c in cfgs]),
    ]:
        print(f"  {label}: {_spread(values)}")
    counts = {name: sum(name in [s["name"] for s in r["perturbations"]] for r in rows) for name in PERTURBATION_ORDER}
    clean = sum(not r["perturbations"] for r in rows)
    print("  perturbations drawn: " + ", ".join(f"{k} {v}" for k, v in counts.items()) + f"; clean scenes {clean}")


def timing(distribution: FieldDistribution, n: int, seed: int) -> None:
    """Generate scenes 0..n-1 in this process and print CPU / wall seconds per scene."""
    print(f"\n{n} generated scenes (one process, one thread; dataset seed {seed})\n")
    print("| scene | cameras | image | rocks | renderer | CPU s | wall s | physics s | render s |")
    print("|---|---|---|---|---|---|---|---|---|")
    cpu, wall = [], []
    for i in range(n):
        c0, w0 = time.process_time(), time.perf_counter()
        scene = synthesize_field(distribution, scene_seed(seed, i))
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
        c, t = scene.truth["field"]["config"], scene.truth["timings_s"]
        print(f"| {i} | {c['cameras']} | {c['width']}x{c['height']} | {c['n_rocks'][0]} | {scene.truth['renderer']} | "
              f"{cpu[-1]:.2f} | {wall[-1]:.2f} | {t['physics']:.2f} | {t['render']:.2f} |", flush=True)
    print(f"\nper scene: CPU {statistics.mean(cpu):.2f} s mean (median {statistics.median(cpu):.2f}, "
          f"max {max(cpu):.2f}); wall {statistics.mean(wall):.2f} s mean")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=20, help="recipes to draw (no rendering)")
    ap.add_argument("--scenes", type=int, default=6, help="scenes to generate and time (0 = none)")
    ap.add_argument("--seed", type=int, default=0, help="dataset seed (scene i uses scene_seed(seed, i))")
    ap.add_argument("--field-config", help="JSON file with FieldDistribution fields (default: the defaults)")
    args = ap.parse_args()
    fields = json.loads(Path(args.field_config).read_text()) if args.field_config else {}
    distribution = FieldDistribution.model_validate(fields)
    recipes(distribution, args.draws, args.seed)
    if args.scenes:
        timing(distribution, args.scenes, args.seed)


if __name__ == "__main__":
    main()
