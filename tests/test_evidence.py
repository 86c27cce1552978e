"""Cross-view surface evidence, the evidence graph and the 'projection' and 'fused' methods."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from pydantic import ValidationError

from shadowcorr import ShadowCorrConfig, correspond, load_model, prepare
from shadowcorr.bundle import SceneBundle
from shadowcorr.stages import (
    Seams, SegmentGraph, SurfaceEvidence, agglomerate, extract_segments, join_isolated, join_nearest_surface,
    link_components, merged_mask_segments, sample_segment_points, segment_confidence, split_mask_ids, surface_evidence,
    thin_cover_pairs, without_landings, without_landings_on,
)

from shadowcorr.stages._09_grouping import (_group_links, _Groups, _initial_heap, _merged_masks,
                                            _segment_group_linkage)

from .scenes import sphere_scene
from .test_engine import FIELD_CENTRES, FIELD_RADII, same_partition

GRAPH_METHODS = ["projection", "fused"]


@pytest.fixture(scope="module")
def model():
    return load_model()


@pytest.fixture(scope="module")
def field():
    return sphere_scene(FIELD_CENTRES, FIELD_RADII, cameras=4, width=480, height_px=270)


def truth_of(result) -> list[int]:
    return [s.instance for s in result.segments]


def test_sampling_spreads_over_each_segment_and_is_deterministic():
    lengths = np.array([10, 3, 0, 7])
    points = np.arange(20, dtype=float)[:, None].repeat(3, axis=1)
    index, drawn = sample_segment_points(points, lengths, 4)
    assert drawn.tolist() == [4, 3, 0, 4]
    seg = np.repeat(np.arange(4), drawn)
    starts = np.cumsum(lengths) - lengths
    assert np.all(index >= starts[seg]) and np.all(index < starts[seg] + lengths[seg])
    assert len(set(index.tolist())) == index.size  # no point drawn twice
    again, _ = sample_segment_points(points, lengths, 4)
    np.testing.assert_array_equal(index, again)


def test_segments_land_on_their_own_sphere_in_neighbouring_views(field):
    config = ShadowCorrConfig(method="projection")
    segments = extract_segments(field, config)
    ev = surface_evidence(field, segments, config)
    s = segments.num_segments
    assert ev.visible.shape == (s, 4)
    # Never projected into the own view.
    assert np.all(ev.visible[np.arange(s), segments.view] == 0)
    assert np.all(ev.on_mask <= ev.visible)
    same = segments.instance[ev.hit_source] == segments.instance[ev.hit_target]
    # Nearly every landing is on the same sphere; the few others are rim pixels.
    assert ev.hit_count[same].sum() > 0.97 * ev.hit_count.sum()
    # Landings are counted once per target view: per (source, view) they add up to on_mask.
    per_view = np.zeros_like(ev.on_mask)
    np.add.at(per_view, (ev.hit_source, segments.view[ev.hit_target]), ev.hit_count)
    np.testing.assert_array_equal(per_view, ev.on_mask)


def test_hidden_points_are_not_visible():
    # Two cameras 180 degrees apart see opposite sides of one sphere: nothing of one side is
    # visible from the other (it lies behind the nearer surface), so there is no evidence.
    bundle = sphere_scene([[0, 0, 0]], [60], cameras=2, height=0.0)
    config = ShadowCorrConfig(method="projection")
    ev = surface_evidence(bundle, extract_segments(bundle, config), config)
    assert ev.visible.sum() < 0.02 * ev.samples.sum()


@pytest.mark.parametrize("method", GRAPH_METHODS)
def test_graph_methods_find_the_spheres(field, model, method):
    result = correspond(field, model, ShadowCorrConfig(method=method))
    assert result.method == method
    assert same_partition(result.labels, truth_of(result)), (result.labels, truth_of(result))
    assert {s.assignment for s in result.segments} == {"evidence"}
    # Every segment sits with its own sphere, with evidence on all sides: each is sure of it
    # (fused's flag of doubtful segments, support below check_below, flags none).
    assert min(s.support for s in result.segments) > 0.9, [s.support for s in result.segments]
    assert "grouping" in result.timings_ms and "surface_evidence" in result.timings_ms
    assert (result.model is not None) == (method == "fused")


def test_fused_joins_opposite_views_that_share_no_surface(model):
    bundle = sphere_scene(FIELD_CENTRES, FIELD_RADII, cameras=2, width=480, height_px=270)
    result = correspond(bundle, model, ShadowCorrConfig(method="fused"))
    assert same_partition(result.labels, truth_of(result)), (result.labels, truth_of(result))


@pytest.mark.parametrize("method", GRAPH_METHODS)
def test_mask_ids_are_never_read_across_views(field, model, method):
    """Renumber every view's mask ids and carry the truth in `mapped`: the partition must not change."""
    rng = np.random.default_rng(5)
    views = []
    for v in field.views:
        ids = np.unique(v.mask[v.mask > 0])
        new = rng.permutation(np.arange(100, 100 + ids.size))
        table = np.zeros(int(v.mask.max()) + 1, dtype=np.int32)
        table[ids] = new
        views.append(replace(v, mask=table[v.mask], instance_objects={int(n): int(o) for n, o in zip(new, ids)}))
    relabelled = SceneBundle(units=field.units, views=views, name="relabelled", ground_truth="mapped")
    config = ShadowCorrConfig(method=method)
    a, b = correspond(field, model, config), correspond(relabelled, model, config)
    key = lambda r: [(s.view, s.num_points) for s in r.segments]  # noqa: E731
    order_b = {k: i for i, k in enumerate(key(b))}
    perm = [order_b[k] for k in key(a)]
    assert same_partition(a.labels, [b.labels[i] for i in perm])
    assert b.metrics["average_purity"] == a.metrics["average_purity"] == 100.0


def _graph(view, instance, on_mask, hits, volume=()):
    src, dst, count = (np.array(x, dtype=np.int64) for x in zip(*hits)) if hits else (np.zeros(0, np.int64),) * 3
    s = len(view)
    surface = SurfaceEvidence(np.full(s, 100), np.zeros((100 * s, 3), np.float32), np.array(on_mask), np.array(on_mask),
                              src, dst, count)
    va, vb, value, mass = (np.array(x) for x in zip(*volume)) if volume else (np.zeros(0, np.int64),) * 2 + (np.zeros(0),) * 2
    return SegmentGraph(np.array(view), np.array(instance), surface, va.astype(np.int64), vb.astype(np.int64),
                        value.astype(float), mass.astype(float))


