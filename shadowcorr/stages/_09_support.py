"""Stage 9, how sure each segment's group is; for ``fused``, the probability that it sits with its own object.

The grouping's evidence margin (its own group's linkage over the best alternative) says how
a segment's place was decided, not how often such a decision is right: under a segmenter's
errors a small eroded piece of a split mask with a clear margin is wrong more often than a
large segment with a thin one.  So the support is a logistic regression on what the evidence
says about the segment (:data:`SUPPORT_FEATURES`), fitted on generated scenes under single and
combined errors whose truth is known (``scripts/fit_support.py``; the scenes differ from the
quality benchmark's), and shipped as ``models/support.json`` with the threshold below which a
segment is worth checking: the highest that still flags wrong segments with 50 % precision on
the fitted scenes (``--precision``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np

from ..config import ShadowCorrConfig
from ._09_grouping import EvidenceGroups, _group_links, segment_confidence

__all__ = ["SUPPORT_FEATURES", "SupportCalibration", "support_calibration", "support_features", "segment_support"]

#: What the calibrated support of ``fused`` reads of a segment (:func:`support_features`).
SUPPORT_FEATURES = (
    "margin",  # its own group's linkage over the best alternative
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
)


def support_features(groups: EvidenceGroups, config: ShadowCorrConfig) -> np.ndarray:
    """(S, len(SUPPORT_FEATURES)) what the evidence says about each segment's place (see SUPPORT_FEATURES)."""
    graph = groups.graph
    if graph.num_segments == 0:
        return np.zeros((0, len(SUPPORT_FEATURES)))
    links = _group_links(graph, groups.labels, config)
    key = graph.view.astype(np.int64) * (int(graph.instance.max(initial=0)) + 1) + graph.instance
    _, mask_of, mask_size = np.unique(key, return_inverse=True, return_counts=True)
    return np.stack([
        links.margin,
        links.own_link,
        np.where(np.isfinite(links.best_other), links.best_other, 0.0),
        links.alone.astype(np.float64),
        links.group_views.astype(np.float64),
        links.own_hits / np.maximum(links.own_trials, 1.0),
        np.log1p(links.own_trials),
        np.log1p(graph.surface.samples.astype(np.float64)),
        groups.merged.astype(np.float64),
        (mask_size[mask_of] > 1).astype(np.float64),
        links.other_share,
        links.other_volume,
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
        z = self.intercept + ((features - self.mean) / self.scale) @ self.coef
        return 1.0 / (1.0 + np.exp(-z))


@lru_cache(maxsize=1)
def support_calibration() -> SupportCalibration:
    """The packaged calibration (``shadowcorr/models/support.json``), read once."""
    data = json.loads(resources.files("shadowcorr").joinpath("models/support.json").read_text())
    calibration = SupportCalibration.from_json(data)
    if calibration.features != SUPPORT_FEATURES:
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
