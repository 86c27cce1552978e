"""A site map that grows scan by scan: stable object ids, an event history, one SQLite file.

:class:`SiteMap` links each new scan to the stored views that see the same ground with the
``fused`` method's evidence, gives the scan's segments the ids of the objects they join, and
revises the map's objects only where the new evidence says so - each revision an event
(:class:`MapEvent`).  :func:`add_to_map` is the one-call form.  See ``docs/guide/site-map.md``.
"""

from ._map import ScanPlan, SiteMap, add_to_map
from ._models import MapEvent, MapObject, MapScan, MapSegment, MapState, MapUpdate, MapViewRef
from ._store import MapBusyError, MapConflictError, MapFileError

__all__ = [
    "MapBusyError",
    "MapConflictError",
    "MapEvent",
    "MapFileError",
    "MapObject",
    "MapScan",
    "MapSegment",
    "MapState",
    "MapUpdate",
    "MapViewRef",
    "ScanPlan",
    "SiteMap",
    "add_to_map",
]
