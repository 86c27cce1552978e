"""Check that a refactor changes no result: record every scene's result under every method, then compare two records.

    PYTHONPATH=OLD_CHECKOUT python scripts/compare_labels.py record before.json
    PYTHONPATH=$PWD         python scripts/compare_labels.py record after.json
    python scripts/compare_labels.py compare before.json after.json

Scenes: the real sample (cameras 0,2,4,6 and 0,1,2; split masks, merged masks, a 1-degree
pose error with refinement on), two analytic sphere scenes and one small synthetic rock
field.  Per scene and method the record holds the labels, the supports, the metrics and a
hash of the whole result JSON (timings, version and the model file's hash left out; the
model hash is recorded apart), and per scene a hash of the network embeddings' bytes.
Run it with the working directory at the repository root (it reads ``examples/ue_sample``).
Nothing here is a test: records are compared with each other, never with stored numbers.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from typing import Any, Iterator

import numpy as np

METHODS = ("fused", "projection", "shadowcorr", "meanshift")


def scenes() -> Iterator[tuple[str, Any]]:
    from shadowcorr.convert import load_ue_scene
    from shadowcorr.synth import SynthConfig, generate_scene, perturb
    from shadowcorr.synth.spheres import sphere_scene

    base = load_ue_scene("examples/ue_sample", 2001, [0, 2, 4, 6])
    yield "ue_0246", base
    yield "ue_012", load_ue_scene("examples/ue_sample", 2001, [0, 1, 2])
    rng = np.random.default_rng(3)
    centres = rng.uniform(-150, 150, (8, 3))
    centres[:, 2] = 0
    yield "spheres8", sphere_scene(centres, rng.uniform(25, 45, 8), cameras=4)
    yield "spheres_touch", sphere_scene([[0, 0, 0], [70, 0, 0], [0, 90, 0]], [40, 35, 50], cameras=3, arc_deg=120)
    yield "ue_split", perturb.split_masks(base, np.random.default_rng(1), 0.3)
    yield "ue_merge", perturb.merge_touching(base, np.random.default_rng(2), 0.5)
    yield "ue_pose_refined", perturb.pose_error(base, np.random.default_rng(4), rotation_deg=1.0)
    small = SynthConfig(renderer="raster", width=480, height=270, focal_px=404, n_rocks=(8, 10),
                        terrain_resolution=64, settle_max_time=1.0)
    yield "synth_raster", generate_scene(small, seed=5)


def record(path: str, threads: int = 1) -> None:
    import torch

    import shadowcorr

    torch.set_num_threads(threads)
    out: dict[str, Any] = {}
    model = shadowcorr.load_model()
    for name, bundle in scenes():
        for method in METHODS:
            config = shadowcorr.ShadowCorrConfig(method=method, refine_poses=name == "ue_pose_refined",
                                                 num_threads=threads)
            doc = shadowcorr.correspond(bundle, model=model, config=config).model_dump(mode="json")
            for volatile in ("timings_ms", "shadowcorr_version"):
                doc.pop(volatile, None)
            doc["config"].pop("num_threads", None)  # how the work was spread, not what it computes
            model_sha = doc["model"].pop("sha256") if doc.get("model") else None
            out[f"{name}/{method}"] = {
                "labels": [s["object"] for s in doc["segments"]],
                "support": [s["support"] for s in doc["segments"]],
                "metrics": doc["metrics"],
                "sha": hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest(),
                "model_sha": model_sha,
            }
            print(f"{name:16s} {method:10s} {len(doc['segments'])} segments -> {len(doc['objects'])} objects", flush=True)
        (embeddings,) = shadowcorr.embed(model, [shadowcorr.prepare(bundle, shadowcorr.ShadowCorrConfig(num_threads=threads))])
        out[f"{name}/embeddings"] = hashlib.sha256(np.ascontiguousarray(embeddings).tobytes()).hexdigest()
    with open(path, "w") as fh:
        json.dump(out, fh, indent=1)


def compare(a_path: str, b_path: str) -> int:
    with open(a_path) as fa, open(b_path) as fb:
        a, b = json.load(fa), json.load(fb)
    if a.keys() != b.keys():
        print(f"different entries: {sorted(set(a) ^ set(b))}")
        return 1

    def without_model_sha(v: Any) -> Any:
        return {k: x for k, x in v.items() if k != "model_sha"} if isinstance(v, dict) else v

    differing = [k for k in a if without_model_sha(a[k]) != without_model_sha(b[k])]
    results = [k for k in a if not k.endswith("/embeddings")]
    model_shas = sorted({(a[k]["model_sha"], b[k]["model_sha"]) for k in results if a[k]["model_sha"]})
    print(f"{len(results)} scene x method results, {len(a) - len(results)} embedding hashes; "
          f"differing: {differing or 'none'}; model file sha256 (first -> second): {model_shas}")
    return 1 if differing else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="write the results of this checkout")
    rec.add_argument("out")
    rec.add_argument("--threads", type=int, default=1, help="num_threads of the configuration and torch's threads")
    cmp = sub.add_parser("compare", help="compare two records; exit 1 when anything differs")
    cmp.add_argument("first")
    cmp.add_argument("second")
    args = parser.parse_args(argv)
    if args.command == "record":
        record(args.out, args.threads)
        return 0
    return compare(args.first, args.second)


if __name__ == "__main__":
    sys.exit(main())
