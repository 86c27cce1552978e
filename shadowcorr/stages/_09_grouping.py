"""Stage 9 (methods ``fused``, ``projection``): evidence between segments -> groups of segments, one group per physical object.

Two ways to resolve the evidence, one per method:

* :func:`link_components` (method ``projection``, training-free): segment ``a`` is linked to
  segment ``b`` of another view when at least ``max(projection_min_points,
  projection_min_share * samples(a))`` of ``a``'s points are visible in ``b``'s view and at
  least ``projection_link_share`` of those land on ``b`` (either direction); the connected
  components of the links are the objects.  One wrong link joins two objects.

* :func:`agglomerate` (method ``fused``): greedy average-linkage clustering on *signed*
  evidence, which does not chain through one bad link.  Every segment starts as its own
  group; the two groups with the highest linkage merge, as long as it is above
  ``fusion_threshold``.  The linkage of groups X and Y adds up

  - surface evidence, mostly the stronger of the two directions (the weaker weighs
    ``fusion_surface_symmetry``): of all points of X that are visible in Y's views and land on
    some segment there, the share ``f`` that lands on Y, read against
    ``fusion_neutral_share`` (two parts of one object land on each other in any proportion,
    two different objects hardly at all) and shrunk by ``n / (n + fusion_surface_prior)`` with
    ``n`` the number of such points (likewise from Y to X) - the smaller of two pieces of one
    surface lands inside the larger one, while the larger only partly covers the smaller;
  - volumetric evidence: the similarity of the network's embeddings of segments whose
    shadows share voxels, pooled as ``sum(value * mass) / (sum(mass) +
    fusion_volume_prior)``, times ``fusion_volume_weight``;
  - constraints of the views: of the views that see both X and Y, the share in which they
    wear different mask ids, times ``fusion_cannot_link``, is subtracted (a segmenter rarely
    cuts one rock in two; it grows by ``fusion_cannot_link_apart`` of itself for every further view
    in which a seam between them shows two surfaces, up to ``fusion_cannot_link_apart_max``: two
    rocks that touch wear two masks along a depth step in every view that sees them meet, while a
    cut through one rock leaves a smooth seam), and the share in which they wear one mask id (blobs of one mask),
    times ``fusion_same_mask``, is added - constraints, not rules: strong evidence from the
    other views can still join a split mask, and a tiny blob nothing else sees joins the
    other blobs of its mask.  The mask ids the constraints read come from
    :func:`split_mask_ids`: two masks of one view whose segments land together on one
    segment in several other views, or that meet on one smooth surface in their own view
    (stage 03 seams), count as one (split) mask; where two masks meet along a seam too short
    or too noisy to decide (an *unsure* seam), their view counts as neither between a group
    that lies in that view alone and a group that other views see too.

Before grouping, segments that look like one mask drawn over two objects are found
(:func:`merged_mask_segments`: the segment spreads over two segments of another view that
both land back on it and that a third view sees apart), and landings *on* them are taken
out of the evidence (:func:`without_landings_on`): everything under a merged mask lands on
it, so those landings would chain its two objects together.  Its own landings stay.  A small
object under a mask that is mostly over its neighbour takes too little of the mask's landings
to make it a merged mask; its own landings on the mask are taken out (:func:`thin_cover_pairs`,
:func:`without_landings`), and the mask stays with the object it is mostly over.  After
the agglomeration each merged mask joins the group that owns most of its surface, read from
the nearest surface points of the other views (:func:`join_nearest_surface`).  Last, a
segment with no evidence at all that stands alone - a rock's sliver, whose few points land on
nothing and whose shadow meets no other - joins the group of the nearest surface another view
saw, where it lies within reach and that group holds no segment of its view
(:func:`join_isolated`).

Each segment's ``confidence`` compares how strongly it is linked to its own group with the
strongest alternative (another group, or standing alone); see :func:`segment_confidence`.

Nothing here reads ground truth: mask ids are compared only within their own view.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, replace

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..config import ShadowCorrConfig
from ._03_surface_evidence import SurfaceEvidence
from ._06_voxel_scene import VoxelScene
from ._08_volume_evidence import volume_pairs


@dataclass
class SegmentGraph:
    """All evidence between segments (plain arrays; input of :func:`agglomerate`)."""

    view: np.ndarray  # (S,) view of each segment
    instance: np.ndarray  # (S,) mask id of each segment (meaningful within its view only)
    surface: SurfaceEvidence
    # Volumetric evidence, one row per unordered pair (a < b): value in [-1, 1] and its mass.
    volume_a: np.ndarray
    volume_b: np.ndarray
    volume_value: np.ndarray
    volume_mass: np.ndarray
    # (S,) mask ids with the unsure neighbours of a view (stage 03 seams) made one id as well.  Where
    # the ids of a group that lies in one view and a group that spans several differ in that view
    # but these agree, the view neither joins nor parts them: the small piece a split cut off, with
    # a seam too short to read, then joins the rest of its rock on what the other views show
    # instead of staying alone.  Between two groups of one view each (nothing else speaks for
    # either) or of several views each (two whole rocks touching at one depth, which under noisy
    # depth all their seams leave unsure), the ids differ as before.  Where the ids agree, the view
    # joins the groups whatever these say (the pairs join segments, so one blob of a mask can take
    # another loose id than its mask's other blobs).  None: the same as ``instance``.
    loose: np.ndarray | None = None

    @property
    def loose_instance(self) -> np.ndarray:
        return self.instance if self.loose is None else self.loose

    @property
    def num_segments(self) -> int:
        return int(self.view.shape[0])


def link_components(surface: SurfaceEvidence, segment_view: np.ndarray, config: ShadowCorrConfig) -> np.ndarray:
    """Objects of the training-free ``projection`` method: connected components of the links."""
    s = surface.num_segments
    a, b, hits = surface.hit_source, surface.hit_target, surface.hit_count
    seen = surface.visible[a, segment_view[b]]
    enough = np.maximum(config.projection_min_points, config.projection_min_share * surface.samples[a])
    link = (seen >= enough) & (hits >= config.projection_link_share * seen)
    graph = coo_matrix((np.ones(int(link.sum())), (a[link], b[link])), shape=(s, s))
    _, labels = connected_components(graph, directed=True, connection="weak")
    return labels.astype(np.int64)


def linkage(hits_xy, trials_xy, hits_yx, trials_yx, volume, mass, agree, differ, config: ShadowCorrConfig):
    """The linkage of groups X and Y from their pooled counts (scalars or arrays; see the module docstring).

    ``hits_xy``: points of X landing on Y; ``trials_xy``: points of X visible in Y's views and
    landing on some segment there (likewise from Y to X); ``volume`` and ``mass``: summed
    volumetric value * mass and mass; ``agree`` / ``differ``: the share of the views seeing
    both X and Y in which they wear one mask id / different mask ids.
    """
    forward, backward = _directed_surface(hits_xy, trials_xy, config), _directed_surface(hits_yx, trials_yx, config)
    if isinstance(forward, np.ndarray):
        stronger, weaker = np.maximum(forward, backward), np.minimum(forward, backward)
    else:
        stronger, weaker = max(forward, backward), min(forward, backward)
    # Plain arithmetic, so that one formula serves the scalar loop and the vectorised confidence.
    surface = stronger + config.fusion_surface_symmetry * (weaker - stronger)
    volumetric = config.fusion_volume_weight * volume / (mass + config.fusion_volume_prior)
    constraints = config.fusion_same_mask * agree - config.fusion_cannot_link * differ
    return surface + volumetric + constraints


def _directed_surface(hits, trials, config: ShadowCorrConfig):
    """Surface evidence of one direction, in [-1, 1].

    The share ``f`` of landings on the other group is read against ``fusion_neutral_share``:
    two parts of one object land on each other in any proportion, two different objects
    hardly at all, so ``f`` rises from -1 at 0 through 0 at the neutral share to +1 at 1
    (piecewise linear).  It is shrunk towards 0 when few points were seen - exactly 0 when
    none was (the shrink factor is 0 there).
    """
    f0 = config.fusion_neutral_share
    share = hits / (trials + 1e-12)
    # The two lines meet at f0; below it the steeper one is the smaller.  Python's min on the
    # agglomeration's scalars: numpy's ufuncs cost microseconds per call there.
    lines = share / f0 - 1.0, (share - f0) / (1.0 - f0)
    value = np.minimum(*lines) if isinstance(share, np.ndarray) else min(lines)
    return value * trials / (trials + config.fusion_surface_prior)


class _Groups:
    """Mutable state of the agglomeration: per group its size, views, mask ids, trials and edges."""

    def __init__(self, graph: SegmentGraph, config: ShadowCorrConfig):
        s = graph.num_segments
        self.config = config
        self.size = np.ones(s, dtype=np.int64)
        # trials[g][j]: points of group g visible in view j and landing on some segment there
        self.trials: list[list[float]] = graph.surface.on_mask.astype(np.float64).tolist()
        self.views = [{int(v): 1} for v in graph.view]
        self.view_ids = [{int(v): {int(i)}} for v, i in zip(graph.view, graph.instance)]  # view -> mask ids
        self.view_loose = [{int(v): {int(i)}} for v, i in zip(graph.view, graph.loose_instance)]  # view -> loose ids
        self.version = np.zeros(s, dtype=np.int64)
        self.parent = np.arange(s)
        # edges[g][h] = [hits g->h, hits h->g, sum of volume value * mass, sum of volume mass]
        self.edges: list[dict[int, list[float]]] = [{} for _ in range(s)]
        surf = graph.surface
        for a, b, h in zip(surf.hit_source.tolist(), surf.hit_target.tolist(), surf.hit_count.tolist()):
            self._edge(a, b)[0] += h
            self._edge(b, a)[1] += h
        for a, b, value, mass in zip(graph.volume_a.tolist(), graph.volume_b.tolist(),
                                     graph.volume_value.tolist(), graph.volume_mass.tolist()):
            for g, h in ((a, b), (b, a)):
                e = self._edge(g, h)
                e[2] += value * mass
                e[3] += mass
        for a, b in zip(*(x.tolist() for x in _same_mask_pairs(graph))):
            self._edge(a, b)
            self._edge(b, a)
        # apart[g][h]: the views in which a seam between g and h shows two surfaces (one set for both sides)
        self.apart: list[dict[int, set[int]]] = [{} for _ in range(s)]
        seams = graph.surface.seams
        for a, b in zip(seams.apart_first.tolist(), seams.apart_second.tolist()):
            views = self.apart[a].setdefault(b, set())
            views.add(int(graph.view[a]))
            self.apart[b][a] = views

    def _edge(self, g: int, h: int) -> list[float]:
        e = self.edges[g].get(h)
        if e is None:
            e = self.edges[g][h] = [0.0, 0.0, 0.0, 0.0]
        return e

    def constraints(self, g: int, h: int) -> tuple[float, float]:
        """Shares of the views seeing both g and h in which they wear one mask id / different ones (the
        latter grown for the views that part them along a seam of two surfaces, see the module docstring)."""
        ids_g, ids_h = self.view_ids[g], self.view_ids[h]
        shared = [v for v in ids_g if v in ids_h] if len(ids_g) <= len(ids_h) else [v for v in ids_h if v in ids_g]
        if not shared:
            return 0.0, 0.0
        # Unsure neighbours count as neither only between a group of one view and a group of several
        # (see SegmentGraph.loose); otherwise as different mask ids.
        one_view_g, one_view_h = len(self.views[g]) == 1, len(self.views[h]) == 1
        loose_g, loose_h = (self.view_loose[g], self.view_loose[h]) if one_view_g != one_view_h else (ids_g, ids_h)
        # A view parts g and h where their ids differ and their loose ids do too (the rest: unsure,
        # neither).  Both: a pair joins segments, so an unsure seam of one blob of a mask gives that
        # blob alone another loose id, and the blobs of a mask must not differ where their ids agree.
        agree = differ = stepped = 0
        apart = self.apart[g].get(h, ())
        for v in shared:
            if len(ids_g[v] | ids_h[v]) == 1:
                agree += 1
            elif len(loose_g[v] | loose_h[v]) > 1:
                differ += 1
                stepped += v in apart
        # A lone segment shares one view at most with a group, so the vectorised linkage (one view) needs no growth.
        config = self.config
        growth = min(config.fusion_cannot_link_apart * max(stepped - 1, 0), config.fusion_cannot_link_apart_max)
        return agree / len(shared), (1.0 + growth) * differ / len(shared)

    def linkage(self, g: int, h: int) -> float:
        hits_gh, hits_hg, volume, mass = self.edges[g][h]
        trials_g, trials_h = self.trials[g], self.trials[h]
        trials_gh = sum(trials_g[v] for v in self.views[h])
        trials_hg = sum(trials_h[v] for v in self.views[g])
        agree, differ = self.constraints(g, h)
        return float(linkage(hits_gh, trials_gh, hits_hg, trials_hg, volume, mass, agree, differ, self.config))

    def merge(self, g: int, h: int) -> int:
        """Fold the smaller group into the larger; returns the surviving group."""
        if self.size[g] < self.size[h]:
            g, h = h, g
        self.parent[h] = g
        self.size[g] += self.size[h]
        self.trials[g] = [a + b for a, b in zip(self.trials[g], self.trials[h])]
        for v, n in self.views[h].items():
            self.views[g][v] = self.views[g].get(v, 0) + n
        for v, ids in self.view_ids[h].items():
            self.view_ids[g].setdefault(v, set()).update(ids)
        for v, ids in self.view_loose[h].items():
            self.view_loose[g].setdefault(v, set()).update(ids)
        for other, (ho, oh, volume, mass) in self.edges[h].items():
            del self.edges[other][h]
            if other == g:
                continue
            e = self._edge(g, other)
            e[0] += ho
            e[1] += oh
            e[2] += volume
            e[3] += mass
            r = self._edge(other, g)
            r[0] += oh
            r[1] += ho
            r[2] += volume
            r[3] += mass
        for other, views in self.apart[h].items():
            del self.apart[other][h]
            if other == g:
                continue
            kept = self.apart[g].get(other)
            if kept is None:
                self.apart[g][other] = self.apart[other][g] = views
            else:
                kept.update(views)
        self.apart[h] = {}
        self.edges[h] = {}
        self.version[g] += 1
        self.version[h] = -1
        return g

    def labels(self) -> np.ndarray:
        root = self.parent.copy()
        while True:
            nxt = root[root]
            if np.array_equal(nxt, root):
                return root
            root = nxt


def agglomerate(graph: SegmentGraph, config: ShadowCorrConfig) -> np.ndarray:
    """Group label of every segment by signed average linkage (see the module docstring)."""
    groups = _Groups(graph, config)
    heap = _initial_heap(graph, config)
    heapq.heapify(heap)
    while heap:
        neg, g, h, vg, vh = heapq.heappop(heap)
        if -neg <= config.fusion_threshold:
            break
        if groups.version[g] != vg or groups.version[h] != vh:
            continue  # one of them has changed since this entry was pushed
        kept = groups.merge(g, h)
        for other in groups.edges[kept]:
            heapq.heappush(heap, (-groups.linkage(kept, other), kept, other, groups.version[kept], groups.version[other]))
    return groups.labels()


def _same_mask_pairs(graph: SegmentGraph) -> tuple[np.ndarray, np.ndarray]:
    """Blobs of one mask id in one view, as a chain of pairs (each blob with the next one):
    candidates for joining even without other evidence (the same-mask constraint)."""
    key = graph.view.astype(np.int64) * (int(graph.instance.max(initial=0)) + 1) + graph.instance
    order = np.argsort(key, kind="stable")
    same = np.flatnonzero(key[order][1:] == key[order][:-1])
    return order[same], order[same + 1]


def _initial_heap(graph: SegmentGraph, config: ShadowCorrConfig) -> list[tuple]:
    """Heap entries of every linked pair of single segments, their linkages computed in one
    vectorised call (:func:`_segment_group_linkage` with every segment its own group): the
    values :meth:`_Groups.linkage` gives, bit for bit (every pooled count is a single term
    there), at a fraction of the time of one Python call per pair."""
    if graph.num_segments == 0:
        return []
    pairs = _segment_group_linkage(graph, np.arange(graph.num_segments), config)
    first = pairs.segment < pairs.group  # each unordered pair once (the linkage is symmetric)
    return [(-value, a, b, 0, 0) for value, a, b in
            zip(pairs.value[first].tolist(), pairs.segment[first].tolist(), pairs.group[first].tolist())]


@dataclass
class _PairLinkage:
    """The linkage of a segment alone to a group, per (segment, group) pair with evidence."""

    segment: np.ndarray  # (P,) the segment
    group: np.ndarray  # (P,) the group
    own: np.ndarray  # (P,) bool: the group is the segment's own (then the rest of it, without the segment)
    value: np.ndarray  # (P,) the linkage (0 where the group holds nothing but the segment)
    hits_out: np.ndarray  # (P,) the segment's points landing on the group
    trials_out: np.ndarray  # (P,) its points visible in the group's views and landing on some segment there
    volume: np.ndarray  # (P,) summed volumetric value * mass between the segment and the group
    mass: np.ndarray  # (P,) summed volumetric mass
    per_view: np.ndarray  # (K, V) members of each group per view


def _segment_group_linkage(graph: SegmentGraph, group: np.ndarray, config: ShadowCorrConfig) -> _PairLinkage:
    """The linkage, as between groups (:func:`linkage`), of every segment alone to its own group
    (the rest of it) and to every group it has evidence with (landings, shared volume, or a blob
    of its mask), for groups numbered ``0..K-1`` in ``group``.  The vectorised counterpart of
    :meth:`_Groups.linkage`, pooling the same counts: the first linkages of the agglomeration
    (every segment its own group) and the confidence of its result both come from here."""
    s = graph.num_segments
    k, num_views = int(group.max()) + 1, graph.surface.on_mask.shape[1]
    surf = graph.surface
    mask_a, mask_b = _same_mask_pairs(graph)
    src = np.concatenate([surf.hit_source, surf.hit_target, graph.volume_a, graph.volume_b, mask_a, mask_b,
                          np.arange(s)])
    dst = np.concatenate([surf.hit_target, surf.hit_source, graph.volume_b, graph.volume_a, mask_b, mask_a,
                          np.arange(s)])
    keys = np.unique(src * k + group[dst])
    seg, grp = keys // k, keys % k
    own = grp == group[seg]

    def gather(a: np.ndarray, g: np.ndarray, values: np.ndarray) -> np.ndarray:
        return np.bincount(np.searchsorted(keys, a * k + g), weights=values, minlength=keys.size)

    ha, hb = surf.hit_source, surf.hit_target
    hits_out = gather(ha, group[hb], surf.hit_count)  # from the segment into the group
    hits_in = gather(hb, group[ha], surf.hit_count)  # from the group onto the segment
    vm = graph.volume_value * graph.volume_mass
    volume = gather(graph.volume_a, group[graph.volume_b], vm) + gather(graph.volume_b, group[graph.volume_a], vm)
    mass = (gather(graph.volume_a, group[graph.volume_b], graph.volume_mass)
            + gather(graph.volume_b, group[graph.volume_a], graph.volume_mass))

    # Members of each group per view (the segment itself left out of its own group).
    per_view = np.bincount(group * num_views + graph.view, minlength=k * num_views).reshape(k, num_views)
    present = per_view[grp] - own[:, None] * (np.arange(num_views)[None, :] == graph.view[seg][:, None])
    on_mask = surf.on_mask.astype(np.float64)
    members = coo_matrix((np.ones(s), (group, np.arange(s))), shape=(k, s)).tocsr()
    group_on_mask = members @ on_mask  # per group, summed over its segments
    trials_out = (on_mask[seg] * (present > 0)).sum(axis=1)
    trials_in = group_on_mask[grp, graph.view[seg]]

    def same_id(instance: np.ndarray) -> np.ndarray:
        """Per pair: the group's members (the segment left out) in the segment's view with its id."""
        mask_key = graph.view.astype(np.int64) * (int(instance.max(initial=0)) + 1) + instance
        m_keys, m_count = np.unique(group * (int(mask_key.max()) + 1) + mask_key, return_counts=True)
        lookup = grp * (int(mask_key.max()) + 1) + mask_key[seg]
        at = np.minimum(np.searchsorted(m_keys, lookup), m_keys.size - 1)
        return np.where(m_keys[at] == lookup, m_count[at], 0) - own

    # A lone segment shares at most its own view with a group: the ids agree there, or the loose
    # ids do (unsure: neither), or they differ.
    others = per_view[grp, graph.view[seg]] - own
    same = same_id(graph.instance)
    same_loose = same if graph.loose is None else same_id(graph.loose)
    agree = ((same > 0) & (same == others)).astype(np.float64)
    # The lone segment lies in one view: unsure neighbours count as neither where the group spans several.
    same_loose = np.where((present > 0).sum(axis=1) > 1, same_loose, same)
    differ = ((others - same > 0) & (others - same_loose > 0)).astype(np.float64)  # as _Groups.constraints
    pairs = np.bincount(group, minlength=k)[grp] - own
    value = np.where(pairs > 0, linkage(hits_out, trials_out, hits_in, trials_in, volume, mass, agree, differ,
                                        config), 0.0)
    return _PairLinkage(seg, grp, own, value, hits_out, trials_out, volume, mass, per_view)


@dataclass
class _GroupLinks:
    """Per segment, its linkage to its own group and to the best other one (see :func:`segment_confidence`)."""

    own_link: np.ndarray  # (S,) linkage of the segment alone to the rest of its group (0 when alone)
    best_other: np.ndarray  # (S,) the highest linkage to another group (-inf: no evidence with any)
    alone: np.ndarray  # (S,) bool: its group holds only the segment
    margin: np.ndarray  # (S,) own group over the best alternative (another group, or standing alone)
    group_views: np.ndarray  # (S,) other views holding a member of its group
    own_hits: np.ndarray  # (S,) its sample points landing on its group's segments
    own_trials: np.ndarray  # (S,) its points visible in its group's views and landing on some segment there
    other_share: np.ndarray  # (S,) the highest share of its landings on one other group
    other_volume: np.ndarray  # (S,) the highest pooled volumetric similarity to one other group (0 without)


def _group_links(graph: SegmentGraph, labels: np.ndarray, config: ShadowCorrConfig,
                 pairs: _PairLinkage | None = None) -> _GroupLinks:
    """For every segment, the linkage (as between groups) of the segment alone to the rest of
    its own group, and to every other group it has evidence with (:func:`_segment_group_linkage`;
    ``pairs``: its result for these labels, where the caller has it already)."""
    s = graph.num_segments
    _, group = np.unique(labels, return_inverse=True)
    k = int(group.max()) + 1
    if pairs is None:
        pairs = _segment_group_linkage(graph, group, config)
    seg, own, value = pairs.segment, pairs.own, pairs.value
    hits_out, trials_out, volume, mass = pairs.hits_out, pairs.trials_out, pairs.volume, pairs.mass
    per_view = pairs.per_view

    own_link = np.zeros(s)
    own_link[seg[own]] = value[own]
    best_other = np.full(s, -np.inf)
    np.maximum.at(best_other, seg[~own], value[~own])
    alone = np.bincount(group, minlength=k)[group] == 1
    margin = np.where(alone, np.where(np.isfinite(best_other), -best_other, 0.0),
                      own_link - np.maximum(best_other, 0.0))
    own_hits, own_trials = np.zeros(s), np.zeros(s)
    own_hits[seg[own]], own_trials[seg[own]] = hits_out[own], trials_out[own]
    group_views = (per_view[group] > 0).sum(axis=1) - (per_view[group, graph.view] == 1)
    # The strongest pull of any other group, by surface (share of the segment's landings) and
    # by volume (the network's pooled similarity): a piece of a rock that its group lost
    # still lands on, and shares voxels with, the rest of that rock.
    other_share, other_volume = np.zeros(s), np.zeros(s)
    with np.errstate(invalid="ignore", divide="ignore"):
        np.maximum.at(other_share, seg[~own], np.where(trials_out > 0, hits_out / trials_out, 0.0)[~own])
    np.maximum.at(other_volume, seg[~own], (volume / (mass + config.fusion_volume_prior))[~own])
    return _GroupLinks(own_link, best_other, alone, margin, group_views, own_hits, own_trials, other_share,
                       other_volume)


def segment_confidence(graph: SegmentGraph, labels: np.ndarray, config: ShadowCorrConfig) -> np.ndarray:
    """How sure each segment's group is, in (0, 1), from the evidence margin alone.

    The margin of a segment's own group over the best alternative - another group, or standing
    alone (linkage 0) - goes through a logistic of slope ``fusion_confidence_slope``: 0.5 means
    no evidence either way.  (``fused`` calibrates its support instead: ``_09_support``.)
    """
    if graph.num_segments == 0:
        return np.zeros(0)
    return 1.0 / (1.0 + np.exp(-config.fusion_confidence_slope * _group_links(graph, labels, config).margin))




def split_mask_ids(surface: SurfaceEvidence, view: np.ndarray, instance: np.ndarray, config: ShadowCorrConfig
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Mask ids for the per-view constraints, with masks that other views show to be one object made one id,
    and the loose ids: the same with the unsure neighbours of a view made one id as well.

    Two segments a and b of one view v with different mask ids *co-land* on a segment t of
    another view when each lands mostly on t (``fusion_split_landing`` of its points that
    land on a mask there, at least ``projection_min_points``) and t, seen from v, covers both:
    at least ``fusion_split_cover`` of t's points landing on a mask in v land on a, and as
    many on b.  A 2D segmenter that cut one rock in two leaves halves that co-land in most
    views seeing both; two touching rocks co-land only where a third view merged their masks
    (the cover test keeps out a rock half hidden behind its neighbour: the neighbour's
    surface lands on the neighbour alone; the high landing share keeps out a rock whose
    points, in noisy depth, pass for visible just behind its neighbour).  When a and b co-land in at least
    ``fusion_split_views`` views and in at least ``fusion_split_share`` of the views where
    both land on a mask, b's id is taken to be a's for the constraints (blobs of one mask):
    the surface and volumetric evidence still decide whether they join.  Not so for a pair
    whose own seam shows two surfaces (``surface.seams.apart_first`` / ``apart_second``, a
    depth step ``fusion_seam_apart`` standard errors beyond the tolerance): those co-land
    because other views merged two touching rocks, and two merged views would otherwise chain
    the rocks in every view.

    Neighbours of one view whose shared border is one smooth surface
    (``surface.seams``, :func:`shadowcorr.stages.smooth_seams`) are taken as one mask too.
    That needs no other view, and it is what mends the split masks that mask errors leave
    unmended together: a half that no other view sees whole (the rock's other views show it
    under a merged mask, or the halves are each seen by a different view) co-lands nowhere,
    and the cannot-link of its view kept it apart from its other half.

    Neighbours whose seam decides nothing (``surface.seams.unsure_first`` / ``unsure_second``)
    share a loose id: where two groups' ids differ in a view but their loose ids agree, that
    view neither joins nor parts them (:class:`SegmentGraph`).

    The pairs join segments, not masks: a segment of a pair takes the smallest id of its
    connected segments, and the other blobs of its mask keep theirs unless a pair joins them
    too.  So an unsure seam of one blob can give it another loose id than its mask's other
    blobs, whose ids still agree; agreeing ids join (the constraints never take both sides).
    """
    if view.size == 0:
        return instance.copy(), instance.copy()
    p, q = _colanding_pairs(surface, view, instance, config)
    seams = surface.seams
    if seams.apart_first.size and p.size:
        # A merged mask in the other views lands two touching rocks together, as if one rock
        # were cut in two here; the depth step on their seam in their own view says they are two.
        p, q = _without_pairs(p, q, seams.apart_first, seams.apart_second, instance.size)
    # Neighbours of one view meeting on one smooth surface (stage 03 seams) count as well,
    # unless another view sees them apart: the seam needs no other view, which a rock seen
    # once, or seen elsewhere under a merged mask, lacks; in noisy depth two rocks can pass
    # for one surface, and the views that see them apart say so.  Likewise for the unsure ones.
    mostly = None
    if seams.first.size or seams.unsure_first.size:
        mostly = _mostly_on(surface, view, config)
    if seams.first.size:
        together = ~_seen_apart(mostly, instance, seams.first, seams.second)
        p, q = np.r_[p, seams.first[together]], np.r_[q, seams.second[together]]
    ids = _joined_ids(instance, p, q)
    if seams.unsure_first.size == 0:
        return ids, ids
    together = ~_seen_apart(mostly, instance, seams.unsure_first, seams.unsure_second)
    return ids, _joined_ids(instance, np.r_[p, seams.unsure_first[together]], np.r_[q, seams.unsure_second[together]])


