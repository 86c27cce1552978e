"""Scene synthesis end to end, and whole datasets in parallel worker processes.

A scene is: random ground -> random rocks -> dropped and settled by MuJoCo -> camera
ring -> depth + instance masks rendered -> optional sensor errors -> ``SceneBundle``
with ``ground_truth="instance"`` (mask id k is rock k in every view).

Reproducibility: a scene depends only on its seed and the config.  The seed feeds a
``numpy.random.SeedSequence`` whose independent child streams drive the ground, the
rocks, the drop, the cameras and the noise separately (so, e.g., changing the camera
count leaves the rock field unchanged).  Scene ``i`` of a dataset uses
``scene_seed(seed, i)``, so results do not depend on the number of workers or on the
order in which workers finish.

Field datasets (``generate_dataset(field=FieldDistribution(...))``, ``synth --field``)
draw every scene's config and perturbations from a distribution instead
(``shadowcorr.synth.field``): scene ``i`` is ``synthesize_field(field, scene_seed(seed, i))``
and ``dataset.json`` lists what each scene drew.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .._version import __version__
from ..bundle import Intrinsics, SceneBundle, View
from .cameras import Camera, make_rig
from .config import SynthConfig
from .noise import boundary_noise, morph_mask, noisy_depth, noisy_pose
from .physics import PhysicsParams, physics_version, place_rocks, settle
from .rocks import RockMesh, make_rock, sample_diameters
from .terrain import make_terrain

if TYPE_CHECKING:
    from .field import FieldDistribution

DATASET_FILE = "dataset.json"
TRUTH_FILE = "synth_truth.json"


@dataclass
class SynthScene:
    """A generated scene: the bundle plus everything known about how it was made."""

    bundle: SceneBundle
    truth: dict[str, Any]  # JSON-able: rocks, contacts, true poses, timings (see synthesize)
    rocks: list[RockMesh] = field(default_factory=list)
    rotations: np.ndarray | None = None  # (N, 3, 3) world <- rock frame
    translations: np.ndarray | None = None  # (N, 3) rock centroids in the world
    cameras: list[Camera] = field(default_factory=list)  # true (rendered) cameras, dropped ones included


def scene_seed(seed: int, index: int) -> int:
    """Seed of scene ``index`` of a dataset generated with ``seed`` (independent streams)."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1, dtype=np.uint32)[0])


def resolve_renderer(requested: str) -> str:
    """``auto`` -> ``gl`` when a headless GL context works here, else ``raster``."""
    from .render import gl_available

    if requested == "raster":
        return "raster"
    if gl_available():
        return "gl"
    if requested == "gl":
        raise RuntimeError(
            "renderer 'gl' needs a headless OpenGL for MuJoCo: set MUJOCO_GL=egl and install "
            "libegl1 libegl-mesa0 libgl1-mesa-dri (Debian), or MUJOCO_GL=osmesa with libosmesa6; "
            "or use renderer 'raster' (pure numpy, no system packages)"
        )
    return "raster"