def test_one_merged_mask_does_not_chain_two_objects():
    # Views 0, 1, 2.  Rocks P and Q: view 0 sees them apart (segments 0, 1), view 1 has one
    # merged mask over both (segment 2), view 2 sees them apart (segments 3, 4).
    view = [0, 0, 1, 2, 2]
    instance = [1, 2, 1, 1, 2]
    n = 100
    on_mask = [[0, n, n], [0, n, n], [2 * n, 0, 2 * n], [n, n, 0], [n, n, 0]]
    hits = [(0, 2, n), (0, 3, n), (1, 2, n), (1, 4, n), (2, 0, n), (2, 1, n), (2, 3, n), (2, 4, n),
            (3, 0, n), (3, 2, n), (4, 1, n), (4, 2, n)]
    graph = _graph(view, instance, on_mask, hits)
    config = ShadowCorrConfig(method="fused")
    labels = agglomerate(graph, config)
    assert labels[0] == labels[3] and labels[1] == labels[4] and labels[0] != labels[1]
    # The training-free check links everything through the merged mask.
    assert len(set(link_components(graph.surface, graph.view, config).tolist())) == 1
    confidence = segment_confidence(graph, labels, config)
    assert confidence[2] < min(confidence[[0, 1, 3, 4]])  # the merged mask is the doubtful one


def test_a_split_mask_is_joined_when_the_evidence_agrees():
    # One rock: view 0 split into two ids (segments 0, 1), views 1 and 2 see it whole (2, 3).
    view = [0, 0, 1, 2]
    instance = [1, 2, 1, 1]
    n = 100
    on_mask = [[0, n, n], [0, n, n], [2 * n, 0, 2 * n], [2 * n, 2 * n, 0]]
    hits = [(0, 2, n), (0, 3, n), (1, 2, n), (1, 3, n), (2, 0, n), (2, 1, n), (2, 3, 2 * n),
            (3, 0, n), (3, 1, n), (3, 2, 2 * n)]
    config = ShadowCorrConfig(method="fused")
    labels = agglomerate(_graph(view, instance, on_mask, hits), config)
    assert len(set(labels.tolist())) == 1
    # Against a stricter reading of the mask ids the surface evidence alone is not enough ...
    strict = config.with_options(fusion_cannot_link=0.9)
    apart = agglomerate(_graph(view, instance, on_mask, hits), strict)
    assert apart[0] != apart[1] and len(set(apart.tolist())) == 2
    # ... until the network's shadows meeting inside the rock tip it.
    volume = [(a, b, 0.6, 1.0) for a in (0, 1) for b in (2, 3)]
    joined = agglomerate(_graph(view, instance, on_mask, hits, volume), strict)
    assert len(set(joined.tolist())) == 1


def _co_landing_pair(n: int = 100):
    """Segments 0 and 1 (view 0, ids 1 and 2) both land on segment 2 (view 1) and 3 (view 2), which
    land back on each: the halves of one cut rock, or two rocks merged in views 1 and 2."""
    view, instance = np.array([0, 0, 1, 2]), np.array([1, 2, 1, 1])
    on_mask = [[0, n, n], [0, n, n], [2 * n, 0, 2 * n], [2 * n, 2 * n, 0]]
    hits = [(0, 2, n), (0, 3, n), (1, 2, n), (1, 3, n), (2, 0, n), (2, 1, n), (2, 3, 2 * n),
            (3, 0, n), (3, 1, n), (3, 2, 2 * n)]
    return view, instance, on_mask, hits


def test_halves_that_co_land_in_two_views_count_as_one_mask_and_a_merge_in_one_view_does_not():
    n = 100
    config = ShadowCorrConfig(method="fused")
    # Split: the co-landing pair, seen whole in views 1 and 2.
    view, instance, on_mask, hits = _co_landing_pair(n)
    graph = _graph(view, instance, on_mask, hits)
    ids, loose = split_mask_ids(graph.surface, view, instance, config)
    assert ids[0] == ids[1] and ids.tolist()[2:] == [1, 1] and loose.tolist() == ids.tolist()
    # Read as one mask, the halves join even under a strict cannot-link weight.
    strict = config.with_options(fusion_cannot_link=0.9)
    joined = agglomerate(_graph(view, ids, on_mask, hits), strict)
    assert len(set(joined.tolist())) == 1
    # Two views are asked for: with the threshold at three the halves keep their ids.
    assert split_mask_ids(graph.surface, view, instance, config.with_options(fusion_split_views=3))[0].tolist() == [1, 2, 1, 1]

    # A rock b half hidden behind its neighbour a: b's points pass for visible on a's segments,
    # but a's segments, seen from view 0, land on a alone - no split.
    hidden = [h for h in hits if h[:2] not in ((2, 1), (3, 1))]
    hidden_surface = _graph(view, instance, on_mask, hidden).surface
    assert split_mask_ids(hidden_surface, view, instance, config)[0].tolist() == [1, 2, 1, 1]

    # Merge: rocks P, Q apart in views 0 and 2, one merged mask in view 1 - they co-land in view 1 only.
    view, instance = np.array([0, 0, 1, 2, 2]), np.array([1, 2, 1, 1, 2])
    on_mask = [[0, n, n], [0, n, n], [2 * n, 0, 2 * n], [n, n, 0], [n, n, 0]]
    hits = [(0, 2, n), (0, 3, n), (1, 2, n), (1, 4, n), (2, 0, n), (2, 1, n), (2, 3, n), (2, 4, n),
            (3, 0, n), (3, 2, n), (4, 1, n), (4, 2, n)]
    graph = _graph(view, instance, on_mask, hits)
    assert split_mask_ids(graph.surface, view, instance, config)[0].tolist() == instance.tolist()


def test_masks_that_co_land_but_meet_across_a_depth_step_keep_their_ids():
    """Rocks P and Q touch; views 1 and 2 each drew one mask over both, so P's and Q's masks in
    view 0 co-land in two views, as the halves of one cut rock would.  Their seam in view 0 is
    an occlusion step (an apart pair): they keep their ids, and without the veto they would not."""
    config = ShadowCorrConfig(method="fused")
    view, instance, on_mask, hits = _co_landing_pair()
    surface = _graph(view, instance, on_mask, hits).surface
    none = np.zeros(0, dtype=np.int64)
    stepped = replace(surface, seams=Seams(none, none, none, np.zeros(0), np.zeros(0), none, none,
                                           np.array([0]), np.array([1])))
    ids, loose = split_mask_ids(stepped, view, instance, config)
    assert ids.tolist() == [1, 2, 1, 1] and loose.tolist() == [1, 2, 1, 1]
    assert split_mask_ids(surface, view, instance, config)[0].tolist() == [1, 1, 1, 1]
    # The step vetoes only its own pair: another pair of the view still co-lands.
    other = replace(stepped, seams=replace(stepped.seams, apart_first=np.array([2]), apart_second=np.array([3])))
    assert split_mask_ids(other, view, instance, config)[0].tolist() == [1, 1, 1, 1]


def _merge_scene(n: int = 100):
    """Rocks P and Q apart in views 0 and 2 (segments 0, 1 and 3, 4), one merged mask over both in view 1 (2)."""
    view, instance = np.array([0, 0, 1, 2, 2]), np.array([1, 2, 1, 1, 2])
    on_mask = [[0, n, n], [0, n, n], [2 * n, 0, 2 * n], [n, n, 0], [n, n, 0]]
    hits = [(0, 2, n), (0, 3, n), (1, 2, n), (1, 4, n), (2, 0, n), (2, 1, n), (2, 3, n), (2, 4, n),
            (3, 0, n), (3, 2, n), (4, 1, n), (4, 2, n)]
    return view, instance, _graph(view, instance, on_mask, hits).surface


