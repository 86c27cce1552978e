"""The site map's JSON: one update (``MapUpdate``), the whole map (``MapState``), and their parts."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

from ..result import ViewPoseCorrection

__all__ = ["EventKind", "MapEvent", "MapObject", "MapScan", "MapSegment", "MapState", "MapUpdate", "MapViewRef"]

EventKind = Literal["created", "observed", "merged", "split", "retired"]


class MapSegment(BaseModel):
    """One segment of one scan and the object it belongs to now."""

    segment: int = Field(description="the segment's id in the map (never reused)")
    scan: int = Field(description="the scan (update) that added it")
    view: str = Field(description="its view's name within that scan")
    instance: int = Field(description="its mask value in that view")
    component: int = Field(description="blob index within (view, instance), largest first; for method 'fused' "
                           "a blob that a depth step parts counts as its pieces (stage 02 depth cut)")
    num_points: int = Field(description="points the map keeps of it (averaged on the downsampling grid)")
    object: int = Field(description="its object's id; segments with one id are one physical object")
    support: float | None = Field(None, description="the calibrated support of its place when it was last placed "
                                  "(see the fused method's support)")
    margin: float | None = Field(None, description="the evidence margin of its place when it was last placed: its "
                                 "group's linkage over the best alternative")


class MapEvent(BaseModel):
    """One revision of the map's objects, with what caused it."""

    event: int = Field(description="position in the map's history (1, 2, ...)")
    kind: EventKind = Field(description="'created': a new object; 'observed': new segments joined an object; "
                            "'merged': `object` and `into` were one rock, `object` is retired and every segment of it "
                            "now has `into`; 'split': some segments of `object` (`moved`) now belong to `into`; "
                            "'retired': `object` has no segment left")
    object: int
    into: int | None = Field(None, description="merged: the surviving object; split: the object the moved segments joined")
    scan: int = Field(description="the scan whose evidence caused it")
    views: list[str] = Field(description="views of that scan whose segments are the evidence")
    segments: list[int] = Field(description="that scan's segments that are the evidence (map segment ids)")
    moved: list[int] = Field(default_factory=list, description="segments of earlier scans whose object changed")
    margin: float | None = Field(None, description="the weakest evidence margin among `segments` and `moved` (their "
                                 "group's linkage over the best alternative; above 0: the evidence chose it)")


class MapViewRef(BaseModel):
    scan: int
    view: str


class MapScan(BaseModel):
    scan: int
    name: str
    added_at: float = Field(description="seconds since the epoch")
    views: list[str]
    num_segments: int
    model: str | None = Field(None, description="sha256 of the network's model file")


class MapObject(BaseModel):
    """One object of the map (retired ones are not listed; their events say where they went)."""

    object: int
    created_scan: int
    scans: list[int]
    views: list[MapViewRef]
    num_segments: int
    centroid: list[float] | None = Field(description="mean of its segments' points (map units)")
    bbox_min: list[float] | None
    bbox_max: list[float] | None


class MapUpdate(BaseModel):
    """What one ``SiteMap.add`` did: the scan's segments with their objects, and the events."""

    scan: int
    name: str
    units: str = Field(description="length units of the map")
    segments: list[MapSegment] = Field(description="every segment of this scan")
    events: list[MapEvent]
    linked_views: list[MapViewRef] = Field(description="the stored views the scan was linked to (same ground)")
    revisited_views: list[MapViewRef] = Field(default_factory=list, description="stored views the scan repeats (the "
                                              "same camera): its segments covering a stored segment's pixels take that "
                                              "segment's id")
    poses: list[ViewPoseCorrection] | None = Field(None, description="pose refinement of this scan's views, relative "
                                                   "to the map's views")
    timings_ms: dict[str, float]
    warnings: list[str] = Field(default_factory=list)


class MapState(BaseModel):
    """The whole map: scans, current objects, every segment with its current object, the history."""

    units: str
    scans: list[MapScan]
    objects: list[MapObject]
    segments: list[MapSegment]
    events: list[MapEvent]