def synthesize(config: SynthConfig, seed: int) -> SynthScene:
    """Generate one scene (bundle + ground-truth record) from ``config`` and ``seed``."""
    from . import render

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    rng_terrain, rng_rocks, rng_drop, rng_cams, rng_noise = (
        np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(5)
    )

    terrain = make_terrain(
        rng_terrain, half_size=config.terrain_half_size, resolution=config.terrain_resolution,
        relief=config.terrain_relief, n_craters=config.terrain_craters,
    )
    n_rocks = int(rng_rocks.integers(config.n_rocks[0], config.n_rocks[1] + 1))
    rocks = [
        make_rock(
            rng_rocks, d, subdivisions=config.rock_subdivisions, roughness=config.rock_roughness,
            elongation=config.rock_elongation, flatness=config.rock_flatness,
        )
        for d in sample_diameters(rng_rocks, n_rocks, *config.rock_diameter)
    ]
    placements = place_rocks(
        rng_drop, rocks, terrain, field_radius=config.field_radius,
        cluster_prob=config.cluster_prob, stack_prob=config.stack_prob, sink=config.sink_depth,
    )
    cameras = make_rig(
        rng_cams, n_cameras=config.cameras, radius=config.radius, height=config.camera_height,
        arc_deg=config.arc_deg, start_deg=config.start_deg, azimuths_deg=config.azimuths_deg, pitch_deg=config.pitch_deg,
        radius_jitter=config.radius_jitter, width=config.width, height_px=config.height,
        focal_px=config.focal_px,
    )
    timings["build"] = time.perf_counter() - t0

    backend = resolve_renderer(config.renderer)
    params = PhysicsParams(timestep=config.physics_timestep, max_time=config.settle_max_time, sink=config.sink_depth)
    t = time.perf_counter()
    settled = settle(
        terrain, rocks, placements, params,
        extra_spec=(lambda spec: render.add_gl_cameras(spec, cameras)) if backend == "gl" else None,
    )
    timings["physics"] = time.perf_counter() - t

    t = time.perf_counter()
    views = None
    if backend == "gl":
        try:
            views = render.render_gl(settled.model, settled.data, cameras, settled.rock_geoms)
        except Exception:
            if config.renderer == "gl":
                raise
            backend = "raster"  # "auto": same images from the numpy rasteriser
    if views is None:
        tv, tf = terrain.mesh()
        verts, faces, ids = render.scene_triangles(
            [settled.world_vertices(i, r) for i, r in enumerate(rocks)], [r.faces for r in rocks], tv, tf
        )
        views = [render.rasterize(c, verts, faces, ids) for c in cameras]
    timings["render"] = time.perf_counter() - t

    # Exact images -> what the bundle carries (validity rules, then the realism knobs).
    out_views: list[View] = []
    cam_records = []
    pixels: dict[int, dict[str, int]] = {k: {} for k in range(1, n_rocks + 1)}
    keep = rng_noise.random(len(cameras)) >= config.drop_view_prob
    if keep.sum() < config.min_views:  # re-admit the first dropped views to reach the minimum
        for k in np.nonzero(~keep)[0][: config.min_views - int(keep.sum())]:
            keep[k] = True
    for k, (cam, rv) in enumerate(zip(cameras, views)):
        depth, mask = rv.depth, rv.ids
        if config.max_depth is not None:
            far = depth > config.max_depth
            depth = np.where(far, 0.0, depth).astype(np.float32)
            mask = np.where(far, 0, mask)
        if config.background_depth == "invalid":
            depth = np.where(mask > 0, depth, 0.0).astype(np.float32)
        # Exact visibility (before mask errors) for the ground-truth record.
        counts = np.bincount(mask.ravel(), minlength=n_rocks + 1)
        for rid in np.nonzero(counts[1:])[0] + 1:
            pixels[int(rid)][cam.name] = int(counts[rid])
        mask = boundary_noise(rng_noise, morph_mask(mask, config.mask_dilate_px), config.mask_boundary_noise)
        if config.depth_noise > 0 or config.depth_quantum > 0:
            depth = noisy_depth(rng_noise, depth, config.depth_noise, config.depth_quantum)
        pose = noisy_pose(rng_noise, cam.pose, config.pose_noise_translation, config.pose_noise_rotation_deg)
        cam_records.append({"name": cam.name, "pose_true": cam.pose.tolist(), "dropped": not bool(keep[k])})
        if not keep[k]:
            continue
        out_views.append(
            View(
                name=cam.name, pose=pose,
                intrinsics=Intrinsics(fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy, width=cam.width, height=cam.height),
                depth=depth.astype(np.float32), mask=mask.astype(np.int32),
            )
        )
    timings["total"] = time.perf_counter() - t0

    on_ground = set(settled.ground_contacts)
    truth = {
        "generator": "shadowcorr.synth",
        "shadowcorr_version": __version__,
        "seed": int(seed),
        "units": config.units,
        "renderer": backend,
        "physics": physics_version(),
        "settled": settled.settled,
        "sim_time_s": round(settled.sim_time, 3),
        "rocks": [
            {
                "id": i + 1,
                "diameter": round(rock.diameter, 3),
                "volume": round(rock.volume, 1),
                "centroid": settled.translations[i].round(4).tolist(),
                "rotation": settled.rotations[i].round(8).tolist(),
                "on_ground": (i + 1) in on_ground,
                "pixels": pixels[i + 1],
            }
            for i, rock in enumerate(rocks)
        ],
        "contacts": [list(p) for p in settled.contacts],
        "cameras": cam_records,
        "timings_s": {k: round(v, 4) for k, v in timings.items()},
    }
    bundle = SceneBundle(units=config.units, views=out_views, name=f"synth_{int(seed)}", ground_truth="instance")
    return SynthScene(
        bundle=bundle, truth=truth, rocks=rocks, rotations=settled.rotations,
        translations=settled.translations, cameras=cameras,
    )


def generate_scene(config: SynthConfig | None = None, seed: int = 0) -> SceneBundle:
    """One synthetic scene as a ``SceneBundle`` (mask ids = rock ids, ground truth ``instance``)."""
    return synthesize(config or SynthConfig(), seed).bundle


def write_scene(scene: SynthScene, out_dir: str | Path, config: SynthConfig) -> Path:
    """Write a scene as a bundle directory plus ``synth_truth.json`` beside its manifest."""
    from ..io import write_bundle

    path = write_bundle(scene.bundle, Path(out_dir), depth_format=config.depth_format, mask_format=config.mask_format)
    (path / TRUTH_FILE).write_text(json.dumps(scene.truth, indent=1))
    return path


