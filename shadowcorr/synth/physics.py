"""Settling rocks onto the terrain under gravity with MuJoCo.

One MuJoCo model holds the whole scene and serves both physics and rendering:

* the terrain heightfield twice: a *collision* copy lowered by the sink depth
  (invisible, group 3) and a *visual* copy at the true height (no collisions,
  group 0).  Rocks come to rest on the lowered copy, so every rock that rests on the
  ground ends up buried by the sink depth in the visible ground, while rocks resting
  on other rocks stay exactly in contact with them;
* one free body per rock with the rock's full mesh.  MuJoCo collides meshes as their
  convex hulls; the renderer draws the true (non-convex) mesh.

Pitfalls handled here (also found by the feasibility probe): rocks are dropped from
just above whatever is below them (high drops bounce away), rolling friction and
per-body damping stop rounded rocks from rolling forever, and settling stops as soon
as every rock is at rest.

``mujoco`` is imported lazily so that the core library imports without it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .rocks import RockMesh
from .terrain import Terrain

if TYPE_CHECKING:  # pragma: no cover
    import mujoco

GRAVITY = 981.0  # cm/s^2: the scene is in centimetres like the reference data
ROCK_DENSITY = 2.7e-3  # kg/cm^3 (basalt); only ratios matter for the dynamics
VISUAL_GROUP = 0  # rendered geoms (rocks, visible ground)
COLLISION_GROUP = 3  # physics-only ground, never rendered or ray cast


def headless_gl_platform() -> str:
    """``egl`` when Mesa's EGL is installed, else ``osmesa`` when OSMesa is, else ``egl``
    (rendering then falls back to the numpy rasteriser).  Only file look-ups: the real
    test is ``render.gl_available``."""
    import ctypes.util

    if ctypes.util.find_library("EGL") and ctypes.util.find_library("EGL_mesa"):
        return "egl"
    if ctypes.util.find_library("OSMesa"):
        return "osmesa"
    return "egl"


def import_mujoco() -> Any:
    """Import MuJoCo or fail with the install hint (``pip install shadowcorr[synth]``)."""
    # The GL platform must be chosen before mujoco is first imported (rendering uses
    # the same module).
    if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
        os.environ["MUJOCO_GL"] = headless_gl_platform()
    try:
        import mujoco
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "shadowcorr synth needs MuJoCo: pip install 'shadowcorr[synth]' (or pip install mujoco)"
        ) from e
    return mujoco


def physics_version() -> str:
    """The MuJoCo release that settles the rocks, e.g. ``"mujoco 4.0.0"``: the same seed settles
    into another field under another release, so scenes and their records carry it."""
    return f"mujoco {import_mujoco().__version__}"


@dataclass
class PhysicsParams:
    """Knobs of the settling simulation (defaults measured to settle 20 rocks in ~1–2 s CPU)."""

    timestep: float = 0.004  # contact time constant is 0.02 s: 5 steps resolve it
    max_time: float = 6.0  # simulated seconds before giving up waiting for rest
    rest_window: float = 0.25  # seconds between rest checks
    rest_motion: float = 0.5  # units: rocks that moved less than this in a window are at rest
    final_damping_factor: float = 20.0  # damping boost for rocks not at rest after max_time
    final_time: float = 2.0  # simulated seconds of that heavily damped phase
    friction: float = 0.9  # sliding friction (regolith on rock is grippy)
    rolling_friction: float = 0.4  # units; stops rounded rocks from rolling away
    linear_damping: float = 2.0  # 1/s, relative to each body's mass (terminal speed g/2)
    angular_damping: float = 10.0  # 1/s, relative to each body's inertia
    impratio: float = 1.0  # >1 stiffens friction against contact-softness creep
    noslip_iterations: int = 0  # post-solve iterations that remove residual slip
    max_hull_vertices: int = 64  # collision hull detail: cost of every contact test grows with it
    sink: float = 5.0  # how far ground-resting rocks are buried in the visible ground


@dataclass
class Placement:
    """Initial pose of one rock before the drop."""

    position: np.ndarray  # (3,)
    quat: np.ndarray  # (4,) w, x, y, z


@dataclass
class SettledScene:
    """Result of the settling: compiled model + data at rest, plus what the physics saw."""

    model: Any  # mujoco.MjModel
    data: Any  # mujoco.MjData
    rock_geoms: np.ndarray  # (N,) geom id of rock i (rock ids are 1..N, index i-1)
    terrain_geom: int  # visual ground geom id
    rotations: np.ndarray  # (N, 3, 3): world <- rock mesh frame (the frame of RockMesh.vertices)
    translations: np.ndarray  # (N, 3): world position of each rock's mesh origin (its centroid)
    contacts: list[tuple[int, int]] = field(default_factory=list)  # rock-id pairs in contact at rest
    ground_contacts: list[int] = field(default_factory=list)  # rock ids touching the ground
    sim_time: float = 0.0
    settled: bool = False

    def world_vertices(self, i: int, rock: RockMesh) -> np.ndarray:
        """Vertices of rock ``i`` (0-based) in the world frame at rest."""
        return rock.vertices @ self.rotations[i].T + self.translations[i]


def random_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    """Uniform random unit quaternions (w, x, y, z)."""
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def place_rocks(
    rng: np.random.Generator,
    rocks: list[RockMesh],
    terrain: Terrain,
    *,
    field_radius: float,
    cluster_prob: float = 0.35,
    stack_prob: float = 0.2,
    sink: float = 0.0,
    tries: int = 40,
) -> list[Placement]:
    """Drop positions that make a natural pile: scattered, clustered and stacked rocks.

    Each rock (largest first, so small ones can land on big ones) goes either to a
    random free spot of the field disc, half-overlapping an earlier rock's footprint
    (``cluster_prob``: it falls against that rock's flank and ends up leaning on it or
    wedged beside it), or on top of a rock that itself lies on the ground
    (``stack_prob``).  The drop height clears the bounding spheres of everything already
    placed below by 1 unit, so nothing overlaps at the start and nothing falls far
    enough to bounce out of the scene.  Candidates outside the field or that would
    start higher than one rock on another are redrawn (``tries`` times; then the lowest
    candidate wins), which keeps piles from growing into towers.
    """
    order = np.argsort([-r.diameter for r in rocks])
    radius = np.array([np.linalg.norm(r.vertices, axis=1).max() for r in rocks])
    quats = random_quats(rng, len(rocks))
    xy = np.zeros((len(rocks), 2))
    z = np.zeros(len(rocks))
    on_ground = np.zeros(len(rocks), dtype=bool)
    placed: list[int] = []
    # A 5-point footprint of the bounding sphere for the ground height below it.
    ring = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], dtype=np.float64)
    for i in order:
        best: tuple[float, np.ndarray, float, bool] | None = None
        for _ in range(tries):
            mode = rng.random()
            ground_level = [j for j in placed if on_ground[j]]
            if ground_level and mode < stack_prob:
                j = ground_level[int(rng.integers(len(ground_level)))]
                p = xy[j] + rng.normal(scale=0.25 * radius[j], size=2)
            elif placed and mode < stack_prob + cluster_prob:
                j = placed[int(rng.integers(len(placed)))]
                ang = rng.uniform(0, 2 * np.pi)
                p = xy[j] + (radius[i] + radius[j]) * rng.uniform(0.6, 0.9) * np.array([np.cos(ang), np.sin(ang)])
            else:
                ang = rng.uniform(0, 2 * np.pi)
                p = field_radius * np.sqrt(rng.random()) * np.array([np.cos(ang), np.sin(ang)])
            if np.linalg.norm(p) > field_radius:
                continue  # keep the pile inside the field so that every camera sees it
            ground = float(terrain.height_at(p[0] + radius[i] * ring[:, 0], p[1] + radius[i] * ring[:, 1]).max()) - sink
            height = ground + radius[i] + 1.0
            lands_on_ground = True
            if placed:
                pj = np.array(placed)
                d = np.linalg.norm(xy[pj] - p, axis=1)
                over = d < radius[pj] + radius[i]
                if over.any():
                    # Vertical clearance above every overlapping bounding sphere.
                    rr = radius[pj][over] + radius[i] + 1.0
                    dz = np.sqrt(np.maximum(rr**2 - d[over] ** 2, 0.0))
                    height = max(height, float((z[pj][over] + dz).max()))
                    lands_on_ground = False
            excess = height - (ground + radius[i] + 1.0)
            if best is None or excess < best[0]:
                best = (excess, p, height, lands_on_ground)
            # Accept at most one rock's height above the ground: higher piles topple.
            if excess <= 2.0 * radius.max():
                break
        if best is None:  # every draw fell outside the field: drop it on the centre
            p = np.zeros(2)
            best = (0.0, p, float(z.max() + 2.0 * radius.max()), False)
        _, p, height, lands_on_ground = best
        xy[i], z[i], on_ground[i] = p, height, lands_on_ground
        placed.append(int(i))
    return [Placement(position=np.array([xy[i, 0], xy[i, 1], z[i]]), quat=quats[i]) for i in range(len(rocks))]


def build_spec(
    terrain: Terrain,
    rocks: list[RockMesh],
    placements: list[Placement],
    params: PhysicsParams,
) -> "mujoco.MjSpec":
    """The MuJoCo scene description (rocks as free bodies, terrain as two heightfields)."""
    mujoco = import_mujoco()
    spec = mujoco.MjSpec()
    spec.modelname = "shadowcorr_synth"
    spec.option.timestep = params.timestep
    spec.option.gravity = [0.0, 0.0, -GRAVITY]
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC  # needed for meaningful rolling friction
    spec.option.impratio = params.impratio
    spec.option.noslip_iterations = params.noslip_iterations

    h = terrain.heights
    lo, hi = float(h.min()), float(h.max())
    span = max(hi - lo, 1e-6)
    # MuJoCo normalises heightfield data to [0, 1] and scales it by size[2]; rows run along y.
    spec.add_hfield(
        name="terrain",
        size=[terrain.half_size, terrain.half_size, span, 50.0],
        nrow=terrain.n,
        ncol=terrain.n,
        userdata=((h - lo) / span).astype(np.float32).ravel().tolist(),
    )
    hf = mujoco.mjtGeom.mjGEOM_HFIELD
    spec.worldbody.add_geom(
        name="ground_collision", type=hf, hfieldname="terrain", pos=[0, 0, lo - params.sink],
        group=COLLISION_GROUP, friction=[params.friction, 0.02, params.rolling_friction], condim=6,
    )
    spec.worldbody.add_geom(
        name="ground", type=hf, hfieldname="terrain", pos=[0, 0, lo],
        group=VISUAL_GROUP, contype=0, conaffinity=0, rgba=[0.55, 0.55, 0.52, 1],
    )
    for i, (rock, pl) in enumerate(zip(rocks, placements)):
        spec.add_mesh(
            name=f"rock{i + 1}",
            uservert=rock.vertices.astype(np.float32).ravel().tolist(),
            userface=rock.faces.ravel().tolist(),
            maxhullvert=params.max_hull_vertices,
        )
        body = spec.worldbody.add_body(name=f"rock{i + 1}", pos=pl.position.tolist(), quat=pl.quat.tolist())
        body.add_freejoint()
        body.add_geom(
            name=f"rock{i + 1}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"rock{i + 1}",
            density=ROCK_DENSITY, group=VISUAL_GROUP, condim=6,
            friction=[params.friction, 0.02, params.rolling_friction], rgba=[0.45, 0.43, 0.4, 1],
        )
    return spec


def _kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid (R, t) minimising |R src + t - dst| (least squares, proper rotation)."""
    cs, cd = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cd - r @ cs


