"""Stage 9, how sure each segment's group is; for ``fused``, the probability that it sits with its own object.

The grouping's evidence margin (its own group's linkage over the best alternative) says how
a segment's place was decided, not how often such a decision is right: under a segmenter's
errors a small eroded piece of a split mask with a clear margin is wrong more often than a
large segment with a thin one.  So the support is a model of what the evidence says about the
segment (:data:`SUPPORT_FEATURES`): its links to its own group and to the others, how much
evidence they rest on, and what its group as a whole says - a group that is pulled towards
another one as a whole (a rock's split-off piece, seen in several views) or holds nothing in
views where the segment's points land.  Most wrong segments the margin misses are a second
object inside a group that is right otherwise: a member that shares its view with another
member under another mask id, and is the smaller of the two; whose points, seen from the
views where the rest of the group is, land on no mask or on other groups; on which the rest
of the group's points, seen from its view, do not land.  Features of each say so.  Which of
them matters depends on the others (a thin share of its view's points means little alone and
much beside another mask of that view), so the model is boosted regression trees, shipped as
node tables (:class:`SupportTrees`; a logistic regression on the standardised features where
a calibration has no trees).  It is fitted on generated scenes under single and combined
errors whose truth is known (``scripts/fit_support.py``; the scenes differ from the quality
benchmark's), and shipped as ``models/support.json`` with the threshold below which a segment
is worth checking: the highest that still flags wrong segments with 55 % precision on the
fitted scenes' combined-error runs, read from out-of-fold supports (``--precision``; the
field's scenes are harder than the fitted ones, and there the flag should keep 50 %).  The
features are read from the grouping's result only: the support never changes a label.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np
from scipy.sparse import coo_matrix

from ..config import ShadowCorrConfig
from ._09_grouping import EvidenceGroups, _group_links, _segment_group_linkage, segment_confidence

__all__ = ["SUPPORT_FEATURES", "SupportCalibration", "SupportTrees", "support_calibration", "support_features",
           "segment_support"]

#: What the calibrated support of ``fused`` reads of a segment (:func:`support_features`).
SUPPORT_FEATURES = (
    "margin",  # its own group's linkage over the best alternative (first: the site map reads it)
    "own_link",  # linkage to the rest of its group (0 alone)
    "best_other",  # the best other group's linkage (0 without evidence)
    "alone",  # 1 when its group holds only the segment
    "group_views",  # other views that hold a member of its group
    "landing_share",  # of its points visible in its group's views and landing on a segment there, the share on its group
    "landing_trials",  # log(1 + those points): how much evidence the share rests on
    "log_samples",  # log(1 + its sample points): small (eroded, split) segments carry little evidence
    "merged",  # 1 when read as a mask drawn over two objects
    "mask_siblings",  # 1 when other segments of its view wear its (split-joined) mask id
    "other_share",  # the highest share of its landings on one other group
    "other_volume",  # the highest volumetric similarity to one other group
    "own_volume",  # the volumetric similarity to the rest of its group (0 without shared voxels)
    "own_volume_mass",  # log(1 + the volumetric mass it shares with the rest of its group)
    "landing_views",  # other views in which its points land on some mask
    "missing_views",  # of those, the views where its group holds no segment
    "group_size",  # log(segments in its group)
    "group_other_share",  # the mean of other_share over its group: the whole group is pulled elsewhere
    "group_landing_share",  # the mean of landing_share over its group
    "group_own_link",  # the mean of own_link over its group
    "own_link_below_group",  # own_link minus the group's mean: the odd member out of a group of two objects
    "pull_size",  # log of its group's sample points over those of the group it is linked to best
    "candidates",  # log(1 + other groups it has evidence with)
    # Two objects in one group: a member that shares its view with another member under another mask id.
    "view_rivals",  # 1 when its group holds another segment of its view with another (split-joined) mask id
    "view_share",  # its sample points over those of its group's segments in its view
    "group_rival_views",  # views in which its group holds segments of two mask ids
    # What the views say where its group is: a rock's points land on its own segments there.
    "own_cover",  # of its points visible in views where the rest of its group is, the share landing on the group
    "off_mask",  # of those points, the share landing on no mask at all
    "reverse_cover",  # of its group's points visible in its view, the share landing on the segment
    "reverse_share",  # of its group's points landing on some mask in its view, the share landing on the segment
    "group_own_cover",  # the mean of own_cover over its group
    "group_reverse_cover",  # the mean of reverse_cover over its group
)


def support_features(groups: EvidenceGroups, config: ShadowCorrConfig) -> np.ndarray:
    """(S, len(SUPPORT_FEATURES)) what the evidence says about each segment's place (see SUPPORT_FEATURES)."""
    graph = groups.graph
    s = graph.num_segments
    if s == 0:
        return np.zeros((0, len(SUPPORT_FEATURES)))
    surface = graph.surface
    _, group = np.unique(groups.labels, return_inverse=True)
    k = int(group.max()) + 1
    pairs = _segment_group_linkage(graph, group, config)
    links = _group_links(graph, groups.labels, config, pairs)
    key = graph.view.astype(np.int64) * (int(graph.instance.max(initial=0)) + 1) + graph.instance
    _, mask_of, mask_size = np.unique(key, return_inverse=True, return_counts=True)
    landing_share = links.own_hits / np.maximum(links.own_trials, 1.0)

    own = pairs.own
    own_volume, own_mass = np.zeros(s), np.zeros(s)
    own_volume[pairs.segment[own]] = (pairs.volume / (pairs.mass + config.fusion_volume_prior))[own]
    own_mass[pairs.segment[own]] = pairs.mass[own]
    # Views whose masks its points land on, and those of them where its group is absent.
    lands = surface.on_mask >= config.projection_min_points
    lands[np.arange(s), graph.view] = False
    present = pairs.per_view[group] > 0
    members = np.bincount(group, minlength=k)

    def group_mean(values: np.ndarray) -> np.ndarray:
        return (np.bincount(group, weights=values, minlength=k) / members)[group]

    # The group each segment is linked to best, other than its own, and how large it is.
    samples = surface.samples.astype(np.float64)
    group_samples = np.bincount(group, weights=samples, minlength=k)
    others = np.flatnonzero(~own)
    order = others[np.lexsort((-pairs.value[others], pairs.segment[others]))]
    first = order[np.r_[True, pairs.segment[order][1:] != pairs.segment[order][:-1]]] if order.size else order
    pull = np.zeros(s)
    pull[pairs.segment[first]] = np.log((group_samples[group[pairs.segment[first]]] + 1.0)
                                        / (group_samples[pairs.group[first]] + 1.0))
    candidates = np.bincount(pairs.segment[others], minlength=s)

    # Segments of its group in its own view: one mask id (blobs of a mask) or several (two objects).
    num_views = surface.on_mask.shape[1]
    group_view = group * num_views + graph.view
    in_view = np.bincount(group_view, minlength=k * num_views)
    same_mask = np.unique(group_view * (int(graph.instance.max(initial=0)) + 1) + graph.instance,
                          return_inverse=True, return_counts=True)
    rivals = in_view[group_view] - same_mask[2][same_mask[1]] > 0
    view_samples = np.bincount(group_view, weights=samples, minlength=k * num_views)
    rival_views = np.zeros(k * num_views)
    rival_views[group_view[rivals]] = 1.0
    # Landings within the group, both ways, over the points visible there.
    within = group[surface.hit_source] == group[surface.hit_target]
    hits = surface.hit_count[within].astype(np.float64)
    hits_out = np.bincount(surface.hit_source[within], weights=hits, minlength=s)
    hits_in = np.bincount(surface.hit_target[within], weights=hits, minlength=s)
    others_there = (pairs.per_view[group] - (np.arange(num_views)[None, :] == graph.view[:, None])) > 0
    visible = surface.visible.astype(np.float64)
    seen = (visible * others_there).sum(axis=1)
    seen_on_mask = (surface.on_mask * others_there).sum(axis=1)
    own_cover = np.where(seen > 0, hits_out / np.maximum(seen, 1.0), 1.0)
    member_of = coo_matrix((np.ones(s), (group, np.arange(s))), shape=(k, s)).tocsr()
    group_visible = np.asarray(member_of @ visible)[group, graph.view]
    group_on_mask = np.asarray(member_of @ surface.on_mask.astype(np.float64))[group, graph.view]
    reverse_cover = np.where(group_visible > 0, hits_in / np.maximum(group_visible, 1.0), 1.0)
    return np.stack([
        links.margin,
        links.own_link,
        np.where(np.isfinite(links.best_other), links.best_other, 0.0),
        links.alone.astype(np.float64),
        links.group_views.astype(np.float64),
        landing_share,
        np.log1p(links.own_trials),
        np.log1p(samples),
        groups.merged.astype(np.float64),
        (mask_size[mask_of] > 1).astype(np.float64),
        links.other_share,
        links.other_volume,
        own_volume,
        np.log1p(own_mass),
        lands.sum(axis=1).astype(np.float64),
        (lands & ~present).sum(axis=1).astype(np.float64),
        np.log(members[group].astype(np.float64)),
        group_mean(links.other_share),
        group_mean(landing_share),
        group_mean(links.own_link),
        links.own_link - group_mean(links.own_link),
        pull,
        np.log1p(candidates),
        rivals.astype(np.float64),
        samples / np.maximum(view_samples[group_view], 1.0),
        rival_views.reshape(k, num_views).sum(axis=1)[group],
        own_cover,
        np.where(seen > 0, 1.0 - seen_on_mask / np.maximum(seen, 1.0), 0.0),
        reverse_cover,
        np.where(group_on_mask > 0, hits_in / np.maximum(group_on_mask, 1.0), 1.0),
        group_mean(own_cover),
        group_mean(reverse_cover),
    ], axis=1)


