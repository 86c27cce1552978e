"""Groups of one linking run -> the map's object ids, revised only where the scan's new evidence says so.

A run groups the new scan's segments together with the stored segments of the map's views
that see the same ground.  Its groups are read against the objects those stored segments
already belong to:

1. **Homes.**  Each object present in the run gets at most one group, and each group at most
   one object: the assignment that keeps the most stored segments where they are (Hungarian
   method on the counts of each object's stored segments in each group).  An object keeps
   its id; the group it is assigned to is its home.
2. **New segments.**  The new segments of a group take the group's owner (``observed``); a
   group with new segments and no owner becomes a new object (``created``) - unless it holds
   stored segments none of which may move (below), in which case its new segments join the
   object most of those belong to.
3. **Revisions.**  A stored segment in a group that carries new evidence - it holds new segments,
   or stored segments that the scan's views see - whose owner is another object moves there
   (where ``min_margin`` is set: only when its evidence margin in the run exceeds it); a group of
   such stored segments without an owner becomes a new object.  When every stored
   segment of an object that lost its home moves to one object, the two were one rock:
   ``merged`` (the owner survives, the other id is retired and all its segments, in views
   the run did not load too, take the survivor's id).  Otherwise each move is a ``split`` of
   the object into the one it joins, and an object left without segments is ``retired``.

A new view that sees a stored segment's surface adds evidence about it (its landings, its depth
carving the shadows, its shadows in the voxels) even where none of its own segments joins that
segment's group; with the whole neighbourhood in the run, the map then takes the run's partition
as one run of all those views would give it, whatever the order the scans came in.  Stored
segments that no view of the scan sees never change: what the run re-read of evidence already
in the map is not new evidence.  The margin is no reason to stay by default: a segment the run's
per-view constraints put in a group other than the one its linkage prefers (a negative margin,
e.g. a merged mask over two rocks) is put there by one run of all the views too, and a map that
kept it where it was disagreed with that run (on the real scene under the ``field`` errors, one
such segment in 5 of 12 orders and draws).  Nor is a revisit: a new segment that repeats a
stored one (the same camera, the same pixels; see ``_linking.revisits``) takes that segment's
id and counts, for the homes, as a stored segment of it; only the scan's other segments are
new evidence.  Nothing here reads ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment


@dataclass
class Revision:
    """One event of an update, on run segment indices (the store maps them to segment ids)."""

    kind: str  # created | observed | merged | split | retired
    object: int
    into: int | None = None
    segments: list[int] = field(default_factory=list)  # new segments that carry the evidence
    moved: list[int] = field(default_factory=list)  # stored segments whose object changes
    margin: float | None = None  # the weakest evidence margin among segments and moved


@dataclass
class RevisionPlan:
    """The object of every run segment after the update, and the events that say why."""

    segment_object: np.ndarray  # (N,) object id of every run segment (new ids from ``first_new_object``)
    events: list[Revision]
    merged_into: dict[int, int]  # retired object -> survivor: every segment of it, stored anywhere, moves
    created: list[int]  # the new object ids
    retired: list[int]  # objects that lost their last segment (merged ones included)


def revise(group: np.ndarray, is_new: np.ndarray, stored_object: np.ndarray, margin: np.ndarray,
           segments_in_map: dict[int, int], first_new_object: int, min_margin: float | None = None,
           repeats: np.ndarray | None = None, seen: np.ndarray | None = None) -> RevisionPlan:
    """Object ids for the segments of one run (see the module docstring).

    ``group``: the run's group of each segment; ``is_new``: the segment belongs to the scan being
    added; ``stored_object``: the current object of each stored segment (ignored for new ones);
    ``margin``: each segment's evidence margin in the run (its group's linkage over the best
    alternative; a stored segment moves only when it exceeds ``min_margin``, where that is not
    None); ``segments_in_map``: how many segments each object present in the run has in
    the whole map (to tell when one is left empty); ``first_new_object``: the id a created
    object gets first; ``repeats``: for each new segment that repeats a stored one, that one's
    object (-1 elsewhere); ``seen``: the stored segments a view of the scan sees (None: none).
    """
    group = np.asarray(group, dtype=np.int64)
    repeated = np.full(group.size, -1, dtype=np.int64) if repeats is None else np.asarray(repeats, dtype=np.int64)
    is_new = np.asarray(is_new, dtype=bool)
    fixed = is_new & (repeated >= 0)  # new, but no new evidence: the id it repeats
    stored_object = np.where(is_new, repeated, np.asarray(stored_object, dtype=np.int64))
    margin = np.asarray(margin, dtype=np.float64)
    n = group.size
    # Groups in order of their first segment, so that ids and events do not depend on label values.
    _, first_index, group_of = np.unique(group, return_index=True, return_inverse=True)
    order = np.argsort(first_index, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    group_of = rank[group_of]
    num_groups = order.size

    held = np.flatnonzero(~is_new | fixed)  # segments holding an object already: they decide the homes
    objects, object_of = np.unique(stored_object[held], return_inverse=True)
    counts = np.zeros((num_groups, objects.size))
    np.add.at(counts, (group_of[held], object_of), 1.0)
    owner = np.full(num_groups, -1, dtype=np.int64)
    home = np.full(objects.size, -1, dtype=np.int64)
    if objects.size:
        rows, cols = linear_sum_assignment(counts, maximize=True)
        kept = counts[rows, cols] > 0
        owner[rows[kept]] = objects[cols[kept]]
        home[cols[kept]] = rows[kept]

    evidence = is_new & ~fixed
    # Groups that carry new evidence: new segments, or stored segments a view of the scan sees.
    has_new = np.bincount(group_of[evidence], minlength=num_groups) > 0
    if seen is not None:
        has_new |= np.bincount(group_of[np.asarray(seen, dtype=bool) & ~is_new], minlength=num_groups) > 0
    movable = ~is_new if min_margin is None else ~is_new & (margin > min_margin)
    target = owner.copy()
    next_object = first_new_object
    created: list[int] = []
    for g in np.flatnonzero(has_new & (owner < 0)).tolist():
        members = np.flatnonzero(group_of == g)
        old = members[~evidence[members]]
        if old.size and not movable[old].any():
            values, votes = np.unique(stored_object[old], return_counts=True)
            target[g] = values[np.argmax(votes)]  # ties: the smaller (older) id
        else:
            target[g] = next_object
            created.append(next_object)
            next_object += 1

    out = stored_object.copy()
    out[evidence] = target[group_of[evidence]]
    moves = np.flatnonzero(movable & has_new[group_of] & (target[group_of] != stored_object))
    out[moves] = target[group_of[moves]]

    def weakest(idx) -> float | None:
        return float(margin[np.asarray(idx, dtype=np.int64)].min()) if len(idx) else None

    def causing(groups: np.ndarray) -> list[int]:
        return np.flatnonzero(evidence & np.isin(group_of, groups)).tolist()

    revisions: list[Revision] = []
    merged_into: dict[int, int] = {}
    retired: list[int] = []
    stored = held[~is_new[held]]
    stored_of = object_of[~is_new[held]]
    for k, obj in enumerate(objects.tolist()):
        mine = stored[stored_of == k]
        gone = mine[out[mine] != obj]
        if gone.size == 0:
            continue
        destinations = np.unique(out[gone])
        if home[k] < 0 and gone.size == mine.size and destinations.size == 1:
            into = int(destinations[0])
            cause = causing(np.unique(group_of[gone]))
            merged_into[obj] = into
            retired.append(obj)
            revisions.append(Revision("merged", obj, into, cause, gone.tolist(), weakest(np.r_[cause, gone])))
            continue
        for into in destinations.tolist():
            moved = gone[out[gone] == into]
            cause = causing(np.unique(group_of[moved]))
            revisions.append(Revision("split", obj, into, cause, moved.tolist(), weakest(np.r_[cause, moved])))
        if segments_in_map.get(obj, mine.size) - gone.size + int(np.sum(fixed & (out == obj))) <= 0:
            retired.append(obj)
            revisions.append(Revision("retired", obj, segments=[], moved=gone.tolist(), margin=weakest(gone)))
    for obj, into in merged_into.items():  # repeats of a merged object's segments follow them
        out[fixed & (out == obj)] = into

    events: list[Revision] = []
    created_set = set(created)
    for obj in dict.fromkeys(out[is_new].tolist()):  # first-seen order
        new_segments = np.flatnonzero(is_new & (out == obj)).tolist()
        kind = "created" if obj in created_set else "observed"
        events.append(Revision(kind, obj, segments=new_segments, margin=weakest(new_segments)))
        created_set.discard(obj)
    for obj in created:  # objects split off stored segments alone (the split events name them)
        if obj in created_set:
            members = np.flatnonzero(~is_new & (out == obj))
            events.append(Revision("created", obj, moved=members.tolist(), margin=weakest(members)))
    events += revisions
    assert out.size == n
    return RevisionPlan(out, events, merged_into, created, retired)