def settle(
    terrain: Terrain,
    rocks: list[RockMesh],
    placements: list[Placement],
    params: PhysicsParams | None = None,
    *,
    extra_spec: Any = None,
) -> SettledScene:
    """Drop the rocks and simulate until all are at rest (or ``params.max_time`` passes).

    ``extra_spec`` is called with the MjSpec before compiling (the renderer adds its
    cameras there, so one model serves physics and rendering).
    """
    mujoco = import_mujoco()
    params = params or PhysicsParams()
    spec = build_spec(terrain, rocks, placements, params)
    if extra_spec is not None:
        extra_spec(spec)
    model = spec.compile()
    data = mujoco.MjData(model)

    rock_geoms = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"rock{i + 1}") for i in range(len(rocks))])
    rock_bodies = model.geom_bodyid[rock_geoms]
    # Damping proportional to each body's own mass / inertia: the same decay rate for a
    # 36-unit pebble and a 157-unit boulder (their masses differ ~70x).
    for b in rock_bodies:
        dof = model.body_dofadr[b]
        model.dof_damping[dof:dof + 3] = params.linear_damping * model.body_mass[b]
        model.dof_damping[dof + 3:dof + 6] = params.angular_damping * model.body_inertia[b].max()

    # At rest = no rock moved more than `rest_motion` over the last check window.  A
    # velocity threshold never triggers reliably: soft contacts leave a few units/s of
    # jitter on some hull vertex, which moves nothing visibly.
    check_every = max(1, int(round(params.rest_window / params.timestep)))
    rock_qpos = model.jnt_qposadr[model.body_jntadr[rock_bodies]]

    def run_until_rest(n_steps: int) -> tuple[bool, int]:
        last = None
        step = 0
        while step < n_steps:
            for _ in range(check_every):
                mujoco.mj_step(model, data)
            step += check_every
            pos = data.qpos[rock_qpos[:, None] + np.arange(3)]
            if last is not None and np.linalg.norm(pos - last, axis=1).max() < params.rest_motion:
                return True, step
            last = pos.copy()
        return False, step

    settled, steps = run_until_rest(int(round(params.max_time / params.timestep)))
    if not settled:
        # A rock still creeping (down a crater wall, or rocking on a hull edge) after
        # max_time: finish with heavy damping, which freezes it where it is instead of
        # letting it wander further.
        model.dof_damping[:] *= params.final_damping_factor
        settled, extra = run_until_rest(int(round(params.final_time / params.timestep)))
        steps += extra
    step = steps
    data.qvel[:] = 0.0
    mujoco.mj_forward(model, data)

    # Pose of each rock's own mesh frame: MuJoCo re-centres and re-orients meshes on their
    # principal axes, so recover world <- RockMesh frame from the compiled vertices.
    rotations = np.zeros((len(rocks), 3, 3))
    translations = np.zeros((len(rocks), 3))
    for i, (g, rock) in enumerate(zip(rock_geoms, rocks)):
        mid = model.geom_dataid[g]
        adr, nv = model.mesh_vertadr[mid], model.mesh_vertnum[mid]
        compiled = model.mesh_vert[adr:adr + nv].astype(np.float64)
        world = compiled @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
        if nv == len(rock.vertices):
            r, t = _kabsch(rock.vertices, world)
            resid = np.abs(rock.vertices @ r.T + t - world).max()
        else:
            resid = np.inf
        if resid > 1e-2 * rock.diameter:
            raise RuntimeError(f"rock {i + 1}: compiled mesh does not match the generated one (resid {resid:.3g})")
        rotations[i], translations[i] = r, t

    contacts: set[tuple[int, int]] = set()
    ground: set[int] = set()
    gid_to_rock = {int(g): i + 1 for i, g in enumerate(rock_geoms)}
    for c in data.contact[: data.ncon] if data.ncon else []:
        a, b = gid_to_rock.get(int(c.geom1)), gid_to_rock.get(int(c.geom2))
        if a and b:
            contacts.add((min(a, b), max(a, b)))
        elif a or b:
            ground.add(a or b)
    return SettledScene(
        model=model, data=data, rock_geoms=rock_geoms,
        terrain_geom=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "ground"),
        rotations=rotations, translations=translations,
        contacts=sorted(contacts), ground_contacts=sorted(ground),
        sim_time=step * params.timestep, settled=settled,
    )