def test_a_merged_mask_is_found_where_a_third_view_sees_its_objects_apart():
    view, instance, surface = _merge_scene()
    config = ShadowCorrConfig(method="fused")
    assert merged_mask_segments(surface, view, instance, config).tolist() == [False, False, True, False, False]
    assert not merged_mask_segments(surface, view, instance, config.with_options(fusion_merge_share=0)).any()
    # A segment that only grazes the second object (a tenth of its landings) is no merged mask.
    grazing = surface.hit_count.copy()
    grazing[(surface.hit_source == 2) & np.isin(surface.hit_target, [1, 4])] = 20
    on_mask = surface.on_mask.copy()
    on_mask[2] = [120, 0, 120]
    grazed = replace(surface, on_mask=on_mask, hit_count=grazing)
    assert not merged_mask_segments(grazed, view, instance, config).any()
    # Without view 2 nothing tells the two segments of view 0 apart: one rock that view 0 cut in two
    # would look the same, so nothing is flagged.
    seen = ~np.isin(surface.hit_source, [3, 4]) & ~np.isin(surface.hit_target, [3, 4])
    two_views = replace(surface, on_mask=surface.on_mask.copy(), hit_source=surface.hit_source[seen],
                        hit_target=surface.hit_target[seen], hit_count=surface.hit_count[seen])
    two_views.on_mask[:, 2] = 0
    assert not merged_mask_segments(two_views, view, instance, config).any()
    # Unless view 0 itself tells them apart: their seam there is a depth step (one in front of the other).
    none = np.zeros(0, dtype=np.int64)
    stepped = replace(two_views, seams=Seams(none, none, none, np.zeros(0), np.zeros(0), none, none,
                                             np.array([1]), np.array([0])))
    assert merged_mask_segments(stepped, view, instance, config).tolist() == [False, False, True, False, False]
    # Which masks only a depth step told apart (their rock is then read along the rays: join_nearest_surface).
    assert _merged_masks(stepped, view, instance, config)[1].tolist() == [False, False, True, False, False]
    assert not _merged_masks(surface, view, instance, config)[1].any()
    # Or the two segments do not even touch in view 0, where its masks were read: a cut leaves the
    # halves of one rock side by side.  Touching, or in a view whose masks were not read, nothing.
    apart = replace(two_views, seams=Seams(none, none, none, np.zeros(0), np.zeros(0), views_read=np.array([0])))
    assert _merged_masks(apart, view, instance, config)[1].tolist() == [False, False, True, False, False]
    touching = replace(apart, seams=replace(apart.seams, touching_first=np.array([0]), touching_second=np.array([1])))
    assert not merged_mask_segments(touching, view, instance, config).any()
    elsewhere = replace(apart, seams=replace(apart.seams, views_read=np.array([1, 2])))
    assert not merged_mask_segments(elsewhere, view, instance, config).any()


def test_a_merged_mask_that_sees_little_of_the_other_view_is_found_from_the_segments_under_it():
    """Two opposite views share only the rocks' rims: merged mask 2 of view 1 lands 60 points in
    view 0 and none elsewhere, all on segment 0, so its spread there names one segment.  Segments 0 and 1 of view 0
    both land mostly on it, and they do not touch in view 0: a merged mask all the same."""
    none = np.zeros(0, dtype=np.int64)
    view, instance = np.array([0, 0, 1]), np.array([1, 2, 1])
    n, few = 100, 60
    surface = _graph(view, instance, [[0, n], [0, n], [few, 0]], [(0, 2, n), (1, 2, n), (2, 0, few)]).surface
    apart = replace(surface, seams=Seams(none, none, none, np.zeros(0), np.zeros(0), views_read=np.array([0])))
    config = ShadowCorrConfig(method="fused")
    assert merged_mask_segments(apart, view, instance, config).tolist() == [False, False, True]
    # Where the mask lands often enough in view 0 (150 points and more), its own spread is read:
    # all of it on segment 0, so segment 1 is another rock's, seen through the rim.
    many = replace(apart, on_mask=np.array([[0, n], [0, n], [200, 0]]), hit_count=np.array([n, n, 200]))
    assert not merged_mask_segments(many, view, instance, config).any()
    # So it is where the mask lands often in any other view: a third view reads how it spreads.
    view3, instance3 = np.array([0, 0, 1, 2]), np.array([1, 2, 1, 1])
    seen_by_third = _graph(view3, instance3, [[0, n, 0], [0, n, 0], [few, 0, 200], [0, 0, 0]],
                           [(0, 2, n), (1, 2, n), (2, 0, few), (2, 3, 200)]).surface
    seen_by_third = replace(seen_by_third, seams=apart.seams)
    assert not merged_mask_segments(seen_by_third, view3, instance3, config).any()
    # A segment under the mask that also lands mostly on a segment of a third view is not taken
    # from the mask's side: its own landings there say which rock it is.
    view, instance = np.array([0, 0, 1, 2]), np.array([1, 2, 1, 1])
    surface = _graph(view, instance, [[0, n, n], [0, n, 0], [5, 0, 0], [n, 0, 0]],
                     [(0, 2, n), (0, 3, n), (1, 2, n), (2, 0, 5), (3, 0, n)]).surface
    third = replace(surface, seams=Seams(none, none, none, np.zeros(0), np.zeros(0), views_read=np.array([0])))
    assert not merged_mask_segments(third, view, instance, config).any()
    without_third = replace(third, on_mask=third.on_mask * (np.arange(3) < 2), hit_source=third.hit_source[[0, 2, 3]],
                            hit_target=third.hit_target[[0, 2, 3]], hit_count=third.hit_count[[0, 2, 3]])
    assert merged_mask_segments(without_third, view, instance, config).tolist() == [False, False, True, False]