@dataclass(frozen=True)
class SupportTrees:
    """Boosted regression trees on the raw features: each tree's leaf value, summed over the trees,
    adds to the logit.  Node arrays are (T, N), padded per tree; a leaf's children are itself, so
    ``depth`` steps from the root end on every row's leaf."""

    feature: np.ndarray  # (T, N) int: the feature a node splits on
    threshold: np.ndarray  # (T, N): a row goes left where its feature <= threshold
    left: np.ndarray  # (T, N) int
    right: np.ndarray  # (T, N) int
    value: np.ndarray  # (T, N): the leaf's share of the logit (0 elsewhere)
    depth: int

    @classmethod
    def from_json(cls, data: dict) -> "SupportTrees":
        return cls(np.asarray(data["feature"], np.int64), np.asarray(data["threshold"], float),
                   np.asarray(data["left"], np.int64), np.asarray(data["right"], np.int64),
                   np.asarray(data["value"], float), int(data["depth"]))

    def to_json(self) -> dict:
        return {"feature": self.feature.tolist(), "threshold": self.threshold.tolist(), "left": self.left.tolist(),
                "right": self.right.tolist(), "value": self.value.tolist(), "depth": self.depth}

    def __post_init__(self) -> None:
        # Flat tables for the walk: node i of tree t is t * N + i; a node's two children sit at
        # 2 * node (right) and 2 * node + 1 (left), so a row's step is one lookup.
        t, n = self.feature.shape
        first = (np.arange(t) * n)[:, None]
        object.__setattr__(self, "_root", first.ravel().astype(np.intp))
        object.__setattr__(self, "_feature", self.feature.ravel().astype(np.intp))
        object.__setattr__(self, "_threshold", self.threshold.ravel())
        object.__setattr__(self, "_value", self.value.ravel())
        object.__setattr__(self, "_child", np.stack([(self.right + first).ravel(), (self.left + first).ravel()],
                                                     axis=1).ravel().astype(np.intp))

    def logit(self, features: np.ndarray) -> np.ndarray:
        """(S,) the trees' summed leaf values of each row: every tree walked at once, level by level."""
        rows, columns = features.shape
        flat = np.ascontiguousarray(features, dtype=np.float64).ravel()
        row_start = (np.arange(rows) * columns)[:, None]
        node = np.broadcast_to(self._root, (rows, self._root.size))
        for _ in range(self.depth):
            go_left = flat[row_start + self._feature[node]] <= self._threshold[node]
            node = self._child[2 * node + go_left]
        return self._value[node].sum(axis=1)


