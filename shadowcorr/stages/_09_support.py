"""Stage 9, how sure each segment's group is; for ``fused``, the probability that it sits with its own object.

The grouping's evidence margin (its own group's linkage over the best alternative) says how
a segment's place was decided, not how often such a decision is right: under a segmenter's
errors a small eroded piece of a split mask with a clear margin is wrong more often than a
large segment with a thin one.  So the support is a logistic regression on what the evidence
says about the segment (:data:`SUPPORT_FEATURES`): its links to its own group and to the others,
how much evidence they rest on, and what its group as a whole says - a group that is pulled
towards another one as a whole (a rock's split-off piece, seen in several views) or holds
nothing in views where the segment's points land.  It is fitted on generated scenes under single and
combined errors whose truth is known (``scripts/fit_support.py``; the scenes differ from the
quality benchmark's), and shipped as ``models/support.json`` with the threshold below which a
segment is worth checking: the highest that still flags wrong segments with 55 % precision on
the fitted scenes' combined-error runs (``--precision``; the field's scenes are harder than the
fitted ones, and there the flag should keep 50 %).  The features are read from the grouping's
result only: the support never changes a label.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np

from ..config import ShadowCorrConfig
from ._09_grouping import EvidenceGroups, _group_links, _segment_group_linkage, segment_confidence

__all__ = ["SUPPORT_FEATURES", "SupportCalibration", "support_calibration", "support_features", "segment_support"]

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
    ], axis=1)


@dataclass(frozen=True)
class SupportCalibration:
    """A fitted logistic regression from :data:`SUPPORT_FEATURES` to P(segment with its own object)."""

    features: tuple[str, ...]
    mean: np.ndarray  # (F,) standardisation of each feature
    scale: np.ndarray  # (F,)
    coef: np.ndarray  # (F,) on the standardised features
    intercept: float
    check_below: float  # support under this: "check this segment"
    fitted_on: str  # what the fit saw, for the record

    @classmethod
    def from_json(cls, data: dict) -> "SupportCalibration":
        return cls(tuple(data["features"]), np.asarray(data["mean"], float), np.asarray(data["scale"], float),
                   np.asarray(data["coef"], float), float(data["intercept"]), float(data["check_below"]),
                   str(data.get("fitted_on", "")))

    def to_json(self) -> dict:
        return {"features": list(self.features), "mean": self.mean.tolist(), "scale": self.scale.tolist(),
                "coef": self.coef.tolist(), "intercept": self.intercept, "check_below": self.check_below,
                "fitted_on": self.fitted_on}

    def probability(self, features: np.ndarray) -> np.ndarray:
        """P(right) of each row of ``features``: (S, len(self.features)) in this calibration's order,
        or (S, len(SUPPORT_FEATURES)) as :func:`support_features` computes them (a calibration
        fitted on some of them picks its columns by name)."""
        if self.features != SUPPORT_FEATURES and features.shape[1] == len(SUPPORT_FEATURES):
            features = features[:, [SUPPORT_FEATURES.index(name) for name in self.features]]
        z = self.intercept + ((features - self.mean) / self.scale) @ self.coef
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
    return support_calibration().probability(features) if len(features) else np.zeros(0)
