"""``SynthConfig``: every knob of the synthetic scene generator, validated.

Defaults reproduce the reference lunar dataset: 18–20 rocks of 36–157 cm, partly sunk
in uneven ground, four cameras 90° apart on a ring of ~750 cm at 329 cm height,
1920x1080 px with fx = fy = 1615 px.  Realism knobs (noise, mask errors, dropped views)
default to off, so the default output is exact ground truth.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class SynthConfig(BaseModel):
    """Configuration of ``generate_scene`` / ``generate_dataset`` (lengths in ``units``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    units: Literal["cm"] = "cm"

    # ---- rocks
    n_rocks: tuple[int, int] = Field((18, 20), description="rocks per scene, inclusive range")
    rock_diameter: tuple[float, float] = Field((36.0, 157.0), description="largest extent, log-uniform in this range")
    rock_subdivisions: int = Field(4, ge=1, le=6, description="icosphere subdivision level (4: 5120 triangles)")
    rock_roughness: float = Field(0.22, ge=0.0, le=0.5, description="radial noise std relative to the radius")
    rock_elongation: tuple[float, float] = Field((0.55, 1.0), description="middle / largest axis ratio range")
    rock_flatness: tuple[float, float] = Field((0.35, 0.8), description="smallest / middle axis ratio range")

    # ---- field and ground
    field_radius: float = Field(320.0, gt=0, description="rocks are dropped inside this disc around the centre")
    cluster_prob: float = Field(0.35, ge=0, le=1, description="chance a rock is dropped against another")
    stack_prob: float = Field(0.3, ge=0, le=1, description="chance a rock is dropped on top of another")
    sink_depth: float = Field(5.0, ge=0, description="how deep ground-resting rocks sit in the ground")
    terrain_half_size: float = Field(1500.0, gt=0, description="ground extends +-this around the centre")
    terrain_resolution: int = Field(256, ge=16, le=2048, description="heightfield samples per side")
    terrain_relief: float = Field(12.0, ge=0, description="RMS height of the ground undulation")
    terrain_craters: int = Field(4, ge=0, le=100)

    # ---- physics
    settle_max_time: float = Field(6.0, gt=0, description="simulated seconds allowed for the rocks to come to rest")
    physics_timestep: float = Field(0.004, gt=0, le=0.01)

    # ---- camera rig
    cameras: int = Field(4, ge=1, le=64)
    radius: float = Field(750.0, gt=0, description="ring radius around the scene centre")
    radius_jitter: float = Field(0.05, ge=0, lt=1, description="relative per-camera variation of the radius")
    camera_height: float = Field(329.0, description="camera height above the scene centre")
    arc_deg: float = Field(360.0, gt=0, le=360, description="ring coverage: 360 = all round, 180, 90, ...")
    start_deg: float | None = Field(None, description="azimuth of the first camera; None = random")
    azimuths_deg: tuple[float, ...] | None = Field(
        None, description="explicit camera azimuths relative to start_deg (uneven rigs); one per camera, "
        "replaces the even spacing over arc_deg"
    )
    pitch_deg: tuple[float, float] = Field((21.0, 27.0), description="downward pitch range")
    width: int = Field(1920, ge=8, le=8192)
    height: int = Field(1080, ge=8, le=8192)
    focal_px: float = Field(1615.0, gt=0, description="fx = fy in pixels; principal point at the image centre")

    # ---- rendering and output
    renderer: Literal["auto", "gl", "raster"] = Field(
        "auto", description="gl: MuJoCo offscreen OpenGL; raster: numpy z-buffer; auto: gl if available"
    )
    background_depth: Literal["terrain", "invalid"] = Field(
        "terrain", description="ground pixels keep their depth (like the real data) or get invalid depth"
    )
    max_depth: float | None = Field(None, gt=0, description="depth beyond this is invalid (and not masked)")
    depth_format: Literal["exr", "npy", "png"] = "exr"
    mask_format: Literal["png", "npy"] = "png"

    # ---- realism knobs (all off by default)
    depth_noise: float = Field(0.0, ge=0, description="Gaussian depth noise sigma (units) on valid pixels")
    depth_quantum: float = Field(0.0, ge=0, description="round depth to multiples of this (0 = off)")
    pose_noise_translation: float = Field(0.0, ge=0, description="sigma of the declared camera position error")
    pose_noise_rotation_deg: float = Field(0.0, ge=0, description="sigma of the declared camera rotation error")
    mask_dilate_px: int = Field(0, ge=-32, le=32, description="grow (>0) or erode (<0) every instance mask")
    mask_boundary_noise: float = Field(0.0, ge=0, le=1, description="chance a pixel on an id boundary takes a neighbour's id")
    drop_view_prob: float = Field(0.0, ge=0, le=1, description="chance each view is left out of the bundle")
    min_views: int = Field(1, ge=1, description="never drop below this many views")

    @model_validator(mode="after")
    def _ranges(self) -> "SynthConfig":
        for name in ("n_rocks", "rock_diameter", "rock_elongation", "rock_flatness", "pitch_deg"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name}: lower bound {lo} exceeds upper bound {hi}")
        if self.n_rocks[0] < 1 or self.n_rocks[1] > 255:
            raise ValueError("n_rocks must lie in 1..255 (mask ids are rock ids)")
        if self.rock_diameter[0] <= 0:
            raise ValueError("rock_diameter must be positive")
        for name in ("rock_elongation", "rock_flatness"):
            lo, hi = getattr(self, name)
            if lo <= 0 or hi > 1:
                raise ValueError(f"{name} ratios must lie in (0, 1]")
        if not (0 < self.pitch_deg[0] and self.pitch_deg[1] < 90):
            raise ValueError("pitch_deg must lie in (0, 90)")
        if self.field_radius + self.rock_diameter[1] >= self.terrain_half_size:
            raise ValueError("terrain_half_size must exceed field_radius + the largest rock diameter")
        if self.azimuths_deg is not None and len(self.azimuths_deg) != self.cameras:
            raise ValueError(f"azimuths_deg has {len(self.azimuths_deg)} entries for {self.cameras} cameras")
        if self.min_views > self.cameras:
            raise ValueError("min_views cannot exceed cameras")
        return self