def test_a_small_rock_under_a_mask_mostly_over_its_neighbour_gives_up_its_landings_there():
    """Mask 2 of view 1 is mostly over rock P and also over a small rock Q: Q's segments take 40 of
    its 200 landings in views 0 and 2 (20 %, under fusion_merge_share), P's the rest; both land
    mostly on it, and each of views 0 and 2 sees P and Q apart, so Q's landings on the mask are
    no evidence, while the mask is no merged mask (it stays with P)."""
    view, instance = np.array([0, 0, 1, 2, 2]), np.array([1, 2, 1, 1, 2])
    n = 100

    def scene(small: int, total: int = 200):
        on_mask = [[0, n, n], [0, n, n], [total, 0, total], [n, n, 0], [n, n, 0]]
        hits = [(0, 2, n), (0, 3, n), (1, 2, n), (1, 4, n), (2, 0, total - small), (2, 1, small),
                (2, 3, total - small), (2, 4, small), (3, 0, n), (3, 2, n), (4, 1, n), (4, 2, n)]
        surface = _graph(view, instance, on_mask, hits).surface
        # P and Q do not touch in views 0 and 2, whose masks were read: two objects for those views too.
        none = np.zeros(0, dtype=np.int64)
        return replace(surface, seams=Seams(none, none, none, np.zeros(0), np.zeros(0), views_read=np.array([0, 2])))

    config = ShadowCorrConfig(method="fused")
    surface = scene(40)
    touching = replace(surface, seams=replace(surface.seams, touching_first=np.array([0, 3]),
                                              touching_second=np.array([1, 4])))
    # Touching on one surface in their own views, they could be a rock that views 0 and 2 both cut.
    assert thin_cover_pairs(touching, view, instance, config)[0].size == 0
    assert not merged_mask_segments(surface, view, instance, config).any()
    small, under = thin_cover_pairs(surface, view, instance, config)
    assert sorted(zip(small.tolist(), under.tolist())) == [(1, 2), (4, 2)]
    # With a quarter of the landings each, the mask is a merged mask, and all its landings go.
    assert merged_mask_segments(scene(50), view, instance, config).tolist() == [False, False, True, False, False]
    assert thin_cover_pairs(scene(50), view, instance, config)[0].size == 0
    # Under 15 % of them (40 of 300), Q's landings stay evidence.
    assert thin_cover_pairs(scene(40, total=300), view, instance, config)[0].size == 0
    # Without the third view nothing tells the small rock from a piece of P that view 0 cut off.
    seen = ~np.isin(surface.hit_source, [3, 4]) & ~np.isin(surface.hit_target, [3, 4])
    two_views = replace(surface, on_mask=surface.on_mask * (np.arange(3) < 2), hit_source=surface.hit_source[seen],
                        hit_target=surface.hit_target[seen], hit_count=surface.hit_count[seen])
    assert thin_cover_pairs(two_views, view, instance, config)[0].size == 0
    # The landings taken out: Q's on the mask, hits and trials; the mask's own and P's stay.
    gone = np.isin(surface.hit_source * 5 + surface.hit_target, small * 5 + under)
    out = without_landings(surface, view, gone)
    assert [(a, t) for a, t in zip(out.hit_source.tolist(), out.hit_target.tolist()) if t == 2] == [(0, 2), (3, 2)]
    assert out.on_mask[1].tolist() == [0, 0, n] and out.on_mask[4].tolist() == [n, 0, 0]
    assert out.on_mask[0].tolist() == surface.on_mask[0].tolist()


def test_merge_share_is_validated():
    assert ShadowCorrConfig(fusion_merge_share=0).fusion_merge_share == 0
    for bad in (-0.1, 0.6):  # two segments cannot each take more than half of the landings
        with pytest.raises(ValidationError, match="fusion_merge_share"):
            ShadowCorrConfig(fusion_merge_share=bad)


def test_a_rock_split_in_one_view_is_not_a_merged_mask():
    # One rock: view 0 cut it in two (segments 0, 1); views 1 and 2 see it whole (2, 3) and the
    # halves land together on it in both.
    view, instance = np.array([0, 0, 1, 2]), np.array([1, 2, 1, 1])
    n = 100
    on_mask = [[0, n, n], [0, n, n], [2 * n, 0, 2 * n], [2 * n, 2 * n, 0]]
    hits = [(0, 2, n), (0, 3, n), (1, 2, n), (1, 3, n), (2, 0, n), (2, 1, n), (2, 3, 2 * n),
            (3, 0, n), (3, 1, n), (3, 2, 2 * n)]
    surface = _graph(view, instance, on_mask, hits).surface
    assert not merged_mask_segments(surface, view, instance, ShadowCorrConfig(method="fused")).any()


def test_landings_on_a_merged_mask_are_taken_out_hits_and_trials():
    view, instance, surface = _merge_scene()
    out = without_landings_on(surface, view, np.array([False, False, True, False, False]))
    assert 2 not in out.hit_target.tolist()
    # Its own landings stay, and so does everything between the other segments.
    assert sorted(zip(out.hit_source.tolist(), out.hit_target.tolist())) == [
        (0, 3), (1, 4), (2, 0), (2, 1), (2, 3), (2, 4), (3, 0), (4, 1)]
    # The points that landed on it no longer count as landing on a mask in its view.
    assert out.on_mask[:, 1].tolist() == [0, 0, 0, 0, 0] and out.on_mask[2].tolist() == [200, 0, 200]
    assert out.on_mask[0].tolist() == [0, 0, 100] and surface.on_mask[0].tolist() == [0, 100, 100]  # input kept
    assert without_landings_on(surface, view, np.zeros(5, dtype=bool)) is surface


def test_a_merged_mask_does_not_chain_a_rock_that_lands_mostly_on_it():
    # Rock P in views 0 and 2 (segments 0, 1), rock Q in views 0 and 2 (2, 3), one mask over both in
    # view 1 (4), mostly P.  Q's two views share little surface (25 points), but most of Q lands on
    # the merged mask: read as evidence, those landings chain Q to P through it.
    view, instance = np.array([0, 2, 0, 2, 1]), np.array([1, 1, 2, 2, 1])
    hits = [(0, 1, 100), (1, 0, 100), (0, 4, 100), (1, 4, 100),
            (2, 3, 25), (3, 2, 25), (2, 4, 300), (3, 4, 300),
            (4, 0, 100), (4, 1, 100), (4, 2, 40), (4, 3, 40)]
    on_mask = np.zeros((5, 3), dtype=np.int64)
    for a, b, h in hits:
        on_mask[a, view[b]] += h
    surface = _graph(view, instance, on_mask, hits).surface
    config = ShadowCorrConfig(method="fused")
    chained = agglomerate(_graph(view, instance, on_mask, hits), config)
    assert len(set(chained.tolist())) == 1
    merged = merged_mask_segments(surface, view, instance, config)
    assert merged.tolist() == [False, False, False, False, True]
    none = np.zeros(0, dtype=np.int64)
    graph = SegmentGraph(view, instance, without_landings_on(surface, view, merged), none, none, np.zeros(0), np.zeros(0))
    labels = agglomerate(graph, config)
    assert labels[0] == labels[1] == labels[4] and labels[2] == labels[3] and labels[0] != labels[2]


def _random_graph(seed: int, s: int = 40, unsure: bool = False, moved: bool = False) -> SegmentGraph:
    """Random evidence among ``s`` segments of 4 views; some pairs share a view and a mask id; with
    ``unsure``, mask ids 1 and 2, and 3 and 4, of a view share a loose id (their seams decide nothing);
    with ``moved`` as well, a quarter of the segments take a random loose id of their own, as one
    blob of a mask does through its own unsure seam."""
    rng = np.random.default_rng(seed)
    view, instance = rng.integers(0, 4, s), rng.integers(1, 6, s)
    on_mask = rng.integers(0, 300, (s, 4)) * (view[:, None] != np.arange(4))
    hits = [(a, b, int(rng.integers(1, 200))) for a, b in rng.integers(0, s, (3 * s, 2)) if view[a] != view[b]]
    hits = list({(a, b): (a, b, h) for a, b, h in hits}.values())  # one row per directed pair
    volume = [(a, b, float(rng.uniform(-1, 1)), float(rng.uniform(0, 2)))
              for a, b in {(min(a, b), max(a, b)) for a, b in rng.integers(0, s, (2 * s, 2)) if a != b}]
    graph = _graph(view.tolist(), instance.tolist(), on_mask, hits, volume)
    if not unsure:
        return graph
    loose = (instance + 1) // 2
    if moved:
        loose = np.where(rng.random(s) < 0.25, rng.integers(1, 4, s), loose)
    return replace(graph, loose=loose)