@dataclass(frozen=True)
class SupportCalibration:
    """A fitted model from :data:`SUPPORT_FEATURES` to P(segment with its own object): the logistic
    of a linear term on the standardised features plus, where fitted, boosted trees' leaf values."""

    features: tuple[str, ...]
    mean: np.ndarray  # (F,) standardisation of each feature
    scale: np.ndarray  # (F,)
    coef: np.ndarray  # (F,) on the standardised features
    intercept: float
    check_below: float  # support under this: "check this segment"
    fitted_on: str  # what the fit saw, for the record
    trees: SupportTrees | None = None  # on the raw features, in this calibration's order

    @classmethod
    def from_json(cls, data: dict) -> "SupportCalibration":
        trees = SupportTrees.from_json(data["trees"]) if data.get("trees") else None
        return cls(tuple(data["features"]), np.asarray(data["mean"], float), np.asarray(data["scale"], float),
                   np.asarray(data["coef"], float), float(data["intercept"]), float(data["check_below"]),
                   str(data.get("fitted_on", "")), trees)

    def to_json(self) -> dict:
        out = {"features": list(self.features), "mean": self.mean.tolist(), "scale": self.scale.tolist(),
               "coef": self.coef.tolist(), "intercept": self.intercept, "check_below": self.check_below,
               "fitted_on": self.fitted_on}
        if self.trees is not None:
            out["trees"] = self.trees.to_json()
        return out

    def probability(self, features: np.ndarray) -> np.ndarray:
        """P(right) of each row of ``features``: (S, len(self.features)) in this calibration's order,
        or (S, len(SUPPORT_FEATURES)) as :func:`support_features` computes them (a calibration
        fitted on some of them picks its columns by name)."""
        if self.features != SUPPORT_FEATURES and features.shape[1] == len(SUPPORT_FEATURES):
            features = features[:, [SUPPORT_FEATURES.index(name) for name in self.features]]
        z = self.intercept + ((features - self.mean) / self.scale) @ self.coef
        if self.trees is not None:
            z = z + self.trees.logit(features)
        return 1.0 / (1.0 + np.exp(-z))


