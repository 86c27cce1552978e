"""Scenes whose segments lack valid depth: refused when nearly all do (wrong units), flagged when some do."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from shadowcorr import correspond
from shadowcorr.config import ShadowCorrConfig
from shadowcorr.pipeline import prepare
from shadowcorr.errors import DepthRangeError

from shadowcorr_service.synthetic import synthetic_bundle


def test_centimetre_scene_declared_in_metres_is_refused():
    bundle = synthetic_bundle(n_rocks=3, n_views=3)
    assert bundle.units == "cm"
    with pytest.raises(DepthRangeError) as ei:
        prepare(dataclasses.replace(bundle, units="m"))
    text = str(ei.value)
    assert isinstance(ei.value, ValueError)
    assert "units" in text and "max_depth" in text and "9 of 9 segments" in text, text


def test_some_segments_without_depth_are_flagged():
    bundle = synthetic_bundle(n_rocks=3, n_views=3)
    views = list(bundle.views)
    views[0] = dataclasses.replace(views[0], depth=np.zeros_like(views[0].depth))  # one view lost its depth
    baseline = ShadowCorrConfig(method="meanshift")  # the warning comes from prepare: no network needed
    result = correspond(dataclasses.replace(bundle, views=views), config=baseline, metrics=False)
    assert result.warnings and "3 of 9 segments have no valid depth point" in result.warnings[0], result.warnings
    assert "max_depth" in result.warnings[0]
    clean = correspond(bundle, config=baseline, metrics=False)
    assert not any("no valid depth point" in w for w in clean.warnings)
