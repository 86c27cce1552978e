"""``render_result``: pictures of a correspondence result, for people to check it at a glance.

Written for one bundle and the result computed from it:

* ``view_<name>_objects.png`` per view (same size as the view): the shaded depth
  image with every segment filled in its object's colour, its object id written on
  it, and low-support segments outlined in black/yellow stripes;
* ``view_<name>_truth.png`` per view when the bundle has ground truth: segments
  green when correct, red when wrong, amber when split (see ``segment_status``);
* ``map_top.png`` and ``map_side.png``: the back-projected segment points of all
  views coloured by object, cameras as arrows, object ids, axes in the bundle's units
  and a scale bar;
* ``contact_sheet.png``: all of the above downscaled on one page, with a summary.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from pydantic import BaseModel, ConfigDict, Field

from ..bundle import SceneBundle, unit_scale
from ..config import ShadowCorrConfig
from ..result import Result
from ..stages import Segments, extract_segments
from ._draw import Box
from .maps import MapScene, UpAxis, choose_frame, render_maps
from .palette import CORRECT, SPLIT, UNKNOWN, WRONG, object_colours
from .sheet import contact_sheet
from .views import crop_box, segment_index_image, shade_depth, view_picture

log = logging.getLogger(__name__)

#: Codes of ``segment_status``.
STATUS_CORRECT, STATUS_WRONG, STATUS_SPLIT, STATUS_UNKNOWN = 0, 1, 2, 3
#: zlib level of the PNGs: level 6 (Pillow's default) takes ~4x longer for ~10% smaller files.
PNG_COMPRESSION = 3
_STATUS_COLOURS = np.array([CORRECT, WRONG, SPLIT, UNKNOWN], dtype=np.uint8)


class RenderConfig(BaseModel):
    """How to draw a result.  ``engine`` must say how the result's segments were cut."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    low_support: float = Field(0.6, ge=0, le=1, description="segments with support below this get a striped outline")
    alpha: float = Field(0.5, ge=0, le=1, description="opacity of the segment fills (1: flat colours)")
    outline_px: int = Field(2, ge=0, le=50, description="width of each segment's solid outline in its fill colour")
    annotate: bool = Field(True, description="write ids, legends and low-support stripes; off: colour fills only")
    up_axis: UpAxis = Field("auto", description="world axis pointing up for the maps; auto: nearest to the cameras' up")
    map_size: int = Field(1000, ge=100, le=8000, description="pixels across the larger horizontal extent of the map")
    sheet_tile_width: int = Field(480, ge=64, le=4000, description="width of one view on the contact sheet")
    sheet_columns: int = Field(4, ge=1, le=16)
    engine: ShadowCorrConfig | None = Field(
        None,
        description="segmentation settings the result was computed with (split_components, min_blob_pixels, "
        "max_depth); None: the configuration recorded in the result (or the defaults)",
    )