@lru_cache(maxsize=1)
def support_calibration() -> SupportCalibration:
    """The packaged calibration (``shadowcorr/models/support.json``), read once."""
    data = json.loads(resources.files("shadowcorr").joinpath("models/support.json").read_text())
    calibration = SupportCalibration.from_json(data)
    if not set(calibration.features) <= set(SUPPORT_FEATURES):
        raise RuntimeError(f"models/support.json was fitted on features {calibration.features}, "
                           f"this version computes {SUPPORT_FEATURES}: refit it with scripts/fit_support.py")
    return calibration


def segment_support(groups: EvidenceGroups, config: ShadowCorrConfig) -> np.ndarray:
    """(S,) how sure each segment's group is: for ``fused`` the calibrated probability that the
    segment sits with its own object; for ``projection`` the margin's logistic
    (:func:`~shadowcorr.stages.segment_confidence`)."""
    if config.method != "fused":
        return segment_confidence(groups.graph, groups.labels, config)
    features = support_features(groups, config)
    if not len(features):
        return np.zeros(0)
    # The result states a support to 4 decimals, and a fitted probability is never a certainty:
    # beyond 1 in 10,000 the fit (tens of thousands of segments) says nothing, so the support
    # stays within [0.0001, 0.9999] instead of rounding to 0 or 1.
    return np.clip(support_calibration().probability(features), SUPPORT_RESOLUTION, 1.0 - SUPPORT_RESOLUTION)


#: The finest difference of ``fused``'s support from 0 or 1 that the result states.
SUPPORT_RESOLUTION = 1e-4
