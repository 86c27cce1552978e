"""Stage 03 seams: neighbouring masks of one view on one smooth surface, against an occlusion contour."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from shadowcorr import ShadowCorrConfig
from shadowcorr.ops import relative_depth_noise
from shadowcorr.stages import SegmentImage, extract_segments, smooth_seams
from shadowcorr.stages._03_seams import TOUCH_REACH, _view_seams

from .scenes import sphere_scene

H, W = 120, 160


def _tilted_plane(z0: float = 500.0, slope: float = 0.8) -> np.ndarray:
    """Depth of a plane tilted along the rows and columns (cm): a steep, smooth surface."""
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float64)
    return z0 + slope * rows + 0.3 * slope * cols


def _image(labels: np.ndarray) -> SegmentImage:
    return SegmentImage(labels.astype(np.int16), 0, 0, labels.shape)


def _two_halves(gap: int, diagonal: bool = False) -> np.ndarray:
    """One blob 20..100 x 30..130 cut in two by a vertical (or slanted) line ``gap`` pixels wide."""
    labels = np.full((H, W), -1, dtype=np.int64)
    rows, cols = np.mgrid[0:H, 0:W]
    inside = (rows >= 20) & (rows < 100) & (cols >= 30) & (cols < 130)
    cut = 80 + (0.5 * (rows - 60) if diagonal else 0)
    labels[inside & (cols < cut)] = 0
    labels[inside & (cols >= cut + gap)] = 1
    return labels


@pytest.mark.parametrize("gap,diagonal", [(0, False), (3, False), (6, True)])
def test_a_cut_across_one_surface_is_a_smooth_seam(gap, diagonal):
    seams = _view_seams(_image(_two_halves(gap, diagonal)), _tilted_plane(), ShadowCorrConfig())
    assert seams.first.tolist() == [0] and seams.second.tolist() == [1]
    assert seams.samples[0] >= 60 and abs(seams.step[0]) < 1e-9  # a plane: the slope explains every step


def test_an_occlusion_contour_is_no_seam():
    """The right half is a different surface 8 % farther (a rock behind its neighbour)."""
    depth = _tilted_plane()
    labels = _two_halves(2)
    depth[labels == 1] *= 1.08
    seams = _view_seams(_image(labels), depth, ShadowCorrConfig())
    assert seams.first.size == 0 and seams.unsure_first.size == 0
    # A long seam with a step far beyond the tolerance shows two surfaces: the pair is apart.
    assert seams.apart_first.tolist() == [0] and seams.apart_second.tolist() == [1]
    assert _view_seams(_image(labels), depth, ShadowCorrConfig(fusion_seam_apart=0)).apart_first.size == 0
    # A cut across one surface is not apart.
    assert _view_seams(_image(labels), _tilted_plane(), ShadowCorrConfig()).apart_first.size == 0


def test_a_gap_wider_than_fusion_seam_gap_is_no_seam():
    config = ShadowCorrConfig()
    assert _view_seams(_image(_two_halves(config.fusion_seam_gap + 1)), _tilted_plane(), config).first.size == 0
    assert _view_seams(_image(_two_halves(config.fusion_seam_gap)), _tilted_plane(), config).first.size == 1


def test_masks_that_touch_at_all_are_listed_whatever_their_seam_says():
    config = ShadowCorrConfig()
    # Smooth, apart (a step) or a corner too short to read: the pair touches.
    depth = _tilted_plane()
    stepped = _two_halves(2)
    depth[stepped == 1] *= 1.08
    corner = np.full((H, W), -1, dtype=np.int64)
    corner[10:40, 10:40], corner[40:70, 40:70] = 0, 1  # meet at one corner: a single diagonal step
    corner[39, 40] = 1
    for labels, z in ((_two_halves(0), _tilted_plane()), (stepped, depth), (corner, _tilted_plane())):
        seams = _view_seams(_image(labels), z, config)
        assert seams.touching_first.tolist() == [0] and seams.touching_second.tolist() == [1]
    assert _view_seams(_image(corner), _tilted_plane(), config).first.size == 0
    # Beyond fusion_seam_gap no seam, but still touching; beyond TOUCH_REACH gaps, apart.
    near = _view_seams(_image(_two_halves(config.fusion_seam_gap + 1)), _tilted_plane(), config)
    assert near.first.size == 0 and near.touching_first.tolist() == [0]
    far = _view_seams(_image(_two_halves(TOUCH_REACH * config.fusion_seam_gap + 1)), _tilted_plane(), config)
    assert far.touching_first.size == 0


def test_smooth_seams_says_which_views_it_read():
    scene = sphere_scene([[0, 0, 40], [78, 0, 40]], [40, 40], cameras=3, width=160, height_px=120)
    config = ShadowCorrConfig()
    segments = extract_segments(scene, config)
    assert smooth_seams(scene, segments, config).views_read.tolist() == [0, 1, 2]
    assert smooth_seams(scene, segments, config.with_options(fusion_seam_gap=0)).views_read.size == 0


def test_noisy_depth_needs_a_longer_seam():
    """Noise sigma = a z^2 (0.5 % at 7.5 m): a long cut across a noisy surface still reads as smooth
    (the signed median cancels the noise); a seam too short for that noise does not count, though
    the same seam counts in clean depth; an occlusion step stays out either way."""
    rng = np.random.default_rng(3)
    clean = _tilted_plane(z0=750.0)
    a = 0.005 / 750.0
    noisy = clean + rng.normal(size=clean.shape) * a * clean ** 2
    assert relative_depth_noise(noisy) == pytest.approx(a, rel=0.25)
    config = ShadowCorrConfig()
    labels = _two_halves(3)
    seams = _view_seams(_image(labels), noisy, config)
    assert seams.first.tolist() == [0]
    n = seams.samples[0]
    # Rows walk 4 pixels from one half's border to the other's; 10 pixels are read a side from
    # 1 inside: the sides' centroids lie 15 pixels apart.  Per step sqrt(2/10 + 15^2 / (2 * 82.5))
    # sigma; the median of n steps 1.25 times that / sqrt(n).
    per_step = np.sqrt(2.0 / 10 + 15.0**2 / (2 * 82.5))
    assert seams.uncertainty[0] == pytest.approx(1.25 * per_step * a * 750.0 / np.sqrt(n), rel=0.3)
    short = labels.copy()
    short[:97] = -1  # the halves now share 3 rows of their border
    few = config.with_options(fusion_seam_min_pixels=3)
    assert _view_seams(_image(short), noisy, few).first.size == 0
    assert _view_seams(_image(short), clean, few).first.tolist() == [0]
    stepped = noisy.copy()
    stepped[labels == 1] *= 1.03
    assert _view_seams(_image(labels), stepped, config).first.size == 0
    assert _view_seams(_image(labels), stepped, config.with_options(fusion_seam_noise=0.0)).first.size == 0


@pytest.mark.parametrize("gap", [3, 12])
def test_the_stated_uncertainty_is_the_spread_of_the_median_step(gap):
    """Over independent noise draws on one surface, the median step of a seam scatters by the
    uncertainty the stage states for it (the noise model of the side fits, not a guess)."""
    rng = np.random.default_rng(11)
    clean = _tilted_plane(z0=750.0)
    a = 0.01 / 750.0
    labels = _two_halves(gap)
    config = ShadowCorrConfig(fusion_seam_tolerance=1.0, fusion_seam_noise=1e-9, fusion_seam_gap=16)
    steps, stated = [], []
    for _ in range(60):
        seams = _view_seams(_image(labels), clean + rng.normal(size=clean.shape) * a * clean**2, config)
        assert seams.first.tolist() == [0]
        steps.append(seams.step[0])
        stated.append(seams.uncertainty[0])
    assert abs(np.mean(steps)) < 3 * np.std(steps) / np.sqrt(len(steps))  # unbiased on a plane
    assert np.std(steps) == pytest.approx(np.median(stated), rel=0.3)


def test_mixed_pixels_on_the_contour_do_not_make_a_seam():
    """The contour pixels of an occlusion hold depth between the two surfaces (a ToF or stereo
    sensor's mixed pixels): the step is read inside each side, so the jump still shows."""
    depth = _tilted_plane()
    labels = _two_halves(0)
    depth[labels == 1] *= 1.08
    cols = np.flatnonzero((labels == 1).any(axis=0))[0]
    depth[:, cols - 1:cols + 1] = 0.5 * (depth[:, cols - 2:cols] + depth[:, cols + 1:cols + 3])
    assert _view_seams(_image(labels), depth, ShadowCorrConfig()).first.size == 0


def test_invalid_depth_on_the_seam_is_not_sampled():
    depth = _tilted_plane()
    labels = _two_halves(2)
    depth[:, 70:90] = 0.0  # no depth along the whole cut
    assert _view_seams(_image(labels), depth, ShadowCorrConfig()).first.size == 0


def test_touching_spheres_have_no_seam_and_a_split_sphere_has_one():
    """On a rendered scene: two touching spheres meet along occlusion contours (no seam in any view);
    one sphere's mask cut in two by a line in one view gives exactly that pair."""
    bundle = sphere_scene([[0, 0, 40], [78, 0, 40]], [40, 40], cameras=4, width=480, height_px=270)
    config = ShadowCorrConfig()
    segments = extract_segments(bundle, config)
    assert smooth_seams(bundle, segments, config).first.size == 0

    view = bundle.views[0]
    mask = np.asarray(view.mask).copy()
    ids = [i for i in np.unique(mask) if i > 0]
    rows, cols = np.nonzero(mask == ids[0])
    cut = mask == ids[0]
    cut &= np.arange(mask.shape[1])[None, :] >= int(np.median(cols))
    mask[cut] = 99
    split = replace(bundle, views=[replace(view, mask=mask), *bundle.views[1:]])
    segments = extract_segments(split, config)
    seams = smooth_seams(split, segments, config)
    assert seams.first.size == 1
    pair = {int(segments.instance[seams.first[0]]), int(segments.instance[seams.second[0]])}
    assert pair == {int(ids[0]), 99} and segments.view[seams.first[0]] == 0
    assert smooth_seams(split, segments, config.with_options(fusion_seam_gap=0)).first.size == 0


@pytest.mark.parametrize("dy, dx", [(0, 1), (1, 0)])
def test_neighbours_match_a_pixel_by_pixel_scan(dy, dx):
    """The run-based neighbour search finds exactly the pairs a plain scan along every line finds:
    a segment's last pixel, at most ``gap`` unlabelled pixels, then a different segment."""
    from shadowcorr.stages._03_seams import _neighbours

    rng = np.random.default_rng(3)
    labels = rng.integers(-1, 4, size=(23, 31))
    labels[rng.random(labels.shape) < 0.55] = -1  # long unlabelled runs between the segments
    gap = 4
    expected = set()
    lines = labels if dx else labels.T
    for line_index, line in enumerate(lines):
        for i, first in enumerate(line):
            if first < 0:
                continue
            j = i + 1
            while j < line.size and line[j] < 0 and j - i - 1 < gap:
                j += 1
            if j < line.size and line[j] >= 0 and line[j] != first:
                row, col = (line_index, i) if dx else (i, line_index)
                expected.add((row, col, int(first), int(line[j]), j - i))
    found = set(zip(*(x.tolist() for x in _neighbours(labels.astype(np.int16), dy, dx, gap))))
    assert found == expected and len(expected) > 20


def test_a_seam_too_short_to_decide_is_unsure_and_an_occlusion_is_not():
    """A small piece cut off a smooth surface meets the rest along 12 rows: too few samples for a
    seam, but its step is no occlusion's, so with ``fusion_seam_unsure`` the pair is unsure; a
    step of 8 % across the same short border is an occlusion contour."""
    labels = _two_halves(3)
    rows = np.arange(H)[:, None]
    labels[((rows < 54) | (rows >= 66)) & (labels == 1)] = -1  # the piece keeps 12 rows
    assert ((labels == 1).any(axis=1)).sum() == 12
    config = ShadowCorrConfig()
    seams = _view_seams(_image(labels), _tilted_plane(), config)
    assert seams.first.size == 0
    assert seams.unsure_first.tolist() == [0] and seams.unsure_second.tolist() == [1]
    off = config.with_options(fusion_seam_unsure=0)
    assert _view_seams(_image(labels), _tilted_plane(), off).unsure_first.size == 0  # off: two masks
    depth = _tilted_plane()
    depth[labels == 1] *= 1.08
    occluded = _view_seams(_image(labels), depth, config)
    assert occluded.first.size == 0 and occluded.unsure_first.size == 0
    assert occluded.apart_first.size == 0  # 12 samples: too short to show two surfaces either


@pytest.mark.parametrize("gap", [0, 6])
def test_a_valley_between_two_surfaces_is_a_crease_and_a_ridge_is_a_seam(gap):
    """Two rocks side by side meet in a valley: each side's surface falls away towards the seam,
    so the step between the sides (one common slope) is nil, but the slope changes across it.
    A cut over the top of one rock (a ridge, convex towards the camera) stays a smooth seam."""
    labels = _two_halves(gap)
    cut = 80 + gap / 2.0
    cols = np.arange(W, dtype=np.float64)[None, :].repeat(H, axis=0)
    focal = (500.0, 500.0)  # pixels: at 5 m, 0.5 cm of depth per pixel is a world slope of 0.5
    valley = 500.0 - 0.5 * np.abs(cols - cut)
    ridge = 500.0 + 0.5 * np.abs(cols - cut)
    config = ShadowCorrConfig()
    creased = _view_seams(_image(labels), valley, config, focal=focal)
    assert creased.first.size == 0 and creased.unsure_first.size == 0
    assert creased.apart_first.tolist() == [0] and creased.apart_second.tolist() == [1]
    # The step alone reads one surface there.
    assert _view_seams(_image(labels), valley, config.with_options(fusion_seam_crease=0), focal=focal
                       ).first.tolist() == [0]
    smooth = _view_seams(_image(labels), ridge, config, focal=focal)
    assert smooth.first.tolist() == [0] and smooth.apart_first.size == 0
    # Without intrinsics the slope has no scale and the crease is not read.
    assert _view_seams(_image(labels), valley, config).first.tolist() == [0]
