"""A distribution of scenes a field robot meets, for training a model beyond one rig.

``FieldDistribution`` holds ranges and choices; ``sample(rng)`` draws one ``FieldSample``:
a concrete ``SynthConfig`` (rig, rocks, ground) plus a perturbation recipe (sensor,
calibration and 2D-segmenter errors from ``shadowcorr.synth.perturb``).
``generate_field_scene(distribution, seed)`` renders the config, applies the recipe and
returns the bundle with a record of exactly what was drawn; ``generate_dataset(...,
field=distribution)`` and ``shadowcorr synth --field`` write whole datasets.

What is drawn, per scene (lengths in cm, angles in degrees):

* rig: camera count; height from one of several weighted bands (low robots at 60-100,
  mast-mounted 150-450, high 600-750); ring radius; per-camera radius jitter; pitch
  aimed at the field centre (``atan(height / radius)``) give or take ``pitch_jitter_deg``;
  a full ring or a partial arc, each camera's azimuth jittered off the even spacing;
  image size from a list and a horizontal field of view (focal length follows:
  ``fx = width / (2 tan(hfov / 2))``).
* rocks: the field radius as a share of the ring radius; the smallest diameter
  (log-uniform) and the ratio of largest to smallest, so a scene has pebbles or boulders
  or both (no rock wider than the field radius, so rocks stay inside the ring); the
  count, capped so the rocks' footprints cover at most ``max_cover`` of the field;
  cluster and stack probabilities (packing); roughness; how deep rocks sink (a share of
  the smallest diameter); ground relief and craters.
* perturbations: each kind is applied with its own probability (and none at all with
  ``clean_prob``), with its strength drawn in its range; they are applied in the fixed
  order of ``PERTURBATION_ORDER`` (sensor, calibration, then segmenter errors: merges
  first, on clean masks where rocks touch, then erosion/dilation, splits, drops and
  spurious blobs last so they stay as small as drawn).

Reproducibility: ``generate_field_scene`` splits its seed into independent streams for
drawing the sample, for the scene itself (``synthesize``) and one per perturbation kind,
so a scene depends only on the distribution and the seed, and ``sample_for_seed`` gives
its record without rendering anything.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ..bundle import SceneBundle
from .config import SynthConfig

if TYPE_CHECKING:  # generate imports this module: annotate only
    from .generate import SynthScene

__all__ = [
    "PERTURBATION_ORDER",
    "FieldDistribution",
    "FieldSample",
    "PerturbationDistribution",
    "PerturbationStep",
    "apply_perturbations",
    "generate_field_scene",
    "sample_for_seed",
    "synthesize_field",
]

PerturbationName = Literal[
    "depth_noise", "depth_holes", "pose_error", "merge_touching", "morph_masks", "split_masks", "drop_masks",
    "spurious_blobs",
]
#: The order perturbations are applied in (each is a function of ``shadowcorr.synth.perturb``).
PERTURBATION_ORDER: tuple[str, ...] = PerturbationName.__args__  # type: ignore[attr-defined]

Probability = Annotated[float, Field(ge=0.0, le=1.0)]


def _check_range(name: str, lo: float, hi: float, *, low: float | None = None, high: float | None = None,
                 positive: bool = False) -> None:
    """Raise ValueError unless ``low <= lo <= hi <= high`` (and ``lo > 0`` when ``positive``)."""
    if lo > hi:
        raise ValueError(f"{name}: lower bound {lo} exceeds upper bound {hi}")
    if positive and lo <= 0:
        raise ValueError(f"{name}: values must be > 0, got {lo}")
    if low is not None and lo < low:
        raise ValueError(f"{name}: values must be >= {low}, got {lo}")
    if high is not None and hi > high:
        raise ValueError(f"{name}: values must be <= {high}, got {hi}")


def _uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(bounds[0], bounds[1]))


def _integer(rng: np.random.Generator, bounds: tuple[int, int]) -> int:
    return int(rng.integers(bounds[0], bounds[1] + 1))


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(math.exp(rng.uniform(math.log(bounds[0]), math.log(bounds[1]))))


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# --------------------------------------------------------------------------- perturbations
class _Applied(_Frozen):
    prob: Probability = Field(0.3, description="chance this perturbation is applied to a scene")

    def draw(self, rng: np.random.Generator) -> dict[str, Any]:
        """Keyword arguments of the perturbation, drawn in the ranges (the same draws every time)."""
        raise NotImplementedError


class DepthNoiseRange(_Applied):
    """``perturb.depth_noise``: sigma = fraction * z^2 / 750 cm (the fraction is sigma/z at 7.5 m)."""

    prob: Probability = 0.5
    fraction: tuple[float, float] = (0.0, 0.02)

    def draw(self, rng: np.random.Generator) -> dict[str, Any]:
        return {"fraction": _uniform(rng, self.fraction)}


class DepthHolesRange(_Applied):
    """``perturb.depth_holes``: this share of valid depth pixels invalid, in blobs ~``blob_px`` across."""

    fraction: tuple[float, float] = (0.0, 0.1)
    blob_px: tuple[float, float] = (8.0, 24.0)

    def draw(self, rng: np.random.Generator) -> dict[str, Any]:
        return {"fraction": _uniform(rng, self.fraction), "blob_px": _uniform(rng, self.blob_px)}


class PoseErrorRange(_Applied):
    """``perturb.pose_error``: a scene's largest camera errors are drawn in these ranges; each
    camera is then off by its own amounts up to them (random axis and direction per camera)."""

    prob: Probability = 0.4
    rotation_deg: tuple[float, float] = (0.0, 2.0)
    translation_cm: tuple[float, float] = (0.0, 5.0)

    def draw(self, rng: np.random.Generator) -> dict[str, Any]:
        return {"rotation_deg": _uniform(rng, self.rotation_deg), "translation_cm": _uniform(rng, self.translation_cm),
                "up_to": True}


class MorphRange(_Applied):
    """``perturb.morph_masks``: masks dilated (> 0) or eroded (< 0) by a whole number of pixels, never 0."""

    prob: Probability = 0.5
    px: tuple[int, int] = (-5, 5)

    def draw(self, rng: np.random.Generator) -> dict[str, Any]:
        values = [p for p in range(self.px[0], self.px[1] + 1) if p != 0]  # never 0: that would change nothing
        return {"px": int(values[int(rng.integers(len(values)))])}


class ShareRange(_Applied):
    """A share of masks (splits, drops) or touching pairs (merges) affected."""

    share: tuple[float, float] = (0.0, 0.1)

    def draw(self, rng: np.random.Generator) -> dict[str, Any]:
        return {"share": _uniform(rng, self.share)}


class SpuriousRange(_Applied):
    """``perturb.spurious_blobs``: ``count`` blobs per view, semi-axes in ``radius_px``,
    the share ``on_rocks`` of them on masks."""

    count: tuple[int, int] = (1, 6)
    radius_px: tuple[float, float] = (2.0, 8.0)
    on_rocks: tuple[float, float] = (0.0, 0.5)

    def draw(self, rng: np.random.Generator) -> dict[str, Any]:
        # The blobs' semi-axes are drawn in a sub-range of radius_px: some scenes have tiny blobs only.
        lo, hi = sorted((_uniform(rng, self.radius_px), _uniform(rng, self.radius_px)))
        return {"count": _integer(rng, self.count), "radius_px": [lo, hi], "on_rocks": _uniform(rng, self.on_rocks)}


class PerturbationStep(_Frozen):
    """One perturbation to apply: a function of ``shadowcorr.synth.perturb`` and its keyword arguments."""

    name: PerturbationName
    args: dict[str, Any] = Field(default_factory=dict)


class PerturbationDistribution(_Frozen):
    """Which perturbations a scene gets, and how strong (defaults: the ranges a field rover sees)."""

    clean_prob: Probability = Field(0.15, description="chance a scene gets no perturbation at all")
    depth_noise: DepthNoiseRange = DepthNoiseRange()
    depth_holes: DepthHolesRange = DepthHolesRange()
    pose_error: PoseErrorRange = PoseErrorRange()
    merge_touching: ShareRange = ShareRange()
    morph_masks: MorphRange = MorphRange()
    split_masks: ShareRange = ShareRange(share=(0.0, 0.2))
    drop_masks: ShareRange = ShareRange()
    spurious_blobs: SpuriousRange = SpuriousRange()

    @model_validator(mode="after")
    def _ranges(self) -> "PerturbationDistribution":
        _check_range("depth_noise.fraction", *self.depth_noise.fraction, low=0.0)
        _check_range("depth_holes.fraction", *self.depth_holes.fraction, low=0.0, high=1.0)
        _check_range("depth_holes.blob_px", *self.depth_holes.blob_px, positive=True)
        _check_range("pose_error.rotation_deg", *self.pose_error.rotation_deg, low=0.0, high=180.0)
        _check_range("pose_error.translation_cm", *self.pose_error.translation_cm, low=0.0)
        _check_range("morph_masks.px", *self.morph_masks.px, low=-32, high=32)
        if self.morph_masks.px == (0, 0):
            raise ValueError("morph_masks.px: the range holds only 0 (no change); set prob 0 instead")
        for name in ("merge_touching", "split_masks", "drop_masks"):
            _check_range(f"{name}.share", *getattr(self, name).share, low=0.0, high=1.0)
        _check_range("spurious_blobs.count", *self.spurious_blobs.count, low=0)
        _check_range("spurious_blobs.radius_px", *self.spurious_blobs.radius_px, positive=True)
        _check_range("spurious_blobs.on_rocks", *self.spurious_blobs.on_rocks, low=0.0, high=1.0)
        return self

    def sample(self, rng: np.random.Generator) -> tuple[PerturbationStep, ...]:
        """The perturbations of one scene, in ``PERTURBATION_ORDER`` (empty for a clean scene).

        Every kind draws its on/off coin and its strengths whether or not it is applied,
        so changing one kind's probability leaves the others' draws unchanged."""
        clean = rng.random() < self.clean_prob
        steps = []
        for name in PERTURBATION_ORDER:
            spec = getattr(self, name)
            applied = rng.random() < spec.prob
            args = spec.draw(rng)
            if applied and not clean:
                steps.append(PerturbationStep(name=name, args=args))
        return tuple(steps)


def apply_perturbations(bundle: SceneBundle, steps: tuple[PerturbationStep, ...],
                        seed: np.random.SeedSequence | int) -> SceneBundle:
    """``bundle`` with ``steps`` applied in order; each kind uses its own stream of ``seed``.

    The streams are indexed by the kind's place in ``PERTURBATION_ORDER``, so whether
    one kind is applied does not change what another does."""
    from . import perturb

    root = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(int(seed))
    for step in steps:
        # the k-th child of root, as root.spawn would make it, without spawn's counter (calls stay repeatable)
        stream = np.random.SeedSequence(root.entropy, spawn_key=(*root.spawn_key, PERTURBATION_ORDER.index(step.name)))
        bundle = getattr(perturb, step.name)(bundle, np.random.default_rng(stream), **step.args)
    return bundle


# --------------------------------------------------------------------------- scenes
class FieldSample(_Frozen):
    """One draw of a ``FieldDistribution``: what to render and what to do to it."""

    config: SynthConfig
    perturbations: tuple[PerturbationStep, ...] = ()


class FieldDistribution(_Frozen):
    """Ranges and choices of the scenes a field robot meets (lengths in cm, angles in degrees).

    A range ``(lo, hi)`` is drawn uniformly unless its description says log-uniform;
    integer ranges include both ends.  ``sample(rng)`` draws one ``FieldSample``.
    """

    # ---- rig
    cameras: tuple[int, int] = Field((2, 12), description="cameras per scene, inclusive range")
    camera_height_bands: tuple[tuple[float, float, float], ...] = Field(
        ((60.0, 100.0, 0.3), (150.0, 450.0, 0.45), (600.0, 750.0, 0.25)),
        description="(lo, hi, weight): a band is chosen by weight, the height uniform in it",
    )
    ring_radius: tuple[float, float] = Field((300.0, 1100.0), description="camera distance from the field centre")
    radius_jitter: tuple[float, float] = Field((0.0, 0.08), description="relative per-camera radius variation")
    pitch_jitter_deg: float = Field(3.0, ge=0.0, le=30.0,
                                    description="each camera's pitch is the aim at the centre +- this")
    full_ring_prob: Probability = Field(0.5, description="chance the cameras go all round; else a partial arc")
    arc_deg: tuple[float, float] = Field((60.0, 300.0), description="span of a partial arc")
    azimuth_jitter: tuple[float, float] = Field(
        (0.0, 0.3), description="per-camera azimuth offset, as a share of the even spacing (uneven rigs)"
    )
    resolutions: tuple[tuple[int, int], ...] = Field(
        ((640, 480), (1280, 720), (1920, 1080)), description="(width, height) choices, equally likely"
    )
    hfov_deg: tuple[float, float] = Field((50.0, 90.0), description="horizontal field of view (sets the focal length)")

    # ---- rocks and ground
    n_rocks: tuple[int, int] = Field((3, 40), description="rocks per scene before the cover cap, inclusive")
    min_diameter: tuple[float, float] = Field((8.0, 60.0), description="smallest rock diameter, log-uniform")
    size_ratio: tuple[float, float] = Field((2.0, 8.0), description="largest / smallest diameter, log-uniform")
    max_diameter: float = Field(400.0, gt=0, description="no rock larger than this")
    field_share: tuple[float, float] = Field((0.25, 0.55), description="field radius / ring radius")
    max_cover: float = Field(0.5, gt=0.0, le=2.0,
                             description="cap on the rocks' summed footprints / field area (stacks may exceed 1)")
    cluster_prob: tuple[float, float] = Field((0.0, 0.7), description="chance a rock falls against another")
    stack_prob: tuple[float, float] = Field((0.0, 0.5), description="chance a rock falls onto another")
    rock_roughness: tuple[float, float] = Field((0.12, 0.3), description="radial noise relative to the radius")
    sink_share: tuple[float, float] = Field((0.0, 0.15), description="sink depth / smallest diameter")
    terrain_relief: tuple[float, float] = Field((0.0, 20.0), description="RMS height of the ground undulation")
    terrain_craters: tuple[int, int] = Field((0, 8))

    # ---- fixed for every scene
    terrain_half_size: float = Field(1500.0, gt=0)
    terrain_resolution: int = Field(256, ge=16, le=2048)
    rock_subdivisions: int = Field(4, ge=1, le=6)
    background_depth: Literal["terrain", "invalid"] = "terrain"
    renderer: Literal["auto", "gl", "raster"] = "auto"
    depth_format: Literal["exr", "npy", "png"] = "exr"
    mask_format: Literal["png", "npy"] = "png"

    perturbations: PerturbationDistribution = PerturbationDistribution()

    @model_validator(mode="after")
    def _ranges(self) -> "FieldDistribution":
        _check_range("cameras", *self.cameras, low=1, high=64)
        if not self.camera_height_bands:
            raise ValueError("camera_height_bands: give at least one (lo, hi, weight) band")
        for lo, hi, weight in self.camera_height_bands:
            _check_range("camera_height_bands", lo, hi, positive=True)
            if weight < 0:
                raise ValueError(f"camera_height_bands: weights must be >= 0, got {weight}")
        if sum(b[2] for b in self.camera_height_bands) <= 0:
            raise ValueError("camera_height_bands: the weights sum to 0")
        _check_range("ring_radius", *self.ring_radius, positive=True)
        _check_range("radius_jitter", *self.radius_jitter, low=0.0, high=0.5)
        _check_range("arc_deg", *self.arc_deg, positive=True, high=360.0)
        _check_range("azimuth_jitter", *self.azimuth_jitter, low=0.0, high=0.5)
        if not self.resolutions:
            raise ValueError("resolutions: give at least one (width, height)")
        for w, h in self.resolutions:
            if not (8 <= w <= 8192 and 8 <= h <= 8192):
                raise ValueError(f"resolutions: {w}x{h} is outside 8..8192 pixels")
        _check_range("hfov_deg", *self.hfov_deg, positive=True, high=170.0)
        _check_range("n_rocks", *self.n_rocks, low=1, high=255)
        _check_range("min_diameter", *self.min_diameter, positive=True)
        _check_range("size_ratio", *self.size_ratio, low=1.0)
        _check_range("field_share", *self.field_share, positive=True, high=0.9)
        for name in ("cluster_prob", "stack_prob"):
            _check_range(name, *getattr(self, name), low=0.0, high=1.0)
        _check_range("rock_roughness", *self.rock_roughness, low=0.0, high=0.5)
        _check_range("sink_share", *self.sink_share, low=0.0, high=0.5)
        _check_range("terrain_relief", *self.terrain_relief, low=0.0)
        _check_range("terrain_craters", *self.terrain_craters, low=0, high=100)
        if self.min_diameter[0] > self.max_diameter:
            raise ValueError(f"min_diameter starts at {self.min_diameter[0]}, above max_diameter {self.max_diameter}")
        # The farthest camera and the widest field must stay on the ground.
        far = self.ring_radius[1] * (1.0 + self.radius_jitter[1])
        if far >= self.terrain_half_size:
            raise ValueError(f"terrain_half_size {self.terrain_half_size} must exceed the farthest camera ({far:.0f})")
        widest = self.field_share[1] * self.ring_radius[1]  # rocks reach at most field radius + largest rock <= 2x
        if 2.0 * widest >= self.terrain_half_size:
            raise ValueError(f"terrain_half_size {self.terrain_half_size} must exceed twice the widest field "
                             f"({widest:.0f})")
        return self

    def sample(self, rng: np.random.Generator) -> FieldSample:
        """Draw one scene: a validated ``SynthConfig`` and its perturbation recipe."""
        # ---- rig
        n_cams = _integer(rng, self.cameras)
        weights = np.array([b[2] for b in self.camera_height_bands], dtype=np.float64)
        band = self.camera_height_bands[int(rng.choice(len(weights), p=weights / weights.sum()))]
        height = _uniform(rng, band[:2])
        radius = _uniform(rng, self.ring_radius)
        aim = math.degrees(math.atan2(height, radius))
        pitch = (max(0.5, aim - self.pitch_jitter_deg), min(89.0, aim + self.pitch_jitter_deg))
        full_ring = bool(rng.random() < self.full_ring_prob)
        arc = 360.0 if full_ring else _uniform(rng, self.arc_deg)
        spacing = arc / n_cams if full_ring or n_cams == 1 else arc / (n_cams - 1)
        jitter = _uniform(rng, self.azimuth_jitter) * spacing
        even = np.arange(n_cams) * spacing
        azimuths = even + rng.uniform(-jitter, jitter, size=n_cams)
        azimuths[0] = 0.0  # the first camera defines the start azimuth
        start = _uniform(rng, (0.0, 360.0))
        width, height_px = self.resolutions[int(rng.integers(len(self.resolutions)))]
        hfov = _uniform(rng, self.hfov_deg)
        focal = width / (2.0 * math.tan(math.radians(hfov) / 2.0))

        # ---- rocks and ground
        field_radius = _uniform(rng, self.field_share) * radius
        d_lo = min(_log_uniform(rng, self.min_diameter), self.max_diameter)
        d_hi = min(d_lo * _log_uniform(rng, self.size_ratio), self.max_diameter, field_radius)
        d_lo = min(d_lo, d_hi)
        n_drawn = _integer(rng, self.n_rocks)
        # Mean footprint of a log-uniform diameter: pi/4 E[d^2], E[d^2] = (hi^2 - lo^2) / (2 ln(hi / lo)).
        mean_d2 = d_lo * d_lo if d_hi <= d_lo * (1 + 1e-9) else (d_hi ** 2 - d_lo ** 2) / (2.0 * math.log(d_hi / d_lo))
        fits = int(self.max_cover * field_radius ** 2 * 4.0 / mean_d2)
        n_rocks = max(1, min(n_drawn, fits))
        config = SynthConfig(
            n_rocks=(n_rocks, n_rocks),
            rock_diameter=(d_lo, d_hi),
            rock_subdivisions=self.rock_subdivisions,
            rock_roughness=_uniform(rng, self.rock_roughness),
            field_radius=field_radius,
            cluster_prob=_uniform(rng, self.cluster_prob),
            stack_prob=_uniform(rng, self.stack_prob),
            sink_depth=_uniform(rng, self.sink_share) * d_lo,
            terrain_half_size=self.terrain_half_size,
            terrain_resolution=self.terrain_resolution,
            terrain_relief=_uniform(rng, self.terrain_relief),
            terrain_craters=_integer(rng, self.terrain_craters),
            cameras=n_cams,
            radius=radius,
            radius_jitter=_uniform(rng, self.radius_jitter),
            camera_height=height,
            arc_deg=arc,
            start_deg=start,
            azimuths_deg=tuple(float(a) for a in azimuths),
            pitch_deg=pitch,
            width=width,
            height=height_px,
            focal_px=focal,
            renderer=self.renderer,
            background_depth=self.background_depth,
            depth_format=self.depth_format,
            mask_format=self.mask_format,
        )
        return FieldSample(config=config, perturbations=self.perturbations.sample(rng))


# --------------------------------------------------------------------------- generation
def _draw(distribution: FieldDistribution, seed: int) -> tuple[FieldSample, dict[str, Any], np.random.SeedSequence]:
    """Field scene ``seed``: the drawn sample, its record, and the perturbations' stream.

    The seed splits into independent streams for the draw, for the scene itself (the
    seed ``synthesize`` gets) and for the perturbations."""
    sample_ss, scene_ss, perturb_ss = np.random.SeedSequence(int(seed)).spawn(3)
    drawn = distribution.sample(np.random.default_rng(sample_ss))
    record = {
        "seed": int(seed),
        "scene_seed": int(scene_ss.generate_state(1, dtype=np.uint32)[0]),
        "config": drawn.config.model_dump(mode="json"),
        "perturbations": [s.model_dump(mode="json") for s in drawn.perturbations],
    }
    return drawn, record, perturb_ss


def sample_for_seed(distribution: FieldDistribution, seed: int) -> dict[str, Any]:
    """The record of field scene ``seed`` without rendering it: what ``generate_field_scene`` draws.

    Keys: ``seed``, ``scene_seed`` (the seed ``synthesize`` gets), ``config`` (the drawn
    ``SynthConfig``), ``perturbations`` (steps in the order applied, ``[]`` = clean)."""
    return _draw(distribution, seed)[1]


def synthesize_field(distribution: FieldDistribution, seed: int) -> "SynthScene":
    """A field scene as a ``SynthScene``: the perturbed bundle, and the generator's truth with
    the record of ``sample_for_seed`` under ``truth["field"]`` (the truth's rock pixel
    counts and true camera poses are those of the exact, unperturbed rendering)."""
    from .generate import synthesize

    drawn, record, perturb_ss = _draw(distribution, seed)
    scene = synthesize(drawn.config, record["scene_seed"])
    scene.bundle = apply_perturbations(scene.bundle, drawn.perturbations, perturb_ss)
    scene.truth["field"] = record
    return scene


def generate_field_scene(distribution: FieldDistribution, seed: int) -> tuple[SceneBundle, dict[str, Any]]:
    """One scene of ``distribution``: the (perturbed) bundle and the record of what was drawn
    (the same dict as ``sample_for_seed(distribution, seed)``).

    The bundle's ground truth is ``instance`` when no perturbation changed mask ids, else
    ``mapped`` (each view's ``instance_objects``); either way every mask id's object is exact."""
    scene = synthesize_field(distribution, seed)
    return scene.bundle, scene.truth["field"]