@pytest.mark.parametrize("unsure, moved", [(False, False), (True, False), (True, True)])
def test_the_first_linkages_computed_at_once_equal_those_of_the_merge_loop(unsure, moved):
    s = 40
    graph = _random_graph(3, s, unsure, moved)
    config = ShadowCorrConfig(method="fused")
    groups = _Groups(graph, config)
    heap = _initial_heap(graph, config)
    expected = {(g, h): groups.linkage(g, h) for g in range(s) for h in groups.edges[g] if g < h}
    assert len(heap) == len(expected) > 100
    for negated, g, h, _, _ in heap:
        assert -negated == expected[(g, h)]  # bit for bit: the merge order depends on it


def _scalar_links(graph: SegmentGraph, labels: np.ndarray, x: int, config: ShadowCorrConfig) -> dict[int, float]:
    """The merge loop's linkage of segment ``x`` alone to every group it has an edge with, keyed
    by group label, from groups built by the merge loop itself; and to the rest of its own group
    (with or without an edge: the constraints of their shared view count either way)."""
    groups = _Groups(graph, config)
    root = {}
    for seg in range(graph.num_segments):
        if seg == x:
            continue
        label = int(labels[seg])
        root[label] = groups.merge(root[label], seg) if label in root else seg
    if int(labels[x]) in root:
        groups._edge(x, root[int(labels[x])])  # no evidence: zero counts
    label_of = {r: label for label, r in root.items()}
    return {label_of[other]: groups.linkage(x, other) for other in groups.edges[x]}


@pytest.mark.parametrize("seed, unsure, moved", [(3, False, False), (4, False, False), (4, True, False),
                                                 (4, True, True)])
def test_the_confidence_summarises_the_linkage_of_the_merge_loop(seed, unsure, moved):
    # Random groups of random evidence: per segment, the vectorised linkage to its own group and
    # to the best other one equals the merge loop's, and the confidence is their logistic margin.
    s = 40
    graph = _random_graph(seed, s, unsure, moved)
    config = ShadowCorrConfig(method="fused")
    labels = np.random.default_rng(seed).integers(0, 9, s)
    labels[:3] = 20 + np.arange(3)  # three segments alone
    links = _group_links(graph, labels, config)
    confidence = segment_confidence(graph, labels, config)
    checked_other = 0
    for x in range(s):
        scalar = _scalar_links(graph, labels, x, config)
        own = scalar.pop(int(labels[x]), 0.0)
        best = max(scalar.values(), default=-np.inf)
        assert links.own_link[x] == pytest.approx(own, rel=1e-12, abs=1e-12)
        assert links.best_other[x] == pytest.approx(best, rel=1e-12, abs=1e-12)
        checked_other += bool(scalar)
        alone = int((labels == labels[x]).sum()) == 1
        margin = (-best if np.isfinite(best) else 0.0) if alone else own - max(best, 0.0)
        expected = 1.0 / (1.0 + np.exp(-config.fusion_confidence_slope * margin))
        assert confidence[x] == pytest.approx(expected, rel=1e-12)
    assert checked_other > s // 2


def test_volumetric_evidence_alone_joins_and_separates():
    # No surface evidence at all (opposite views): the network's evidence decides.
    view, instance = [0, 1, 0, 1], [1, 1, 2, 2]
    volume = [(0, 1, 0.9, 1.0), (2, 3, 0.8, 1.0), (0, 3, -0.9, 1.0), (1, 2, -0.7, 1.0)]
    graph = _graph(view, instance, np.zeros((4, 2), int), [], volume)
    labels = agglomerate(graph, ShadowCorrConfig(method="fused"))
    assert labels[0] == labels[1] and labels[2] == labels[3] and labels[0] != labels[2]


def test_surface_evidence_is_computed_only_for_graph_methods(field):
    assert prepare(field, ShadowCorrConfig(method="shadowcorr")).surface is None
    scene = prepare(field, ShadowCorrConfig(method="projection"))
    assert scene.surface is not None and scene.num_voxels == 0  # no shadows are cast


def test_a_merged_mask_joins_the_group_that_owns_most_of_its_surface():
    # View 0 sees rocks P (segment 0, x < 0) and Q (segment 1, x > 0) apart; segment 2 (view 1)
    # is a mask over both, 70 of its points on P's surface and 30 on Q's; segment 3 (view 1)
    # is another merged mask, whose points must not vote.  The agglomeration left 2 with Q.
    rng = np.random.default_rng(0)
    p_surface = np.c_[rng.uniform(-50, -1, (100, 2)), np.zeros(100)]
    q_surface = np.c_[rng.uniform(1, 50, (100, 2)), np.zeros(100)]
    on_p = p_surface[:70] + [0.5, 0.5, 0.5]
    on_q = q_surface[:30] + [0.5, 0.5, 0.5]
    points = np.concatenate([p_surface, q_surface, on_p, on_q, q_surface + 0.1]).astype(np.float32)
    samples = np.array([100, 100, 100, 100])
    none = np.zeros(0, np.int64)
    surface = SurfaceEvidence(samples, points, np.zeros((4, 2), np.int64), np.zeros((4, 2), np.int64), none, none,
                              none)
    view = np.array([0, 0, 1, 1])
    merged = np.array([False, False, True, True])
    config = ShadowCorrConfig(method="fused")
    labels = np.array([0, 1, 1, 3])
    joined = join_nearest_surface(labels, surface, view, merged, config)
    assert joined.tolist() == [0, 1, 0, 1]  # 2 to P (70 of 100 votes); 3 lies on Q's surface
    # Too few votes (points farther than the tolerance do not vote), or no majority: no move.
    far = config.with_options(fusion_merge_reach=0.1)
    assert join_nearest_surface(labels, surface, view, merged, far).tolist() == [0, 1, 1, 3]
    split = surface.points.copy()
    split[200:300] = np.concatenate([on_p[:50], on_q[:30], on_q[:20]])
    even = replace(surface, points=split)
    assert join_nearest_surface(labels, even, view, merged, config).tolist() == [0, 1, 1, 1]
    assert join_nearest_surface(labels, surface, view, np.zeros(4, bool), config) is labels


def _two_segments_and_a_merged_mask(points: np.ndarray, samples: list[int], labels: tuple[int, ...] = (0, 1, 1)):
    """Surface evidence of segments 0 and 1 of view 0 and the merged mask 2 of view 1 (their
    sample points, in that order, and nothing else), the views, the merged flags and the labels."""
    none = np.zeros(0, np.int64)
    surface = SurfaceEvidence(np.array(samples), points.astype(np.float32), np.zeros((3, 2), np.int64),
                              np.zeros((3, 2), np.int64), none, none, none)
    return surface, np.array([0, 0, 1]), np.array([False, False, True]), np.array(labels)