def segment_status(truth: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """Per segment: ``STATUS_CORRECT``, ``STATUS_WRONG``, ``STATUS_SPLIT`` or ``STATUS_UNKNOWN``.

    Segments are counted unweighted, like the segment metrics.  Among the segments with
    ground truth (``truth >= 0``) and a label (``objects >= 0``):

    * the *majority rock* of an object is the rock most of its segments belong to
      (ties: the smallest rock id);
    * a segment is **wrong** when its own rock is not its object's majority rock
      (it was merged into another rock's object: what lowers cluster purity);
    * otherwise it is **correct** - the paper's Fig. 9 green/red split;
    * a correct segment is further marked **split** when its rock's segments are spread
      over several objects and its object is not the rock's *main object* (the object
      holding most of the rock's segments; ties: the smallest object id).  Such a rock
      was over-segmented (what lowers rock purity); splits are invisible in green/red.

    Segments without ground truth or label are ``STATUS_UNKNOWN``.
    """
    truth = np.asarray(truth, dtype=np.int64)
    objects = np.asarray(objects, dtype=np.int64)
    status = np.full(truth.shape, STATUS_UNKNOWN, dtype=np.int64)
    known = (truth >= 0) & (objects >= 0)
    if not known.any():
        return status
    pairs, counts = np.unique(np.stack([objects[known], truth[known]], axis=1), axis=0, return_counts=True)
    obj_of_pair, rock_of_pair = pairs[:, 0], pairs[:, 1]

    # Majority rock per object: sort by (object, -count, rock) and take the first of each object.
    order = np.lexsort((rock_of_pair, -counts, obj_of_pair))
    objs, first = np.unique(obj_of_pair[order], return_index=True)
    majority_rock = rock_of_pair[order][first]
    # Main object per rock, and on how many objects each rock is spread.
    order = np.lexsort((obj_of_pair, -counts, rock_of_pair))
    rocks, first, spread = np.unique(rock_of_pair[order], return_index=True, return_counts=True)
    main_object = obj_of_pair[order][first]

    o, r = objects[known], truth[known]
    wrong = majority_rock[np.searchsorted(objs, o)] != r
    rock_pos = np.searchsorted(rocks, r)
    split = ~wrong & (spread[rock_pos] > 1) & (main_object[rock_pos] != o)
    status[known] = np.where(wrong, STATUS_WRONG, np.where(split, STATUS_SPLIT, STATUS_CORRECT))
    return status


def _safe_name(name: str, taken: set[str]) -> str:
    """A file-name-safe, unique version of a view name."""
    base = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "view"
    candidate, n = base, 1
    while candidate in taken:
        n += 1
        candidate = f"{base}_{n}"
    taken.add(candidate)
    return candidate


def _darker(colours: np.ndarray, factor: float = 0.55) -> np.ndarray:
    return (colours.astype(np.float32) * factor).astype(np.uint8)


@dataclass
class _Labels:
    """What the pictures show per result segment (arrays indexed by the result's segment order)."""

    obj: np.ndarray  # object id
    support: np.ndarray
    low: np.ndarray  # support below the threshold
    truth: np.ndarray  # ground-truth rock, -1 unknown
    status: np.ndarray | None  # segment_status, None without ground truth


def render_result(bundle: SceneBundle, result: Result, out_dir: str | Path, *, config: RenderConfig | None = None) -> list[Path]:
    """Draw ``result`` over ``bundle`` into ``out_dir`` (see the module docstring); returns the files written.

    Raises ``ValueError`` when the result names views the bundle does not have.  Blobs
    of a mask that the result does not list (or result segments no mask blob matches:
    the result was computed with other ``engine`` settings) are left undrawn and logged.
    """
    config = config or RenderConfig()
    if config.engine is None:
        recorded = ShadowCorrConfig.model_validate(result.config) if result.config else ShadowCorrConfig()
        config = config.model_copy(update={"engine": recorded})
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    unknown_views = sorted({s.view for s in result.segments} - {v.name for v in bundle.views})
    if unknown_views:
        raise ValueError(f"the result names views the bundle does not have: {unknown_views[:5]}")
    notes: list[str] = []

    # The engine's own segmentation: the same blobs, their 3D points and their ground truth.
    segs = extract_segments(bundle, config.engine)
    index_of = {(s.view, s.instance, s.component): i for i, s in enumerate(result.segments)}
    seg_to_result = np.array([index_of.get((segs.view_names[v], int(i), int(c)), -1)
                              for v, i, c in zip(segs.view, segs.instance, segs.component)], dtype=np.int64)
    if (seg_to_result < 0).any():
        notes.append(f"{int((seg_to_result < 0).sum())} segments of the bundle are not in the result, not drawn "
                     "(was it computed with other split_components / min_blob_pixels?)")
    unmatched = len(result.segments) - int(np.unique(seg_to_result[seg_to_result >= 0]).size)
    if unmatched:
        notes.append(f"{unmatched} result segments match no segment of the bundle: not drawn")
    labels = _labels(bundle, result, segs, seg_to_result, config)

    written: list[Path] = []

    def save(image: Image.Image, name: str) -> None:
        path = out / name
        image.save(path, compress_level=PNG_COMPRESSION)
        written.append(path)

    sheet_objects: list[tuple[str, Image.Image]] = []
    sheet_truth: list[tuple[str, Image.Image]] = []
    taken: set[str] = set()
    max_depth = config.engine.max_depth / unit_scale(bundle.units, config.engine.units)
    pictureless = [v.name for v in bundle.views if v.depth is None or v.mask is None or v.intrinsics is None]
    if pictureless:
        notes.append(f"{len(pictureless)} views without depth and mask images: no view pictures for them")
    for view in (v for v in bundle.views if v.name not in pictureless):  # one iteration per view
        lookup = {(s.instance, s.component): i for i, s in enumerate(result.segments) if s.view == view.name}
        seg_image = segment_index_image(view, lookup, config.engine)
        base = shade_depth(view, max_depth)
        name = _safe_name(view.name, taken)
        pictures = [("objects", sheet_objects, _objects_picture(view.name, base, seg_image, labels, config))]
        if labels.status is not None:
            pictures.append(("truth", sheet_truth, _truth_picture(view.name, base, seg_image, labels, config)))
        # One crop for both thumbnails of a view, around its segments and every label.
        thumb = crop_box(seg_image, [b for _, _, (_, _, boxes) in pictures for b in boxes])
        for kind, tiles, (picture, plain, _) in pictures:
            save(picture, f"view_{name}_{kind}.png")
            tiles.append((view.name, plain.crop(thumb)))

    maps = _render_maps(bundle, result, segs, seg_to_result, labels.obj, config)
    save(maps[0], "map_top.png")
    save(maps[1], "map_side.png")
    sheet = contact_sheet([("Objects (colour = object id)", sheet_objects),
                           ("Ground truth check (green correct, red wrong, amber split)", sheet_truth)],
                          maps, _summary(result, labels, config, notes), tile_width=config.sheet_tile_width,
                          columns=config.sheet_columns)
    save(sheet, "contact_sheet.png")
    for note in notes:
        log.warning("%s", note)
    return written


def _labels(bundle: SceneBundle, result: Result, segs: Segments, seg_to_result: np.ndarray,
            config: RenderConfig) -> _Labels:
    """Object, support and ground-truth status of every result segment."""
    num = len(result.segments)
    obj = np.array([s.object for s in result.segments], dtype=np.int64)
    support = np.array([s.support for s in result.segments], dtype=np.float64)
    truth = np.full(num, -1, dtype=np.int64)
    has_truth = bundle.has_ground_truth and segs.truth is not None
    if has_truth:
        hit = seg_to_result >= 0
        truth[seg_to_result[hit]] = segs.truth[hit]
    return _Labels(obj=obj, support=support, low=support < config.low_support, truth=truth,
                   status=segment_status(truth, obj) if has_truth else None)


def _objects_picture(name: str, base: np.ndarray, seg_image: np.ndarray, labels: _Labels,
                     config: RenderConfig) -> tuple[Image.Image, Image.Image, list[Box]]:
    """Segments in their objects' colours, ids, low-support stripes (see ``view_picture``)."""
    present = np.unique(seg_image[seg_image >= 0])
    obj, support, low = labels.obj, labels.support, labels.low
    texts = {int(s): (f"{obj[s]} ({support[s]:.2f})" if low[s] else str(obj[s])) for s in present}
    n_low = int(low[present].sum())
    legend = [(f"{name}: {present.size} segments of {np.unique(obj[present]).size} objects; label = object id", None)]
    if n_low:
        legend.append((f"striped outline, (0.xx): support < {config.low_support:.2f} ({n_low})", None))
    fill = object_colours(obj)
    return view_picture(base, seg_image, fill, fill, texts, fill, legend, alpha=config.alpha,
                        outline_px=config.outline_px, draw_text=config.annotate,
                        hazard=low if config.annotate else None)


def _truth_picture(name: str, base: np.ndarray, seg_image: np.ndarray, labels: _Labels,
                   config: RenderConfig) -> tuple[Image.Image, Image.Image, list[Box]]:
    """Segments green / red / amber by ``segment_status`` (see ``view_picture``)."""
    present = np.unique(seg_image[seg_image >= 0])
    status, obj, truth = labels.status, labels.obj, labels.truth
    colours = _STATUS_COLOURS[status]
    counts = np.bincount(status[present], minlength=4)
    flagged = (STATUS_WRONG, STATUS_SPLIT)
    texts = {int(s): (f"{obj[s]} | rock {truth[s]}" if status[s] in flagged else str(obj[s])) for s in present}
    legend = [(f"{name}: ground truth check (label = object | true rock)", None),
              (f"correct ({counts[STATUS_CORRECT]})", CORRECT),
              (f"wrong: object's majority is another rock ({counts[STATUS_WRONG]})", WRONG),
              (f"split: rock spread over objects ({counts[STATUS_SPLIT]})", SPLIT)]
    if counts[STATUS_UNKNOWN]:
        legend.append((f"no ground truth ({counts[STATUS_UNKNOWN]})", UNKNOWN))
    # Outlines darker than the fill: neighbouring segments of one status stay apart.
    return view_picture(base, seg_image, colours, _darker(colours), texts, _darker(colours, 0.8), legend,
                        alpha=config.alpha, outline_px=config.outline_px, draw_text=config.annotate)


def _render_maps(bundle: SceneBundle, result: Result, segs: Segments, seg_to_result: np.ndarray, obj: np.ndarray,
                 config: RenderConfig) -> tuple[Image.Image, Image.Image]:
    """Top-down and side views of the back-projected points, in bundle units."""
    to_bundle = 1.0 / unit_scale(bundle.units, config.engine.units)
    point_seg = np.repeat(seg_to_result, segs.lengths)
    keep = point_seg >= 0
    points = segs.points[keep] * to_bundle
    point_object = obj[point_seg[keep]]
    object_ids = np.array([o.object for o in result.objects], dtype=np.int64)
    centres = np.full((object_ids.size, 3), np.nan)
    for i, o in enumerate(result.objects):  # one per object
        if o.centroid is not None:
            centres[i] = o.centroid
        elif (point_object == o.object).any():
            centres[i] = points[point_object == o.object].mean(axis=0)
    poses = np.stack([v.pose for v in bundle.views])
    scene = MapScene(points=points, point_object=point_object, object_ids=object_ids, object_centres=centres,
                     camera_centres=poses[:, :3, 3], camera_axes=poses[:, :3, 2],
                     camera_names=[v.name for v in bundle.views], units=bundle.units,
                     point_spacing=_point_spacing(bundle, segs, keep, to_bundle))
    return render_maps(scene, choose_frame(poses, config.up_axis), config.map_size)


def _point_spacing(bundle: SceneBundle, segs: Segments, keep: np.ndarray, to_bundle: float) -> float:
    """Typical distance between neighbouring back-projected points, in bundle units.

    A pixel at distance r from a camera of focal length f spans about r / f: the median
    over the points of that.  Bundles of point segments have no focal length: there the
    median nearest-neighbour distance of a sample of points stands in.
    """
    points = segs.points[keep] * to_bundle
    if points.shape[0] < 2:
        return 0.0
    seg_of_point = np.repeat(np.arange(segs.num_segments), segs.lengths)[keep]
    focal = np.array([min(v.intrinsics.fx, v.intrinsics.fy) if v.intrinsics else np.nan for v in bundle.views])
    f = focal[segs.view[seg_of_point]]
    if np.all(np.isfinite(f)):
        distance = np.linalg.norm(points - segs.camera_center[seg_of_point] * to_bundle, axis=1)
        return float(np.median(distance / f))
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)  # fixed: the same picture every run
    sample = points[rng.choice(points.shape[0], size=min(points.shape[0], 2000), replace=False)]
    dist, _ = cKDTree(points).query(sample, k=2)
    return float(np.median(dist[:, 1]))


def _summary(result: Result, labels: _Labels, config: RenderConfig, notes: list[str]) -> list[str]:
    """Text lines for the contact sheet."""
    lines = [f"scene: {result.scene}",
             f"method: {result.method}" + (f" ({result.model.name} {result.model.version})" if result.model else ""),
             f"{len(result.segments)} segments -> {len(result.objects)} objects",
             f"segments with low support (< {config.low_support:.2f}): {int(labels.low.sum())}"]
    if labels.status is not None:
        counts = np.bincount(labels.status, minlength=4)
        lines.append(f"correct {counts[0]}, wrong {counts[1]}, split {counts[2]}"
                     + (f", no truth {counts[3]}" if counts[3] else ""))
    if result.metrics:
        m = result.metrics
        for key, label in (("average_purity", "average purity"), ("rock_purity", "rock purity"),
                           ("cluster_purity", "cluster purity"), ("voxel_ari", "voxel ARI"), ("coverage", "coverage")):
            if key in m:
                lines.append(f"{label}: {float(m[key]):.4g}")
    fallback = sum(s.assignment != "vote" for s in result.segments)
    if fallback:
        lines.append(f"segments labelled without kept voxels: {fallback}")
    lines.extend(notes[:5])
    return lines
