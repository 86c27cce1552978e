"""The result JSON shared by the library, the CLI, the HTTP service and the client."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field, PrivateAttr

from ._version import __version__

Assignment = Literal["vote", "unfiltered_voxels", "nearest_object", "own_object", "same_mask", "evidence"]


class SegmentLabel(BaseModel):
    """One input segment (a blob of one mask value in one view) and the object it belongs to."""

    segment: int = Field(description="index of the segment in this result")
    view: str = Field(description="name of the view the segment was cut from")
    instance: int = Field(description="the mask value of the segment in its view")
    component: int = Field(description="blob index within (view, instance), largest blob first; for method "
                           "'fused' a blob that a depth step parts counts as its pieces (stage 02 depth cut)")
    num_points: int = Field(description="back-projected 3D points with valid depth")
    object: int = Field(description="object label; segments with the same label are the same physical object")
    support: float = Field(description="how sure the label is (0-1): for 'shadowcorr' and 'meanshift' the share of "
                           "the segment's voxel votes that went to its object; for 'projection' and 'fused' the "
                           "calibrated confidence of the evidence (see shadowcorr.stages, stage 09 grouping)")
    assignment: Assignment = Field(
        "vote",
        description="how the label was found: 'vote' (majority of its kept voxels); 'unfiltered_voxels' "
        "(no voxel survived the consensus filter: nearest kept voxels of its own shadow voted); "
        "'nearest_object' (no shadow at all: nearest kept voxel to its centroid); "
        "'own_object' (no valid 3D point, or its shadow is near no kept voxel: an object of its own); "
        "'same_mask' (methods 'projection' and 'fused', no valid 3D point: grouped with another blob of its mask); "
        "'evidence' (methods 'projection' and 'fused': grouped by the evidence between segments)",
    )


class OrientedBox(BaseModel):
    """A box around an object, turned about the world's up axis (bundle units).

    It spans the object's solid samples and the fused surface points near them.  Its axes are,
    in order, the longer and the shorter side of the smallest-area rectangle around the
    footprint on the ground plane, then the up axis (``ShadowCorrConfig.up_axis``): ``size`` is
    the extent along each, ``quaternion`` turns the box frame into the world frame.
    """

    center: list[float] = Field(description="box centre [x, y, z]")
    size: list[float] = Field(description="edge lengths along the box's own axes: [long, short, vertical]")
    quaternion: list[float] = Field(description="orientation, [x, y, z, w] (ROS order), box frame -> world frame")


class Extent(BaseModel):
    """Axis-aligned bounds of the surface the views saw (bundle units)."""

    min: list[float]
    max: list[float]


class ObjectSummary(BaseModel):
    """One physical object found in the scene. Lengths in the bundle's units."""

    object: int
    segments: list[int]
    views: list[str]
    centroid: list[float] | None = Field(description="mean of the object's voxel centres (or segment points)")
    bbox_min: list[float] | None
    bbox_max: list[float] | None
    num_voxels: int
    confidence: float | None = Field(None, description="mean support of its segments (0-1)")
    oriented_box: OrientedBox | None = Field(
        None, description="box around the solid samples of its largest connected set of voxels and the fused "
        "surface points near them, turned about the up axis (see OrientedBox); none without points")
    volume: float | None = Field(
        None, description="bundle units^3: the solid part of the shadow voxels it owns, which no view sees through "
        "or sees the background in front of, plus half the part only one view's background rules out "
        "(shadowcorr.stages, stage 05 occupancy); none under 'projection', for bundles without depth images, and "
        "when none of its voxels is solid")
    volume_std: float | None = Field(
        None, description="uncertainty of `volume` (bundle units^3): half the volume only one view's background rules "
        "out, the sampling of the voxels and volume_relative_std of the volume, added in quadrature")
    extent: Extent | None = Field(None, description="axis-aligned bounds of the fused surface points its box spans")
    num_views: int = Field(0, description="views whose points it holds")
    num_points: int = Field(0, description="fused surface points: the segments' cleaned points averaged per "
                            "downsample cell of the object, so that overlapping views count once")


PoseStatus = Literal["corrected", "unchanged", "not_registered", "correction_too_large", "not_confirmed"]


class ViewPoseCorrection(BaseModel):
    """What pose refinement did to one view (``refine_poses``). Lengths in the bundle's units."""

    view: str
    status: PoseStatus = Field(
        description="'corrected': registered with its neighbours and its pose moved by `correction`; 'unchanged': "
        "registered, and no view of the scene needed a correction larger than the refinement resolves, so "
        "every pose was kept exactly; "
        "'not_registered': too little overlap, degenerate or poorly fitting surface, or inconsistent with "
        "the others - its pose is kept; 'correction_too_large': the correction exceeded the configured "
        "bound - its pose is kept; with pose_mask_alignment, a view of either status is turned about its camera "
        "centre to the other views' masks instead (`correction`, `message`); "
        "'not_confirmed': corrected, the views' masks would not agree better where "
        "they see the same surface than with the declared poses (registration misled, e.g. by depth noise) - "
        "every pose of its group is kept"
    )
    rotation_deg: float = Field(description="rotation of the applied correction (0 when the pose was kept)")
    translation: float = Field(description="how far the camera centre moved (0 when the pose was kept)")
    correction: list[list[float]] = Field(
        description="4x4 world-frame rigid transform applied: refined pose = correction @ declared pose"
    )
    residual: float | None = Field(
        None, description="RMS point-to-plane distance to the overlapping neighbours after registration"
    )
    overlap: float | None = Field(
        None, description="largest share (0-1) of matched surface among its registered pairs (share of the pair's "
        "source view's sampled points within one point spacing of the other view's surface)"
    )
    neighbours: list[str] = Field(default_factory=list, description="views it was registered with")
    consistent: bool | None = Field(
        None, description="false when the refined pose still disagrees with its neighbours (a warning says so); "
        "none when the pose was kept"
    )
    message: str | None = Field(None, description="why the pose was kept, or what looks inconsistent")


class ModelInfo(BaseModel):
    name: str
    version: str
    sha256: str


class Result(BaseModel):
    """One object label per input segment, plus per-object summaries and provenance."""

    scene: str
    units: str = Field(description="length units of centroids and boxes (the bundle's units)")
    method: Literal["shadowcorr", "meanshift", "projection", "fused"]
    segments: list[SegmentLabel]
    objects: list[ObjectSummary]
    model: ModelInfo | None = Field(None, description="the network used (none for the 'meanshift' baseline)")
    timings_ms: dict[str, float] = Field(default_factory=dict)
    warnings: list[str] = Field(default_factory=list)
    metrics: dict[str, float | int] | None = Field(
        None, description="quality against the bundle's ground truth, when it has one and metrics were asked for"
    )
    poses: list[ViewPoseCorrection] | None = Field(
        None, description="per-view pose refinement report, when `refine_poses` was on"
    )
    config: dict[str, object] | None = Field(
        None, description="the ShadowCorrConfig the result was computed with (how segments were cut, clustering, ...)"
    )
    shadowcorr_version: str = __version__
    # The fused surface points of every object when the pipeline made this result (see
    # shadowcorr.object_points), so that exports do not compute them again; never serialised.
    _object_points: Any = PrivateAttr(default=None)

    @property
    def labels(self) -> list[int]:
        """Object label of each segment, in segment order."""
        return [s.object for s in self.segments]