def _one(job: tuple[str, dict, int, int, str]) -> tuple[int, str, dict[str, Any]]:
    """Worker: generate and write scene ``index``; returns only a small summary.

    ``job`` = (kind, spec, index, seed, out): kind ``config`` renders the ``SynthConfig``
    ``spec``; kind ``field`` draws the scene from the ``FieldDistribution`` ``spec``."""
    kind, spec, index, seed, out = job
    if kind == "field":
        from .field import FieldDistribution, synthesize_field

        scene = synthesize_field(FieldDistribution.model_validate(spec), seed)
        config = SynthConfig.model_validate(scene.truth["field"]["config"])
    else:
        config = SynthConfig.model_validate(spec)
        scene = synthesize(config, seed)
    path = write_scene(scene, out, config)
    t = scene.truth
    return index, str(path), {"contacts": len(t["contacts"]), "rocks": len(t["rocks"]), "seconds": t["timings_s"]["total"]}


def _init_worker() -> None:
    """One thread per worker process: the workers already fill the cores."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "LP_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def generate_dataset(
    config: SynthConfig | None = None,
    n_scenes: int = 1,
    out_dir: str | Path = "synth",
    seed: int = 0,
    workers: int = 1,
    *,
    progress: bool = True,
    resume: bool = False,
    field: FieldDistribution | None = None,
) -> list[Path]:
    """Generate ``n_scenes`` bundles ``out_dir/scene_00000 ...`` plus ``out_dir/dataset.json``.

    Every scene uses ``config``, or, with ``field``, draws its own config and perturbations
    from that distribution (``config`` must then be None); ``dataset.json`` then records
    the distribution under ``field`` and, per scene, exactly what was drawn (``scene_seed``,
    ``config``, ``perturbations``; see ``shadowcorr.synth.field.sample_for_seed``).

    ``workers`` > 1 runs scenes in that many spawned processes (spawn, not fork: OpenGL
    contexts and MuJoCo do not survive a fork safely).  ``resume`` skips scenes whose
    manifest already exists (an interrupted run can be continued with the same seed).
    Returns the scene directories in index order.  As with any spawn-based pool, a
    script calling this with ``workers`` > 1 needs an ``if __name__ == "__main__":`` guard.
    """
    from tqdm import tqdm

    if field is not None and config is not None:
        raise ValueError("give either config or field, not both")
    if field is None:
        config = config or SynthConfig()
    if n_scenes < 0:
        raise ValueError("n_scenes must be >= 0")
    if workers < 1:
        raise ValueError("workers must be >= 1")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scenes = [
        {"index": i, "dir": f"scene_{i:05d}", "seed": scene_seed(seed, i)} for i in range(n_scenes)
    ]
    record = {
        "format": "shadowcorr-synth-dataset",
        "version": 1,
        "shadowcorr_version": __version__,
        "physics": physics_version(),
        "seed": int(seed),
        "n_scenes": n_scenes,
        "seed_rule": "scene i uses SeedSequence([seed, i]).generate_state(1, uint32)[0]",
    }
    if field is None:
        record["config"] = config.model_dump(mode="json")
        job_kind, spec = "config", config.model_dump(mode="json")
    else:
        from .field import sample_for_seed

        record["field"] = field.model_dump(mode="json")
        record["field_rule"] = "scene i is shadowcorr.synth.field.synthesize_field(field, its seed)"
        for s in scenes:  # drawing needs no rendering: the record is complete before any scene exists
            s.update({k: v for k, v in sample_for_seed(field, s["seed"]).items() if k != "seed"})
        job_kind, spec = "field", field.model_dump(mode="json")
    record["scenes"] = scenes
    # Written first (an interrupted run still records how it was made) and again at the end.
    (out / DATASET_FILE).write_text(json.dumps(record, indent=1))

    jobs = [
        (job_kind, spec, s["index"], s["seed"], str(out / s["dir"]))
        for s in scenes
        if not (resume and (out / s["dir"] / "manifest.json").exists())
    ]
    paths = {s["index"]: out / s["dir"] for s in scenes}
    bar = tqdm(total=n_scenes, initial=n_scenes - len(jobs), unit="scene", desc="synth", disable=not progress)
    contacts = 0
    done = 0
    pool = None
    try:
        if workers == 1 or len(jobs) <= 1:
            results = map(_one, jobs)
        else:
            pool = mp.get_context("spawn").Pool(processes=min(workers, len(jobs)), initializer=_init_worker)
            results = pool.imap_unordered(_one, jobs)
        for _, _, info in results:
            done += 1
            contacts += info["contacts"]
            bar.update(1)
            bar.set_postfix(contacts_per_scene=f"{contacts / done:.1f}")
        if pool is not None:
            pool.close()
            pool.join()
    except BaseException:
        if pool is not None:
            pool.terminate()
        raise
    finally:
        bar.close()
    (out / DATASET_FILE).write_text(json.dumps(record, indent=1))
    return [paths[i] for i in range(n_scenes)]
