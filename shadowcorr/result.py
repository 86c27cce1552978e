"""The result JSON shared by the library, the CLI, the HTTP service and the client."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

from ._version import __version__

Assignment = Literal["vote", "unfiltered_voxels", "nearest_object", "own_object", "evidence"]


class SegmentLabel(BaseModel):
    """One input segment (a blob of one mask value in one view) and the object it belongs to."""

    segment: int = Field(description="index of the segment in this result")
    view: str = Field(description="name of the view the segment was cut from")
    instance: int = Field(description="the mask value of the segment in its view")
    component: int = Field(description="blob index within (view, instance), largest blob first")
    num_points: int = Field(description="back-projected 3D points with valid depth")
    object: int = Field(description="object label; segments with the same label are the same physical object")
    support: float = Field(description="how sure the label is (0-1): for 'shadowcorr' and 'meanshift' the share of "
                           "the segment's voxel votes that went to its object; for 'projection' and 'fused' the "
                           "calibrated confidence of the evidence (see shadowcorr.grouping)")
    assignment: Assignment = Field(
        "vote",
        description="how the label was found: 'vote' (majority of its kept voxels); 'unfiltered_voxels' "
        "(no voxel survived the consensus filter: nearest kept voxels of its own shadow voted); "
        "'nearest_object' (no shadow at all: nearest kept voxel to its centroid); "
        "'own_object' (no valid 3D point, or its shadow is near no kept voxel: an object of its own); "
        "'evidence' (methods 'projection' and 'fused': grouped by the evidence between segments)",
    )


class ObjectSummary(BaseModel):
    """One physical object found in the scene. Lengths in the bundle's units."""

    object: int
    segments: list[int]
    views: list[str]
    centroid: list[float] | None = Field(description="mean of the object's voxel centres (or segment points)")
    bbox_min: list[float] | None
    bbox_max: list[float] | None
    num_voxels: int


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
    config: dict[str, object] | None = Field(
        None, description="the ShadowCorrConfig the result was computed with (how segments were cut, clustering, ...)"
    )
    shadowcorr_version: str = __version__

    @property
    def labels(self) -> list[int]:
        """Object label of each segment, in segment order."""
        return [s.object for s in self.segments]