def _among_pairs(p: np.ndarray, q: np.ndarray, first: np.ndarray, second: np.ndarray, num_segments: int
                 ) -> np.ndarray:
    """Per pair (``p``, ``q``): is it among the pairs (``first``, ``second``), either order?"""
    def keys(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.minimum(a, b) * num_segments + np.maximum(a, b)

    return np.isin(keys(p, q), keys(first, second))


def _without_pairs(p: np.ndarray, q: np.ndarray, first: np.ndarray, second: np.ndarray, num_segments: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The pairs (``p``, ``q``) that are not among the pairs (``first``, ``second``), either order."""
    kept = ~_among_pairs(p, q, first, second, num_segments)
    return p[kept], q[kept]


def _joined_ids(instance: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``instance`` with the segments that the pairs (``p``, ``q``) connect taking the smallest id among them."""
    out = instance.copy()
    if p.size == 0:
        return out
    s = instance.size
    graph = coo_matrix((np.ones(p.size), (p, q)), shape=(s, s))
    _, comp = connected_components(graph, directed=False)
    # Every segment of a component takes the smallest id of its members (ids compared within a view only).
    smallest = np.full(comp.max() + 1, np.iinfo(np.int64).max)
    np.minimum.at(smallest, comp, instance)
    joined = np.bincount(comp, minlength=comp.max() + 1)[comp] > 1
    out[joined] = smallest[comp[joined]]
    return out


def _colanding_pairs(surface: SurfaceEvidence, view: np.ndarray, instance: np.ndarray, config: ShadowCorrConfig
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of segments of one view that co-land often enough to be halves of one mask (see
    :func:`split_mask_ids`)."""
    none = np.zeros(0, dtype=np.int64)
    if surface.hit_count.size == 0 or config.fusion_split_views == 0:
        return none, none
    s = view.size
    strong = _strong_landings(surface, view, config)
    # Pairs of same-view sources landing mostly on one target: group the strong hits by (target, source view).
    a, t = surface.hit_source[strong], surface.hit_target[strong]
    key = t * (int(view.max()) + 1) + view[a]
    order = np.lexsort((a, key))
    a, t, key = a[order], t[order], key[order]
    first, pair_at = _pairs_within(key)
    if first.size == 0:
        return none, none
    p, q, t = a[first], a[pair_at], t[first]
    # The target must cover both: its landings in their view, on each of them.
    hits_from = _hit_lookup(surface)
    cover = config.fusion_split_cover * surface.on_mask[t, view[p]]
    keep = (instance[p] != instance[q]) & (hits_from(t, p) >= cover) & (hits_from(t, q) >= cover) & (cover > 0)
    p, q = p[keep], q[keep]
    pair, colanding = np.unique(p * s + q, return_counts=True)
    p, q = pair // s, pair % s
    both = ((surface.on_mask[p] >= config.projection_min_points)
            & (surface.on_mask[q] >= config.projection_min_points)).sum(axis=1)
    split = (colanding >= config.fusion_split_views) & (colanding >= config.fusion_split_share * both)
    return p[split], q[split]


def _pairs_within(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)``, ``i < j``, of the entries of a sorted ``key`` that share their key.

    Vectorised per run length: a few distinct run lengths, so a loop over lengths, not pairs.
    """
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if key.size else np.zeros(0, np.int64)
    sizes = np.diff(np.r_[starts, key.size])
    first, second = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for size in np.unique(sizes[sizes >= 2]):
        at = starts[sizes == size]
        i, j = np.triu_indices(size, k=1)
        first.append((at[:, None] + i[None, :]).ravel())
        second.append((at[:, None] + j[None, :]).ravel())
    return np.concatenate(first), np.concatenate(second)


def _hit_lookup(surface: SurfaceEvidence):
    """A function ``(src, dst) -> points of src landing on dst`` (0 where none), vectorised over pairs."""
    s = surface.num_segments
    hit_key = surface.hit_source * s + surface.hit_target
    by_key = np.argsort(hit_key)

    def hits_from(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
        if hit_key.size == 0:
            return np.zeros(np.shape(src), dtype=np.int64)
        k = src * s + dst
        at = np.minimum(np.searchsorted(hit_key, k, sorter=by_key), hit_key.size - 1)
        found = hit_key[by_key[at]] == k
        return np.where(found, surface.hit_count[by_key[at]], 0)

    return hits_from


def _strong_landings(surface: SurfaceEvidence, view: np.ndarray, config: ShadowCorrConfig) -> np.ndarray:
    """Per hit: does its source land mostly on its target?  (``fusion_split_landing`` of the
    source's landings in the target's view, at least ``projection_min_points`` of them.)
    At most one such target per (source, view)."""
    a, t, hits = surface.hit_source, surface.hit_target, surface.hit_count
    landed = surface.on_mask[a, view[t]]
    return (landed >= config.projection_min_points) & (hits >= config.fusion_split_landing * landed)


def _mostly_on(surface: SurfaceEvidence, view: np.ndarray, config: ShadowCorrConfig) -> np.ndarray:
    """(S, V) the segment of view j each segment lands mostly on (``_strong_landings``), -1 where none."""
    strong = _strong_landings(surface, view, config)
    mostly = np.full((view.size, int(view.max()) + 1), -1, dtype=np.int64)
    mostly[surface.hit_source[strong], view[surface.hit_target[strong]]] = surface.hit_target[strong]
    return mostly


def _seen_apart(mostly: np.ndarray, instance: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Per pair: does some view see p and q apart (each lands mostly on a segment there, two
    segments with different mask ids)?"""
    u, v = mostly[p], mostly[q]  # (pairs, views)
    return ((u >= 0) & (v >= 0) & (u != v) & (instance[u] != instance[v])).any(axis=1)


def merged_mask_segments(surface: SurfaceEvidence, view: np.ndarray, instance: np.ndarray,
                         config: ShadowCorrConfig) -> np.ndarray:
    """Which segments look like one mask drawn over two objects (a segmenter's merged mask).

    Segment m of view i is flagged when, in some other view j, two segments t1 and t2 with
    different mask ids

    * each take at least ``fusion_merge_share`` of m's landings in j (and
      ``projection_min_points``): m spreads over both;
    * each land mostly on m (``fusion_split_landing`` of their landings in i): m covers both;
    * are told apart: a third view sees them on two different segments with different mask
      ids (each lands mostly on its own there), or their own seam in view j is a depth step
      (``surface.seams.apart_first`` / ``apart_second``: one surface in front of another,
      which a cut through one rock does not leave), or they do not touch in view j at all
      (``surface.seams.touching_first`` / ``touching_second``, in the views it read: a cut
      leaves the halves of a rock side by side).

    A rock that view j cut in two passes the first two tests but not the third (its halves
    land together on one segment wherever the rock is whole, and meet on one surface in j);
    two touching rocks under one mask of view i pass all three wherever a third view sees them
    apart or one of them stands in front of the other in view j.  The depth step needs no
    third view: with two views, or where the third view merged them too, only view j can
    tell.  Measured on the quality benchmark (30 scenes per cell, 20 seeds of the real scene),
    the third view alone against both: ``real:04`` (two opposite views) under ``mild`` /
    ``field`` errors 98.48 / 98.22 -> 98.57 / 98.46, ``real:012`` 99.11 / 98.38 -> 99.15 /
    98.48 (with :func:`join_nearest_surface`'s vote of the surface in front).  Two opposite
    views also see rocks that stand apart in one view under one mask in the other; their masks
    in view j do not touch, which the depth step cannot read (no seam).  Not touching, against
    the step alone (same benchmark): ``real:04`` under ``mild`` / ``field`` errors 98.80 /
    98.96 -> 98.98 / 98.99; over all 110 rows 9 gain and 6 lose, at most 0.09
    (``syn:4v-720p+harsh``; in its worst scene, and in that of ``syn:3v-arc90+harsh``, the mask
    found was a true merge, and without the landings on it a third rock fell apart).  The fused
    method passes the ids of :func:`split_mask_ids`, so masks read as halves of one split mask are
    never the two objects.  Where m lands fewer than ``_MERGE_FEW_LANDINGS`` points in every
    other view (two opposite cameras share only the rocks' rims), its spread names one segment
    or none; the segments of another view that land mostly on m then count as its spread too,
    those that land mostly on no segment of a third view (a third view that sees a segment says
    by itself which rock it is).  Measured on the quality benchmark against reading m's spread
    alone: 10 of 110 rows move, 7 gain and 3 lose, at most 0.08 (``syn:4v-720p+harsh`` 96.75
    -> 96.67); ``real:04`` under ``mild`` / ``field`` errors 98.98 / 98.99 -> 99.09 / 99.12,
    ``syn:2v-opposite+field`` 98.77 -> 98.93, +0.38 over the rows together; no row without
    combined errors moves.  With few landings asked of view j alone, ``syn:4v+harsh`` lost 0.08
    (+0.34 together); without the third-view condition, ``syn:4v-low+mild`` lost 0.13.  A mask
    over three rocks, or over a large rock and a small one, leaves the smaller ones less than
    ``fusion_merge_share`` of its landings and is missed; a lower share did not pay on the 39
    combined-error rows (same benchmark): 0.15 nets -0.08 over them (15 rows gain, 13 lose),
    0.10 nets -0.40 (``real:all8+field`` -0.11), and 0.10 only for pairs that a third view sees
    apart nets -0.28 (10 gain, 12 lose).  In three of the runs that lost most, the masks that
    rule added were true merges, but with all their landings gone the rock a mask is mostly
    over joined a neighbour (``real:all8+field``: two rocks became one object); taking out only
    the small rock's landings on the mask, and keeping the mask's other evidence, nets -0.16
    (4 gain, 6 lose, at most 0.08); with view j asked to part the pair too, that is what
    :func:`thin_cover_pairs` does.  What counting landings cannot tell apart: a rock cut the
    same way in two views and whole in a third looks exactly like two rocks merged in that
    third view (measured: 4 such segments flagged in 30 scenes of the quality benchmark's 20 %
    line splits, about 2,000 segments, and no purity lost).  Ground truth is not read: mask ids
    are compared only within their own view.
    """
    return _merged_masks(surface, view, instance, config)[0]


#: A segment that lands fewer points than this in every other view shows too little of how it
#: spreads there: the segments under it are read instead (see merged_mask_segments).
_MERGE_FEW_LANDINGS = 150

#: The least share of a mask's landings in a view that marks a segment there as a small object under
#: it (:func:`thin_cover_pairs`); below ``fusion_merge_share``, where :func:`merged_mask_segments` reads.
_MERGE_THIN_SHARE = 0.15


def _merged_masks(surface: SurfaceEvidence, view: np.ndarray, instance: np.ndarray, config: ShadowCorrConfig
                  ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """(S,) the merged masks (:func:`merged_mask_segments`), (S,) those of them whose two objects
    only view j itself tells apart (a depth step between them there, or no contact; no third view
    sees both), and the (segment, mask) pairs of the small objects under masks that are mostly
    one object (:func:`thin_cover_pairs`)."""
    s = view.size
    merged = np.zeros(s, dtype=bool)
    none = np.zeros(0, dtype=np.int64)
    if s == 0 or surface.hit_count.size == 0 or config.fusion_merge_share == 0:
        return merged, merged.copy(), (none, none)
    a, t, hits = surface.hit_source, surface.hit_target, surface.hit_count
    landed = surface.on_mask[a, view[t]]
    mostly = _mostly_on(surface, view, config)
    spread = (hits >= config.projection_min_points) & (hits >= config.fusion_merge_share * landed)
    # A thin share of m's landings (from _MERGE_THIN_SHARE): the segment under it is a small object
    # beside the one m is mostly over (see thin_cover_pairs).
    thin = (hits >= config.projection_min_points) & (hits >= _MERGE_THIN_SHARE * landed) & ~spread
    # Where m lands too rarely in every other view to read how it spreads there (two cameras that
    # share only the rocks' rims), the segments that land mostly on m, and on no segment of a third
    # view, are m's candidates too.  (A segment never lands in its own view: on_mask is 0 there.)
    rarely_seen = (surface.on_mask < _MERGE_FEW_LANDINGS).all(axis=1)
    lands_mostly = mostly >= 0
    in_one_view = lands_mostly.sum(axis=1) == 1
    covered, seen_in = np.nonzero(lands_mostly)
    over = mostly[covered, seen_in]
    reverse = rarely_seen[over] & in_one_view[covered]
    spread_pair = np.unique(np.r_[a[spread], over[reverse]] * s + np.r_[t[spread], covered[reverse]])
    thin_pair = np.setdiff1d(a[thin] * s + t[thin], spread_pair)
    pair = np.r_[spread_pair, thin_pair]
    is_thin = np.r_[np.zeros(spread_pair.size, dtype=bool), np.ones(thin_pair.size, dtype=bool)]
    a, t = pair // s, pair % s
    key = a * (int(view.max()) + 1) + view[t]  # per (m, view j): the segments m spreads over
    order = np.argsort(key, kind="stable")
    a, t, key, is_thin = a[order], t[order], key[order], is_thin[order]
    i, j = _pairs_within(key)
    m, t1, t2 = a[i], t[i], t[j]
    thin_i, thin_j = is_thin[i], is_thin[j]
    covers = (instance[t1] != instance[t2]) & (mostly[t1, view[m]] == m) & (mostly[t2, view[m]] == m)
    seen_apart = covers & _seen_apart(mostly, instance, t1, t2)
    # View j itself parts the pair: a depth step on their seam there, or two masks that do not even
    # touch there (a cut leaves the halves of a rock side by side).
    seams = surface.seams
    parted_in_j = _among_pairs(t1, t2, seams.apart_first, seams.apart_second, s) | (
        np.isin(view[t1], seams.views_read) & ~_among_pairs(t1, t2, seams.touching_first, seams.touching_second, s))
    # A pair with a thin member is read only where a third view and view j both see it apart, and
    # never makes m a merged mask: m stays with the object it is mostly over.
    thin_cover = seen_apart & (thin_i | thin_j) & parted_in_j
    covers &= ~(thin_i | thin_j)
    seen_apart &= covers
    stepped = covers & parted_in_j
    merged[m[seen_apart | stepped]] = True
    step_only = merged.copy()
    step_only[m[seen_apart]] = False
    thin_cover &= ~merged[m]  # a merged mask's landings all go (without_landings_on)
    small = np.r_[t1[thin_cover & thin_i], t2[thin_cover & thin_j]]
    under = np.r_[m[thin_cover & thin_i], m[thin_cover & thin_j]]
    return merged, step_only, (small, under)


def thin_cover_pairs(surface: SurfaceEvidence, view: np.ndarray, instance: np.ndarray, config: ShadowCorrConfig
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(segment t, mask m) pairs: m, mostly over one object, also covers a small object that t is.

    A mask drawn over a large rock and a small one (or over three rocks) leaves the small ones
    less than ``fusion_merge_share`` of its landings, so :func:`merged_mask_segments` does not read
    it as merged.  Segment t of view j is such a small object under mask m of view i when t takes
    at least ``_MERGE_THIN_SHARE`` of m's landings in j (and ``projection_min_points``), t and a
    segment t' of j with another mask id each land mostly on m, t' takes at least
    ``fusion_merge_share`` of m's landings or a thin share too, a third view sees t and t' apart
    (each lands mostly on its own segment there, two mask ids), and view j parts them too (a
    depth step on their seam there, or their masks do not touch).  The landings of t on m are
    then no evidence that t is m's object (:func:`without_landings`); m keeps the rest of its
    evidence, so it stays with the object it is mostly over, and its view's constraints keep
    that object apart from its neighbours.

    Measured on the quality benchmark (30 scenes per cell, 20 seeds of the real scene) against
    the grouping without it: 7 of 110 rows move, 6 gain and 1 loses, +0.18 points over them
    together (``real:013467+harsh`` 97.58 -> 97.63, ``syn:4v-low+mild`` 98.99 -> 99.03,
    ``syn:4v+depth1%corr4px`` 99.96 -> 100.00; ``syn:4v-720p+field`` 99.26 -> 99.24); no clean
    row moves.  From a tenth of the landings (``_MERGE_THIN_SHARE`` = 0.1) every row is the same
    but ``syn:4v-low+field``, 97.66 -> 97.59 (a merge rightly found moved a third rock's
    14-sample segment to the wrong object); from 6 %, the 39 combined-error rows net -0.08
    against a tenth (``real:all8+harsh`` -0.06).  Without view j's parting (the
    third view alone) it nets -0.16 over the 39 combined-error rows: a rock cut the same way in two views passes the third
    view's test (``syn:8v+field``).  Making such a mask a merged mask instead (all landings on it
    dropped) found true merges but lost 0.28 over the 39 combined-error rows: with the mask's
    evidence gone, the object it is mostly over lost its member in that view, and with it the
    constraint that held it apart from a neighbour (``real:all8+field``: two rocks joined).
    Mask ids are compared only within their own view; ground truth is not read.
    """
    return _merged_masks(surface, view, instance, config)[2]


def without_landings_on(surface: SurfaceEvidence, view: np.ndarray, drop: np.ndarray) -> SurfaceEvidence:
    """The surface evidence with every landing *on* a segment in ``drop`` taken out (hits and trials).

    Landing on a merged mask says only that a point belongs to one of the objects under it:
    no evidence for or against any one of them.  The segment's own landings stay (which object
    it finally joins is settled by :func:`join_nearest_surface`).
    """
    return without_landings(surface, view, drop[surface.hit_target])


def without_landings(surface: SurfaceEvidence, view: np.ndarray, gone: np.ndarray) -> SurfaceEvidence:
    """The surface evidence without the landings ``gone`` (per hit of ``surface``): their hits, and
    their points from the trials (``on_mask``) of their sources in their targets' views."""
    if not gone.any():
        return surface
    on_mask = surface.on_mask.copy()
    np.subtract.at(on_mask, (surface.hit_source[gone], view[surface.hit_target[gone]]), surface.hit_count[gone])
    keep = ~gone
    return replace(surface, on_mask=on_mask, hit_source=surface.hit_source[keep],
                   hit_target=surface.hit_target[keep], hit_count=surface.hit_count[keep])


@dataclass
class EvidenceGroups:
    """What grouping by evidence hands on: a group per segment and the evidence it was read from."""

    labels: np.ndarray  # (S,) group of each segment
    graph: SegmentGraph  # the evidence the groups were resolved from
    merged: np.ndarray  # (S,) bool: read as a mask drawn over two objects


def group_by_evidence(scene: VoxelScene, embeddings: np.ndarray | None, config: ShadowCorrConfig) -> EvidenceGroups:
    """The group of every segment from the evidence between segments.

    ``projection`` links segments by cross-view landings alone; ``fused`` adds the network's
    volumetric evidence (``embeddings``) and resolves both by signed average linkage.  How sure
    each segment's group is comes next (``_09_support.segment_support``).
    """
    if scene.surface is None:
        raise ValueError(f"method {config.method!r} needs a scene prepared with method {config.method!r} "
                         "(its cross-view surface evidence is missing)")
    s = scene.num_segments
    none = np.zeros(0, dtype=np.int64)
    volume = (none, none, np.zeros(0), np.zeros(0))
    if config.method == "fused":
        volume = volume_pairs(scene, embeddings, config)
    instance, surface = scene.segment_instance, scene.surface
    merged = np.zeros(s, dtype=bool)
    loose = None
    if config.method == "fused":
        instance, loose = split_mask_ids(surface, scene.segment_view, instance, config)
        merged, step_only, (small, under) = _merged_masks(surface, scene.segment_view, instance, config)
        # No evidence: landings on a merged mask, and a small object's landings on the mask over its neighbour.
        hit_key = surface.hit_source * s + surface.hit_target
        gone = merged[surface.hit_target] | np.isin(hit_key, small * s + under)
        surface = without_landings(surface, scene.segment_view, gone)
    graph = SegmentGraph(scene.segment_view, instance, surface, *volume,
                         loose=None if loose is instance else loose)  # the same array when no pair is unsure
    if config.method == "projection":
        labels = link_components(scene.surface, scene.segment_view, config)
    else:
        cameras = None if scene.view_poses is None else scene.view_poses[:, :3, 3] * scene.unit_scale
        # The landings as measured (scene.surface, not the graph's): what a merged mask covers
        # is read from the landings on it, which the graph leaves out.
        labels = join_nearest_surface(agglomerate(graph, config), scene.surface, scene.segment_view, merged, config,
                                      scene.shell_points, scene.shell_count, cameras, step_only)[:s]
        if scene.shell_points is not None:
            labels = join_isolated(labels, graph, scene.shell_points, scene.shell_count, config)
        if scene.segment_cut is not None:
            labels = join_lone_pieces(labels, scene.segment_view, scene.segment_cut, scene.segment_num_points)
    return EvidenceGroups(labels[:s], graph, merged)


def join_lone_pieces(labels: np.ndarray, view: np.ndarray, cut: np.ndarray, size: np.ndarray) -> np.ndarray:
    """``labels`` with each piece of a blob cut at a depth step (stage 02, ``cut`` >= 0) that stands
    alone in its group joined to the group of the largest of its blob's pieces that does not.

    The cut parts a mask drawn over two rocks, so that the other views can tell them apart; where
    no other view says anything of a piece (it lands on nothing, no shadow it casts meets another),
    the step alone made it an object, and a rock's own step (an overhang, a ledge) cuts as well
    as two rocks do.  Measured with the segments' truth on the quality benchmark (9 rows of
    combined and mask errors, 20 scenes each): of the 50 pieces that the cut took out of one
    rock, 7 ended in a wrong group, 5 of them alone; of the 285 pieces of masks over two rocks, 4,
    1 of them alone.  So a piece alone goes back to its blob.
    """
    if labels.size == 0 or not (cut >= 0).any():
        return labels
    alone = np.bincount(labels, minlength=int(labels.max()) + 1)[labels] == 1
    pieces = np.flatnonzero(cut >= 0)
    key = view[pieces] * (int(cut.max()) + 1) + cut[pieces]
    grouped = ~alone[pieces]
    if not grouped.any() or grouped.all():
        return labels
    # Per blob, its largest grouped piece (ties: the first).
    g = pieces[grouped]
    order = np.lexsort((g, -size[g], key[grouped]))
    blob_keys, first = np.unique(key[grouped][order], return_index=True)
    best = g[order][first]
    lone = ~grouped
    at = np.minimum(np.searchsorted(blob_keys, key[lone]), blob_keys.size - 1)
    found = blob_keys[at] == key[lone]
    out = labels.copy()
    out[pieces[lone][found]] = labels[best[at[found]]]
    return out


def isolated_segments(graph: SegmentGraph) -> np.ndarray:
    """(S,) bool: segments without any evidence with another segment - no landing either way, no
    shared shadow voxel, no other blob of their mask - which the agglomeration leaves alone."""
    linked = np.zeros(graph.num_segments, dtype=bool)
    for ends in (graph.surface.hit_source, graph.surface.hit_target, graph.volume_a, graph.volume_b,
                 *_same_mask_pairs(graph)):
        linked[ends] = True
    return ~linked


#: The most sample points a segment :func:`join_isolated` joins may carry.  A larger segment's shadow reaches
#: deep behind it (``projection_factor`` times its second axis), so where it meets nothing, nothing of
#: its rock lies there: a rock only its own view sees.  Of the isolated segments that joined the wrong
#: rock without this bound, each carried 364 to 756 points (two opposite cameras under ``field`` and
#: ``harsh`` errors, the real scene's three cameras under ``harsh`` ones); of those it joined rightly,
#: all but one carried 4 to 65.
_ISOLATED_MAX_SAMPLES = 100


def join_isolated(labels: np.ndarray, graph: SegmentGraph, shell_points: np.ndarray, shell_count: np.ndarray,
                  config: ShadowCorrConfig) -> np.ndarray:
    """``labels`` with each segment that has no evidence at all (:func:`isolated_segments`) and stands
    alone joined to the group of the nearest surface another view saw, where that surface lies
    within ``fusion_isolated_reach`` of one of its points and that group holds no segment of its view.

    A rock's sliver - the part of it that peeks past a neighbour, or an eroded piece of a split
    mask - carries a handful of points: none of them lands on a segment of another view (the
    other views see the rock's other side, or the eroded rim they would land on is gone), and its
    shadow is too short to share a voxel with anything.  Left alone it is an object of its own
    and splits its rock.  Yet its surface meets the rest of its rock at the rock's outline, where
    the views that see the rest of the rock saw surface within a few centimetres of it.  A rock
    seen by one view alone lies as close to its neighbours; what tells the two apart is the
    view: a neighbour the segment's own view also sees is another rock there (its own segment),
    while the views that see the rest of the sliver's rock do not see the sliver's side.  The
    nearest surface is read on the cleaned shells of the other views' segments (one point per
    ``downsample_size`` cell); segments are taken in order, and a group that took one segment
    of a view takes no other of that view.  Only segments of at most ``_ISOLATED_MAX_SAMPLES``
    sample points are joined: a larger one casts a shadow deep enough to meet its rock's other
    segments, so where it meets none, it is a rock of its own.

    Measured with the segments' truth on the quality benchmark's rigs (30 scenes, before the
    rule existed): on the low rig (cameras 80 cm high, grazing views) 26-38 such segments per
    row stood alone, 8-16 of them pieces of a rock that other segments see; within 12 units,
    with the view test, the rule joins 9 of them under ``field`` errors, 6 under ``mild`` and 2
    on clean images, with 0, 1 and 0 joined to the wrong rock.  On the quality benchmark (30
    scenes per cell, 20 seeds of the real scene), against no such rule: ``syn:4v-low`` clean /
    ``mild`` / ``field`` / ``harsh`` 99.64 / 98.93 / 97.44 / 93.62 -> 99.70 / 99.03 / 97.66 /
    93.95, ``syn:3v-arc90`` clean / ``field`` 99.74 / 99.41 -> 99.81 / 99.58, ``real:04+harsh``
    95.21 -> 95.30; 9 rows gain, none loses.  On the four-camera default rig no segment is
    isolated.  0 turns the rule off.
    """
    reach = config.fusion_isolated_reach
    view = graph.view
    if reach <= 0 or labels.size == 0:
        return labels
    alone = np.bincount(labels, minlength=int(labels.max()) + 1)[labels] == 1
    small = graph.surface.samples <= _ISOLATED_MAX_SAMPLES
    candidates = np.flatnonzero(isolated_segments(graph) & alone & small & (shell_count > 0))
    if candidates.size == 0:
        return labels
    owner = np.repeat(np.arange(view.size), shell_count)
    ends = np.cumsum(shell_count)
    # Per candidate: the nearest shell point of another view, one k-d tree per view that holds a candidate.
    target, gap = np.full(view.size, -1), np.full(view.size, np.inf)
    for v in np.unique(view[candidates]).tolist():
        others = np.flatnonzero(view[owner] != v)
        if others.size == 0:
            continue
        tree = KDTree(np.asarray(shell_points[others], dtype=np.float64))
        for a in candidates[view[candidates] == v].tolist():
            distance, nearest = tree.query(np.asarray(shell_points[ends[a] - shell_count[a]:ends[a]], np.float64), k=1)
            i = int(np.argmin(distance))
            gap[a], target[a] = distance[i], owner[others[nearest[i]]]
    out = labels.copy()
    for a in candidates.tolist():  # in order: a group that took a segment of a view takes no other of it
        if gap[a] > reach or (view[out == out[target[a]]] == view[a]).any():
            continue
        out[a] = out[target[a]]
    return out


def join_nearest_surface(labels: np.ndarray, surface: SurfaceEvidence, view: np.ndarray, segments: np.ndarray,
                         config: ShadowCorrConfig, shell_points: np.ndarray | None = None,
                         shell_count: np.ndarray | None = None, cameras: np.ndarray | None = None,
                         drawn: np.ndarray | None = None) -> np.ndarray:
    """``labels`` with each of ``segments`` (merged masks) moved to the group that owns more than
    half of its surface, where one does.

    A mask drawn over two objects belongs, for its view, to the object under most of it.
    Its landings only count its points that other views see, and its linkage mixes in the
    volume it shares with both objects, so neither tells which object that is.  Its sample
    points do (spread evenly over its pixels).  A point that another view sees - within
    ``projection_depth_tolerance`` of the nearest surface point of another view's segment
    (other merged masks left out) - votes for that segment's group; every other point takes
    the vote of the nearest point of the mask that one sees.  With at least
    ``projection_min_points`` seen points and a majority over all the points, the mask joins
    that group.  One k-d tree per view that holds a merged mask; nothing runs when there is none.

    A point that no other view sees lies near no seen surface of its own rock; under a mask over
    two touching rocks the nearest surface can be the other rock's side, which the mask's view
    does not see, while the mask's own nearest seen points lie on its own rock.  Measured on the
    quality benchmark (30 scenes per cell, 20 seeds of the real scene, each mask's truth),
    against each point within ``fusion_merge_reach`` voting for its nearest surface:
    ``syn:4v-720p`` under 5 % merges and 2 px erosion together 99.33 -> 99.52,
    ``real:0246+merge5%`` 99.32 -> 99.40, the mean over the 13 rigs under ``mild`` errors
    99.13 -> 99.15, ``harsh`` 95.53 -> 95.54, the ``field`` mean and every clean row unchanged;
    the rows that lose lose one mask each on an even vote (``real:0246+harsh`` -0.07: 49 % of
    the points where the other rule gave 51 %; ``syn:4v+merge5%`` -0.01: a mask half over each
    rock).

    With fewer seen points than that, every point within ``fusion_merge_reach`` votes for its
    nearest surface and the majority of them decides.  The reach is wider than the depth
    tolerance: the part of the mask that no other view sees lies nearer to its own rock's
    surface elsewhere than to the other rock's more often than not (with every point voting
    this way, on the quality benchmark's rows, 10 scenes: against 3 units, 15 raised the mean
    over the 13 rigs under ``mild`` errors from 98.96 to 99.08).

    The other views' surface points are the segments' cleaned shells (``shell_points``, sorted by
    segment, ``shell_count`` per segment: one point per ``downsample_size`` cell of surface), so
    that every part of the surface is found as easily as any other.  Their sample points
    instead (the fallback without shells) are a fixed number per segment: a large segment's lie
    several centimetres apart, a small one's nearly touch, and under depth noise a point of the
    mask finds the small segment's surface within the tolerance more often than the large one's -
    the vote went to the rock with the smaller segments.  Measured on the quality benchmark's
    default rig under the ``mild`` errors (10 scenes), four of the twelve merged masks found
    joined the wrong rock that way, each by a close vote; counted on the shells, one.

    The masks in ``drawn`` (with ``cameras``, every view's camera centre in config units) are
    those whose two objects only another view's own masks told apart, by a depth step between
    them or by not touching: no third view sees both (:func:`merged_mask_segments`).  Other
    views see little of such a mask - two opposite cameras see each rock's far side - and the
    few points they see carry the vote above for the
    rest.  Instead, the surfaces of the segments it covers (those of other views that land
    mostly on it) are drawn into its view: each of its sample points takes the group of the
    surface in front along its ray from the camera (:func:`_surface_in_front`), and with at
    least ``projection_min_points`` such points the majority of them decides (none: it stays).
    Where its covered segments hold one group only, or too few rays meet them, the vote above
    decides.  Measured on the quality benchmark (30 scenes per cell, 20 seeds of the real
    scene), against that vote for these masks as well: ``real:04`` under ``field`` errors
    98.20 -> 98.46, ``syn:4v+harsh`` 97.64 -> 97.69, ``syn:2v-opposite+mild`` 98.57 -> 98.63;
    ``real:04+mild`` 98.69 -> 98.57.  For the masks a third view told apart the vote above is
    the better one (drawn for every mask, ``real:0246+merge10%`` fell from 99.28 to 98.95).
    """
    if not segments.any():
        return labels
    reference, count = (surface.points, surface.samples) if shell_points is None else (shell_points, shell_count)
    reference_owner = np.repeat(np.arange(view.size), count)
    reference_view = np.where(segments[reference_owner], -1, view[reference_owner])  # merged masks: no view
    end = np.cumsum(surface.samples)
    if cameras is None or drawn is None or not (drawn & segments).any():
        drawn = None
    mostly = None if drawn is None else _mostly_on(surface, view, config)
    out = labels.copy()
    for v in np.unique(view[segments]).tolist():
        others = np.flatnonzero((reference_view != v) & (reference_view >= 0))
        if others.size == 0:
            continue
        tree = KDTree(reference[others])
        for m in np.flatnonzero(segments & (view == v)).tolist():
            points = surface.points[end[m] - surface.samples[m]: end[m]]
            if drawn is not None and drawn[m]:
                # The objects it covers: the other views' segments that land mostly on it.
                candidates = np.flatnonzero((mostly[:, v] == m) & ~segments)
                if np.unique(labels[candidates]).size >= 2:
                    covered = np.isin(reference_owner, candidates)
                    front = _surface_in_front(points, cameras[v], reference[covered],
                                              labels[reference_owner[covered]], config)
                    if front.size >= config.projection_min_points:
                        groups, votes = np.unique(front, return_counts=True)
                        if votes.max() > 0.5 * front.size:
                            out[m] = groups[np.argmax(votes)]
                        continue
            distance, nearest = tree.query(points, k=1)
            voting = distance <= config.fusion_merge_reach
            if voting.sum() < config.projection_min_points:
                continue
            owner = labels[reference_owner[others[nearest]]]
            seen = distance <= config.projection_depth_tolerance
            if seen.sum() >= config.projection_min_points:
                # every point takes the vote of the nearest point of the mask that another view sees
                owner = owner[seen][KDTree(points[seen]).query(points, k=1)[1]]
                voting[:] = True
            groups, votes = np.unique(owner[voting], return_counts=True)
            if votes.max() > 0.5 * voting.sum():
                out[m] = groups[np.argmax(votes)]
    return out


def _surface_in_front(points: np.ndarray, camera: np.ndarray, reference: np.ndarray, reference_group: np.ndarray,
                      config: ShadowCorrConfig) -> np.ndarray:
    """The group of the surface in front along the ray of each of ``points`` from ``camera``, for the
    points whose ray meets one (see :func:`join_nearest_surface`).

    A ray meets the ``reference`` points within twice the angular spacing of ``points`` around it
    (at most ``_FRONT_NEIGHBOURS`` of them); of those that do not lie in front of the point by more
    than ``projection_depth_tolerance`` (a surface there would hide it), the nearest to the camera
    gives the group.
    """
    rays, depth = _rays(points, camera)
    reference_rays, reference_depth = _rays(reference, camera)
    spacing = float(np.median(KDTree(rays).query(rays, k=2)[0][:, 1]))
    k = min(_FRONT_NEIGHBOURS, len(reference))
    _, near = KDTree(reference_rays).query(rays, k=k, distance_upper_bound=2.0 * spacing)
    near = near.reshape(len(points), k)
    met = near < len(reference)  # pykdtree marks a missing neighbour with the number of points
    near = np.where(met, near, 0)
    behind = np.where(met & (reference_depth[near] >= depth[:, None] - config.projection_depth_tolerance),
                      reference_depth[near], np.inf)
    first = np.argmin(behind, axis=1)
    rows = np.flatnonzero(np.isfinite(behind[np.arange(len(points)), first]))
    return reference_group[near[rows, first[rows]]]


def _rays(points: np.ndarray, camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (float64, for the k-d tree) and distances of ``points`` from ``camera``."""
    offset = np.asarray(points, dtype=np.float64) - camera
    distance = np.sqrt(np.einsum("ij,ij->i", offset, offset))
    return offset / np.maximum(distance, 1e-12)[:, None], distance


#: Reference points a ray is compared with: the nearest in angle, of which the nearest in depth counts.
_FRONT_NEIGHBOURS = 16