def test_a_merged_mask_counts_the_other_views_surface_not_their_samples():
    """A large segment's fixed number of sample points lie far apart, a small one's close together:
    counted on samples, the merged mask's points find the small segment's surface more often and
    the vote goes to the wrong rock.  The shells (one point per 2 cm cell of surface) count every
    part alike."""
    rng = np.random.default_rng(1)
    # View 0: rock P, a large flat segment (x < 0, 2,450 cm^2), and rock Q, a small one (x > 0, 81 cm^2).
    p_grid = np.stack(np.meshgrid(np.arange(-49.0, -0.5, 2.0), np.arange(0.0, 50.0, 2.0)), -1).reshape(-1, 2)
    q_grid = np.stack(np.meshgrid(np.arange(1.0, 10.0, 2.0), np.arange(0.0, 9.5, 2.0)), -1).reshape(-1, 2)
    p_shell, q_shell = np.c_[p_grid, np.zeros(len(p_grid))], np.c_[q_grid, np.zeros(len(q_grid))]
    p_samples = p_shell[rng.choice(len(p_shell), 30, replace=False)]  # 30 samples over P: far apart
    q_samples = np.c_[rng.uniform(1, 10, (100, 2)), np.zeros(100)]  # 100 over Q: close together
    # View 1: a mask over both, 60 of its points on P and 40 on Q.
    m_points = np.concatenate([np.c_[rng.uniform(-49, -1, 60), rng.uniform(0, 48, 60), np.zeros(60)],
                               np.c_[rng.uniform(1, 9, (40, 2)), np.zeros(40)]])
    surface, view, merged, labels = _two_segments_and_a_merged_mask(
        np.concatenate([p_samples, q_samples, m_points]), [30, 100, 100], labels=(0, 1, 2))
    # Only points the other view sees vote, each for itself: a depth tolerance no point meets leaves
    # the vote to the reach (see the next tests for what the tolerance does).
    config = ShadowCorrConfig(method="fused", fusion_merge_reach=3.0, projection_depth_tolerance=0.01)
    shells = np.concatenate([p_shell, q_shell, m_points]).astype(np.float32)
    shell_count = np.array([len(p_shell), len(q_shell), len(m_points)])
    assert join_nearest_surface(labels, surface, view, merged, config, shells, shell_count).tolist() == [0, 1, 0]
    assert join_nearest_surface(labels, surface, view, merged, config).tolist() == [0, 1, 1]  # on samples: Q


def test_a_merged_mask_joins_the_rock_under_most_of_it_where_other_views_see_little_of_it():
    """View 0 sees only the top strip of rock P (z 40..50 cm) and all of Q; the merged mask of view 1
    has 70 points on P below that strip (up to 12 cm beneath it) and 30 on Q.  Within the depth
    tolerance only the points on Q find a surface; within ``fusion_merge_reach`` P's points find P's."""
    rng = np.random.default_rng(2)
    p_seen = np.c_[np.zeros(200), rng.uniform(0, 40, 200), rng.uniform(40, 50, 200)]  # the plane x = 0
    q_seen = np.c_[np.zeros(200), rng.uniform(60, 100, 200), rng.uniform(0, 50, 200)]
    on_p = np.c_[np.zeros(70), rng.uniform(0, 40, 70), rng.uniform(28, 38, 70)]
    on_q = q_seen[:30] + [0.5, 0.0, 0.0]
    surface, view, merged, labels = _two_segments_and_a_merged_mask(np.concatenate([p_seen, q_seen, on_p, on_q]),
                                                                    [200, 200, 100])
    config = ShadowCorrConfig(method="fused")
    assert join_nearest_surface(labels, surface, view, merged, config).tolist() == [0, 1, 0]
    # Reaching only as far as the depth tolerance, P's points below the strip still follow the
    # mask's points that view 0 sees just beneath it.
    tolerance = config.with_options(fusion_merge_reach=config.projection_depth_tolerance)
    assert join_nearest_surface(labels, surface, view, merged, tolerance).tolist() == [0, 1, 0]
    # Without them (nothing seen within a tolerance no point meets), only Q's points find a surface.
    blind = tolerance.with_options(projection_depth_tolerance=0.01)
    assert join_nearest_surface(labels, surface, view, merged, blind).tolist() == [0, 1, 1]


def test_a_merged_masks_points_no_other_view_sees_follow_the_masks_nearest_seen_points():
    """Rock Q's side faces rock P (the wall x = 5 cm, seen by view 0, hidden from view 1).  View 1's
    merged mask has 60 points on P's top (x -30..0 cm) and 40 on Q's top, which lies further back
    (x 20..40); view 0 sees only P's far strip (x < -24).  Within ``fusion_merge_reach`` the P points
    near the wall find Q's side first, and a vote of each point for its nearest surface gives the
    mask to Q; following the mask's own points that view 0 sees (P's strip, Q's top), it goes to P."""
    rng = np.random.default_rng(3)
    p_strip = np.c_[rng.uniform(-30, -24, 200), rng.uniform(0, 20, 200), np.zeros(200)]
    q_side = np.c_[np.full(200, 5.0), rng.uniform(0, 20, 200), rng.uniform(-10, 0, 200)]
    q_top = np.c_[rng.uniform(20, 40, 200), rng.uniform(0, 20, 200), np.zeros(200)]
    on_p = np.c_[np.linspace(-30, 0, 60), rng.uniform(0, 20, 60), np.zeros(60)]
    on_q = np.c_[rng.uniform(20, 40, 40), rng.uniform(0, 20, 40), np.zeros(40)]
    surface, view, merged, labels = _two_segments_and_a_merged_mask(
        np.concatenate([p_strip, q_side, q_top, on_p, on_q]), [200, 400, 100])
    config = ShadowCorrConfig(method="fused")
    assert join_nearest_surface(labels, surface, view, merged, config).tolist() == [0, 1, 0]
    blind = config.with_options(projection_depth_tolerance=0.01)  # each point votes for its nearest surface
    assert join_nearest_surface(labels, surface, view, merged, blind).tolist() == [0, 1, 1]


