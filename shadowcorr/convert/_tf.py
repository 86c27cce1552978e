"""The tf tree of a ROS bag: poses of frames in a fixed frame at an image's stamp (REP 105 frames).

Static transforms hold at every time; dynamic ones are interpolated (linear translation,
slerp rotation) between the two samples around the stamp and never extrapolated beyond
the sync tolerance.  Stamps are integer nanoseconds.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import Problem
from ..poses import quaternion_to_matrix, slerp


def stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def fmt_stamp(ns: int) -> str:
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d} s"


@dataclass
class _Track:
    """All transforms recorded from ``parent`` to one child frame, sorted by stamp."""

    parent: str
    static: bool
    stamps: list[int] = field(default_factory=list)
    translations: list[np.ndarray] = field(default_factory=list)
    rotations: list[np.ndarray] = field(default_factory=list)  # quaternions (x, y, z, w)


class TransformTree:
    """The tf tree of a bag: ``lookup(fixed, frame, stamp)`` = pose of ``frame`` in ``fixed``.

    Each child frame has one parent (tf's rule).  Static transforms hold at every
    time; dynamic ones are interpolated between the two samples around the stamp and
    may be extrapolated by at most ``tolerance_ns`` (then the nearest sample is used).
    """

    def __init__(self, tolerance_ns: int = 0) -> None:
        self.tracks: dict[str, _Track] = {}
        self.tolerance_ns = tolerance_ns
        self.problems: list[Problem] = []

    def add(self, msg: Any, static: bool, topic: str) -> None:
        for tr in msg.transforms:
            parent, child = tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/")
            track = self.tracks.setdefault(child, _Track(parent, static))
            if track.parent != parent:
                self.problems.append(Problem(
                    loc=f"topics[{topic}]",
                    msg=f"frame {child!r} has two parents, {track.parent!r} and {parent!r} (at {fmt_stamp(stamp_ns(tr.header))})"))
                continue
            t, r = tr.transform.translation, tr.transform.rotation
            stamp = stamp_ns(tr.header)
            i = bisect.bisect_right(track.stamps, stamp)
            track.stamps.insert(i, stamp)
            track.translations.insert(i, np.array([t.x, t.y, t.z], dtype=np.float64))
            track.rotations.insert(i, np.array([r.x, r.y, r.z, r.w], dtype=np.float64))
            track.static = track.static and static

    def _chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root."""
        chain = [frame]
        while chain[-1] in self.tracks and len(chain) <= len(self.tracks):
            chain.append(self.tracks[chain[-1]].parent)
        return chain

    def _edge(self, child: str, stamp: int) -> np.ndarray:
        """4x4 pose of ``child`` in its parent at ``stamp``; ``LookupError`` when out of range."""
        tr = self.tracks[child]
        if tr.static:
            k = len(tr.stamps) - 1  # a re-published static transform: the latest one holds
            return _rigid(tr.rotations[k], tr.translations[k])
        i = bisect.bisect_left(tr.stamps, stamp)
        if i < len(tr.stamps) and tr.stamps[i] == stamp:
            return _rigid(tr.rotations[i], tr.translations[i])
        if 0 < i < len(tr.stamps):
            t0, t1 = tr.stamps[i - 1], tr.stamps[i]
            w = (stamp - t0) / (t1 - t0)
            return _rigid(slerp(tr.rotations[i - 1], tr.rotations[i], w),
                          (1 - w) * tr.translations[i - 1] + w * tr.translations[i])
        nearest = 0 if i == 0 else len(tr.stamps) - 1
        if abs(tr.stamps[nearest] - stamp) <= self.tolerance_ns:
            return _rigid(tr.rotations[nearest], tr.translations[nearest])
        raise LookupError(
            f"transform {tr.parent!r} -> {child!r} is known from {fmt_stamp(tr.stamps[0])} to "
            f"{fmt_stamp(tr.stamps[-1])}, not at {fmt_stamp(stamp)} (no extrapolation beyond the sync tolerance)")

    def lookup(self, fixed: str, frame: str, stamp: int) -> np.ndarray:
        """Pose (4x4, ``frame`` -> ``fixed``) at ``stamp``; ``LookupError`` naming the frames otherwise."""
        fixed, frame = fixed.lstrip("/"), frame.lstrip("/")
        up_frame, up_fixed = self._chain(frame), self._chain(fixed)
        common = next((f for f in up_frame if f in up_fixed), None)
        if common is None:
            known = ", ".join(sorted(set(self.tracks) | {t.parent for t in self.tracks.values()})) or "none"
            raise LookupError(f"no transform from {fixed!r} to {frame!r} at {fmt_stamp(stamp)}: "
                              f"the frames are not connected in /tf and /tf_static (frames known: {known})")
        root_frame, root_fixed = np.eye(4), np.eye(4)
        for child in up_frame[: up_frame.index(common)]:
            root_frame = self._edge(child, stamp) @ root_frame
        for child in up_fixed[: up_fixed.index(common)]:
            root_fixed = self._edge(child, stamp) @ root_fixed
        return np.linalg.inv(root_fixed) @ root_frame


def _rigid(quaternion: np.ndarray, translation: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quaternion_to_matrix(quaternion)
    m[:3, 3] = translation
    return m