def test_a_merged_mask_only_a_depth_step_told_joins_the_surface_drawn_in_front_along_its_rays():
    """View 1 (camera at the origin, looking along z) drew one mask over rocks P and Q at 500 cm.  View
    0 sees P's face there (x < -20 cm, segment 0); view 2 sees only Q's far side, 30 cm behind the
    mask's surface (x > -20, segment 1): 30 of the mask's points are on P and 70 on Q.  Both land
    mostly on the mask.  The seen points (all on P) carry the vote for a mask that a third view told
    apart; for one that only a depth step told (``drawn``), Q is drawn under most of its rays.
    Segment 3 of view 2, also covered by the mask, lies 100 cm in front of its surface, where it
    would hide the mask: it is drawn nowhere."""
    grid = np.stack(np.meshgrid(np.arange(-50.0, 50.0, 2.0), np.arange(-50.0, 50.0, 2.0)), -1).reshape(-1, 2)
    p_face = np.c_[grid[grid[:, 0] < -20], np.full((grid[:, 0] < -20).sum(), 500.0)]
    q_back = np.c_[grid[grid[:, 0] >= -20], np.full((grid[:, 0] >= -20).sum(), 530.0)]
    occluder = np.c_[grid, np.full(len(grid), 400.0)]
    mask_points = np.c_[np.linspace(-49, 49, 100), np.tile(np.linspace(-45, 45, 10), 10), np.full(100, 500.0)]
    shells = [p_face, q_back, mask_points, occluder]
    view, instance = np.array([0, 2, 1, 2]), np.array([1, 1, 1, 2])
    on_mask = np.zeros((4, 3), dtype=np.int64)
    on_mask[[0, 1, 3], 1] = 100
    hit_source, hit_target = np.array([0, 1, 3]), np.array([2, 2, 2])  # each lands wholly on the mask
    samples = np.array([100, 100, 100, 100])
    points = np.concatenate([x[np.linspace(0, len(x) - 1, 100).astype(int)] for x in shells]).astype(np.float32)
    surface = SurfaceEvidence(samples, points, on_mask, on_mask, hit_source, hit_target, np.full(3, 100))
    config = ShadowCorrConfig(method="fused")
    labels, merged = np.array([0, 1, 0, 3]), np.array([False, False, True, False])
    shell_points, shell_count = np.concatenate(shells).astype(np.float32), np.array([len(x) for x in shells])
    cameras = np.zeros((3, 3))
    joined = join_nearest_surface(labels, surface, view, merged, config, shell_points, shell_count, cameras, merged)
    assert joined.tolist() == [0, 1, 1, 3]
    assert join_nearest_surface(labels, surface, view, merged, config, shell_points, shell_count, cameras,
                                np.zeros(4, bool)).tolist() == [0, 1, 0, 3]
    without_cameras = join_nearest_surface(labels, surface, view, merged, config, shell_points, shell_count)
    assert without_cameras.tolist() == [0, 1, 0, 3]
    # Just behind the mask's surface instead, the third surface is the first one along Q's rays.
    shell_points[shell_count[:3].sum():, 2] = 510.0
    assert join_nearest_surface(labels, surface, view, merged, config, shell_points, shell_count,
                                cameras, merged).tolist() == [0, 1, 3, 3]


@pytest.mark.parametrize("method", GRAPH_METHODS)
def test_a_blob_without_depth_is_reported_as_what_happened_to_it(model, method):
    # View 0: the sphere's mask gets a second blob, far from the sphere and without valid depth.
    bundle = sphere_scene([[0, 0, 0]], [40], cameras=3)
    view = bundle.views[0]
    value = int(view.mask[view.mask > 0].max())
    view.mask[5:20, 5:20] = value
    view.depth[5:20, 5:20] = 0
    result = correspond(bundle, model, ShadowCorrConfig(method=method))
    (empty,) = [s for s in result.segments if s.num_points == 0]
    (sibling,) = [s for s in result.segments if s.view == empty.view and s.segment != empty.segment]
    assert empty.instance == sibling.instance
    if empty.object == sibling.object:  # fused: the same-mask constraint joins the blobs
        assert empty.assignment == "same_mask"
        assert any("joined the other blobs of its mask" in w for w in result.warnings), result.warnings
    else:  # projection links by landings only: a blob nothing lands on stays alone
        assert empty.assignment == "own_object"
        assert sum(s.object == empty.object for s in result.segments) == 1
    assert method == "projection" or empty.object == sibling.object


def test_an_unsure_seam_neither_joins_nor_parts_the_pair_in_its_view():
    """A small piece (segment 1) that a split cut off segment 0 in view 0; segment 2 (view 1) sees the
    rock whole.  The piece lands on segment 2, segment 2 partly on it.  With two mask ids in view 0
    the cannot-link keeps the piece alone; with one loose id (an unsure seam) view 0 says nothing
    between the piece and the group of segments 0 and 2 (two views), and the landings join it.
    Between the two segments of view 0 alone (one view each) the ids still differ."""
    n = 100
    config = ShadowCorrConfig(method="fused")
    view, instance = [0, 0, 1], [1, 2, 1]
    on_mask = [[0, 3 * n], [0, n // 5], [3 * n, 0]]
    hits = [(0, 2, 3 * n), (1, 2, n // 5), (2, 0, 2 * n), (2, 1, n // 3)]
    apart = _graph(view, instance, on_mask, hits)
    labels = agglomerate(apart, config)
    assert labels[0] == labels[2] and labels[1] != labels[0]
    unsure = replace(apart, loose=np.array([1, 1, 1]))
    labels = agglomerate(unsure, config)
    assert len(set(labels.tolist())) == 1
    groups = _Groups(unsure, config)
    assert groups.constraints(0, 1) == (0.0, 1.0)  # one view each: different masks
    rock = groups.merge(0, 2)
    assert groups.constraints(rock, 1) == (0.0, 0.0)  # a piece of one view against two views: neither share
    apart_groups = _Groups(apart, config)
    assert apart_groups.constraints(apart_groups.merge(0, 2), 1) == (0.0, 1.0)


def test_a_blob_with_a_loose_id_of_its_own_still_agrees_with_its_mask():
    """Mask 5 of view 0 falls into blobs 0 and 1; an unsure seam with segment 3 (mask 2 of view 0)
    gave blob 1 alone the loose id 2.  Segment 2 (view 1) sees the rock whole.  Blob 1 against the
    group of blob 0 and segment 2 (two views): view 0's ids agree, so it joins them and does not
    part them as well; a group holding segment 3 (a different id and loose id) is still parted."""
    config = ShadowCorrConfig(method="fused")
    view, instance = [0, 0, 1, 0], [5, 5, 1, 2]
    on_mask = [[0, 100], [0, 10], [100, 0], [0, 50]]
    hits = [(0, 2, 90), (1, 2, 8), (2, 0, 80), (2, 1, 6)]
    graph = replace(_graph(view, instance, on_mask, hits), loose=np.array([5, 2, 1, 2]))
    groups = _Groups(graph, config)
    rock = groups.merge(0, 2)
    assert groups.constraints(rock, 1) == (1.0, 0.0)
    assert groups.constraints(groups.merge(rock, 3), 1) == (0.0, 1.0)
    links = _segment_group_linkage(graph, np.array([0, 1, 0, 2]), config)
    (at,) = np.flatnonzero((links.segment == 1) & (links.group == 0))
    fresh = _Groups(graph, config)
    assert links.value[at] == fresh.linkage(fresh.merge(0, 2), 1) > 0


def test_the_cannot_link_grows_with_the_views_that_part_two_groups_along_a_depth_step():
    """Rocks P (segments 0, 2, 4) and Q (1, 3, 5) touch and wear two masks in each of views 0, 1, 2.
    Where their seams show two surfaces in two of the views, the cannot-link between the two whole
    groups grows by ``fusion_cannot_link_apart`` of itself, in all three views by at most
    ``fusion_cannot_link_apart_max``; a depth step in one view alone, or none, leaves it as it was,
    and so does any number of them between segments that share one view at most."""
    config = ShadowCorrConfig(method="fused")
    view, instance = [0, 0, 1, 1, 2, 2], [1, 2, 1, 2, 1, 2]
    on_mask = [[0, 50, 50]] * 2 + [[50, 0, 50]] * 2 + [[50, 50, 0]] * 2
    hits = [(a, b, 40) for a, b in ((0, 2), (2, 4), (4, 0), (1, 3), (3, 5), (5, 1))] + [(0, 3, 5), (3, 0, 5)]
    plain = _graph(view, instance, on_mask, hits)

    def with_steps(pairs):
        first, second = (np.array(x, dtype=np.int64) for x in zip(*pairs)) if pairs else (np.zeros(0, np.int64),) * 2
        return replace(plain, surface=replace(plain.surface, seams=replace(
            plain.surface.seams, apart_first=first, apart_second=second)))

    def whole_rocks(graph):
        groups = _Groups(graph, config)
        p, q = groups.merge(groups.merge(0, 2), 4), groups.merge(groups.merge(1, 3), 5)
        return groups, p, q

    shares = {}
    for name, pairs in (("none", []), ("one", [(0, 1)]), ("two", [(0, 1), (2, 3)]),
                        ("three", [(0, 1), (2, 3), (4, 5)])):
        groups, p, q = whole_rocks(with_steps(pairs))
        shares[name] = groups.constraints(p, q)
        assert groups.constraints(q, p) == shares[name]
        # Two lone segments of one view: one shared view, nothing to grow.
        assert _Groups(with_steps(pairs), config).constraints(0, 1) == (0.0, 1.0)
    assert shares["none"] == shares["one"] == (0.0, 1.0)
    assert shares["two"] == (0.0, 1.0 + config.fusion_cannot_link_apart)
    assert shares["three"] == (0.0, 1.0 + min(2 * config.fusion_cannot_link_apart,
                                              config.fusion_cannot_link_apart_max))
    groups, p, q = whole_rocks(with_steps([(0, 1), (2, 3)]))
    before, after = _Groups(plain, config), groups
    bp, bq = before.merge(before.merge(0, 2), 4), before.merge(before.merge(1, 3), 5)
    assert before.linkage(bp, bq) - after.linkage(p, q) == pytest.approx(
        config.fusion_cannot_link * config.fusion_cannot_link_apart)
    # The seams' views follow the groups through the merges in either order.
    reverse = _Groups(with_steps([(0, 1), (2, 3)]), config)
    q2 = reverse.merge(reverse.merge(5, 3), 1)
    p2 = reverse.merge(reverse.merge(4, 2), 0)
    assert reverse.constraints(p2, q2) == shares["two"]
    off = _Groups(with_steps([(0, 1), (2, 3)]), config.with_options(fusion_cannot_link_apart=0.0))
    assert off.constraints(off.merge(off.merge(0, 2), 4), off.merge(off.merge(1, 3), 5)) == (0.0, 1.0)


def test_a_view_whose_pose_refinement_could_not_verify_lands_within_the_wider_depth_tolerance(field):
    # View 0 measures every depth 2 % too far, as a pose off along its rays would: beyond
    # projection_depth_tolerance_rel (1.5 %), within projection_depth_tolerance_unverified_rel (2.5 %)
    # (the absolute floor lowered to half a unit, a sixth of the default, so the relative ones decide).
    config = ShadowCorrConfig(method="projection", projection_depth_tolerance=0.5)
    views = list(field.views)
    views[0] = replace(views[0], depth=views[0].depth * 1.02)
    shifted = replace(field, views=views)
    segments = extract_segments(shifted, config)
    exact = surface_evidence(field, extract_segments(field, config), config)
    verified = surface_evidence(shifted, segments, config)
    unverified = surface_evidence(shifted, segments, config, unverified=np.array([True, False, False, False]))
    into_0 = segments.view != 0  # the other views' segments, projected into view 0
    # (Of the points that still land, most lie on the spheres' hidden sides, 2 % behind their fronts.)
    assert verified.visible[into_0, 0].sum() < 0.5 * exact.visible[into_0, 0].sum()
    assert unverified.visible[into_0, 0].sum() > exact.visible[into_0, 0].sum()
    # View 0's own segments, projected into the others, read the wider tolerance too; pairs of views
    # whose poses both stand verified keep the narrow one.
    from_0 = segments.view == 0
    assert unverified.visible[from_0].sum() >= verified.visible[from_0].sum()
    others = np.ix_(into_0, [1, 2, 3])
    np.testing.assert_array_equal(unverified.visible[others], verified.visible[others])
    # The wider tolerance is never narrower than the other one.
    narrow = config.with_options(projection_depth_tolerance_unverified_rel=0.01)
    np.testing.assert_array_equal(
        surface_evidence(shifted, segments, narrow, unverified=np.array([True, False, False, False])).visible,
        verified.visible)


def test_an_isolated_sliver_joins_the_nearest_group_another_view_sees_unless_that_group_holds_its_view():
    # Rock A: segments 0 (view 0) and 1 (view 1), linked by their landings.  Segments 2-4 have no
    # evidence at all: 2 (view 2) touches segment 0's surface; 3 (view 0) lies 8 units from
    # segment 1, but its own view already sees rock A as segment 0; 4 (view 2) lies far from all.
    graph = _graph([0, 1, 2, 0, 2], [1, 1, 1, 2, 2], np.zeros((5, 3), np.int64), [(0, 1, 50), (1, 0, 50)])
    line = np.c_[np.arange(0.0, 10.0, 2.0), np.zeros(5), np.zeros(5)]
    shells = [line, line + [0, 0, 30], line[:2] + [12, 0, 0], line[:2] + [0, 8, 30], line[:2] + [100, 0, 0]]
    points, count = np.concatenate(shells).astype(np.float32), np.array([len(x) for x in shells])
    labels = np.array([0, 0, 2, 3, 4])
    config = ShadowCorrConfig(method="fused")
    assert join_isolated(labels, graph, points, count, config).tolist() == [0, 0, 0, 3, 4]
    # within reach of nothing, or with the rule off, every one stays
    assert join_isolated(labels, graph, points, count, config.with_options(fusion_isolated_reach=1.0)).tolist() \
        == [0, 0, 2, 3, 4]
    assert join_isolated(labels, graph, points, count, config.with_options(fusion_isolated_reach=0.0)) is labels
    # a segment with any evidence (here a shared shadow voxel) is left to the agglomeration
    linked = _graph([0, 1, 2, 0, 2], [1, 1, 1, 2, 2], np.zeros((5, 3), np.int64), [(0, 1, 50), (1, 0, 50)],
                    volume=[(2, 4, -0.5, 1.0)])
    assert join_isolated(labels, linked, points, count, config).tolist() == [0, 0, 2, 3, 4]
    # a segment of many points casts a shadow deep enough to meet its rock: where it meets nothing, it stays
    large = replace(graph, surface=replace(graph.surface, samples=np.array([100, 100, 1000, 100, 100])))
    assert join_isolated(labels, large, points, count, config).tolist() == [0, 0, 2, 3, 4]
