"""One validated configuration object for the whole method (SPEC §2 defaults).

Every length is expressed in ``units`` (the model's units: centimetres for the
reference data and the shipped model).  A bundle in other units is converted to
these units when its segments are extracted, so the parameters never need editing
by hand for metre or millimetre data.
"""

from __future__ import annotations

from typing import Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, model_validator

#: World axis names an "up" may be given as ("auto": the one nearest to the cameras' up).
UpAxis = Literal["auto", "x", "y", "z", "-x", "-y", "-z"]
UP_AXES: tuple[str, ...] = get_args(UpAxis)

#: Torch devices the network may be placed on (every other stage runs on the CPU).
DEVICE_PATTERN = r"^(cpu|cuda(:\d+)?|mps)$"

#: The methods, and those that run the network.
METHODS = ("shadowcorr", "meanshift", "projection", "fused")
NETWORK_METHODS = ("shadowcorr", "fused")
#: The methods that read the cross-view surface evidence and group segments by evidence.
SURFACE_METHODS = ("projection", "fused")

#: Options a remote caller may change per request without making the model's
#: inputs inconsistent with its training (used by the HTTP service).
REQUEST_OPTIONS = ("bandwidth", "split_components", "min_blob_pixels", "min_cluster_size", "refine_poses")


class ShadowCorrConfig(BaseModel):
    """Parameters of the volumetric-consensus method, in the order the stages use them."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    units: Literal["m", "cm", "mm"] = "cm"
    num_threads: int = Field(1, ge=0, description="threads for one scene's preparation (views, view pairs, chunks "
                             "of segments, k-NN searches); 0: every core.  Results do not depend on it.  The network "
                             "uses torch's own setting (torch.set_num_threads).  The service runs one scene per core "
                             "and keeps 1")

    # step 0: pose refinement (shadowcorr.stages, stage 01)
    refine_poses: bool = Field(True, description="register the views' full depth to each other and correct their poses first")
    pose_point_spacing: float = Field(12.0, gt=0, description="registration point cloud: one point per cell of this size (units)")
    pose_max_rotation_deg: float = Field(5.0, gt=0, le=30, description="larger corrections are refused (the pose is kept)")
    pose_max_translation: float = Field(50.0, gt=0, description="camera centre moves beyond this are refused (units)")
    pose_min_rotation_deg: float = Field(0.1, ge=0, description="when no view needs more (and no more than pose_min_translation), all poses are kept")
    pose_min_translation: float = Field(1.0, ge=0, description="see pose_min_rotation_deg: how far a correction may move the view's surface (units)")
    pose_min_overlap: float = Field(0.2, gt=0, le=1, description="view pairs sharing less of their surface are not registered")
    pose_depth_window: int = Field(5, ge=1, le=15, description="registration reads each sampled pixel's depth as the mean over "
                                   "a square of this width (pixels; odd, at most the sampling stride) of the pixels on its "
                                   "surface: less depth noise (1: the pixel alone)")
    pose_max_residual: float = Field(5.0, gt=0, description="registrations fitting worse (RMS point-to-plane, units) are not used")
    pose_mask_alignment: bool = Field(True, description="turn the views that registration leaves 'not_registered' or "
                                      "'correction_too_large' about their camera centres until the other views' masked "
                                      "pixels land on their masks (cameras too low to share surface; see "
                                      "shadowcorr.stages, stage 01 mask alignment)")

    # segments
    split_components: bool = Field(True, description="split disconnected blobs of one mask value into segments")
    min_blob_pixels: int = Field(50, ge=0, description="blobs with fewer pixels are ignored")
    depth_cut_step: float | None = Field(
        None, ge=0, description="a blob is cut in pieces where the depth of neighbouring pixels jumps by more than "
        "this share of the depth (and 4 standard deviations of the view's estimated depth noise), when every piece "
        "keeps at least a tenth of its pixels: one mask drawn over two rocks, one in front of the other (see "
        "shadowcorr.stages.cut_at_depth_steps); None: 0.02 for 'fused', 0 (no cut) for the paper's methods")
    max_segments: int = Field(5000, ge=1, description="refuse a scene with more segments (checked once they are cut)")
    max_voxels: int = Field(2_000_000, ge=1, description="refuse a scene with more consensus voxels (checked after "
                            "the consensus filter, before segment embeddings and the network)")
    max_stage_seconds: float | None = Field(None, gt=0, description="refuse a scene once one stage has run longer "
                                            "than this (wall seconds, checked as each stage ends, so the next one "
                                            "never starts); None: no time limit")
    max_depth: float = Field(2000.0, gt=0, description="depth beyond this is invalid (units)")

    subsample_pixels: bool = Field(True, description="back-project only every k-th pixel per axis, k as many "
                                   "pixels as fit in pixel_spacing of a downsample cell at the view's median depth "
                                   "(num_points then counts the back-projected points)")
    pixel_spacing: float = Field(0.7, gt=0, le=1, description="with subsample_pixels: the back-projected pixels' "
                                 "spacing on a surface facing the camera, in downsample cells (at most; the stride "
                                 "is a whole number of pixels)")

    # step 1: per-segment clean-up
    downsample_size: float = Field(2.0, gt=0, description="voxel-grid downsampling cell (units)")
    remove_outliers: bool | None = Field(
        None, description="statistical outlier removal on the downsampled shells; None: on for the paper's methods "
        "('shadowcorr', 'meanshift'), off for 'fused' (measured on the quality benchmark: the same purity in every "
        "row within a standard error at 15-25 % less time; 'projection' casts no shadows)")
    outlier_min_points: int = Field(20, ge=2, description="statistical outlier removal above this many points")
    outlier_std_ratio: float = Field(3.0, gt=0)
    outlier_max_neighbours: int = Field(10, ge=2)

    # steps 2-4: shadow geometry
    ellipsoid_scale: float = Field(1.765, gt=0, description="axis length = scale * sqrt(eigenvalue)")
    projection_factor: float = Field(3.0, gt=0, description="shadow depth = factor * second axis length")
    view_direction: Literal["centroid", "optical_axis"] = Field(
        "centroid", description="camera centre -> segment centroid (paper) or the camera's optical axis (reference code)"
    )

    # step 5-6: voxels and confidence
    voxel_size: float = Field(8.0, gt=0, description="shadow voxel size (units)")
    chebyshev_fraction: float = Field(0.4, gt=0, le=0.5, description="a point fills a voxel within this fraction of v per axis")
    beta_alpha: float = Field(1.41, gt=1)
    beta_beta: float = Field(1.94, gt=1)
    distance_margin: float = Field(1.01, ge=1)
    surface_distance_cell: float | None = Field(
        None, ge=0, description="the confidence's distance runs to the segment's shell points averaged per cell of this "
        "size (units; 0: the shell points themselves, the paper); None: half a voxel for 'fused' (measured on the "
        "quality benchmark: average purity unchanged in 46 of 47 rows, one 0.03 points higher, a k-d tree of a third "
        "of the points), 0 for the paper's methods")
    min_confidence: float = Field(0.05, ge=0, lt=1)

    # step 7: consensus filter
    gamma_percentile: float = Field(50.0, ge=0, le=100)

    # step 8: segment-id embeddings
    segment_embedding_dim: int = Field(12, ge=1)
    segment_embedding_steps: int | None = Field(
        None, ge=0, description="full-batch Adam steps; None: 200 for the paper's methods, 25 for 'fused' (at the "
        "default learning rate the same purity in every row of the quality benchmark, at an eighth of the time)")
    segment_embedding_lr: float | None = Field(
        None, gt=0, description="Adam's learning rate; None: 0.2 / steps (the paper's 1e-3 at 200 steps), so fewer "
        "steps move the vectors about as far")
    segment_embedding_tau: float = Field(0.1, gt=0)
    segment_embedding_init_std: float = Field(0.5, gt=0)
    segment_embedding_weights: Literal["row_normalised", "raw"] = "row_normalised"
    segment_embedding_scope: Literal["component", "scene"] = Field(
        "component", description="softmax denominator over the segment's connected component of the co-occurrence "
        "graph (linear cost) or over the whole scene (the original; quadratic in segments)"
    )
    seed: int = 0

    # which method labels the segments (see METHODS)
    method: Literal["shadowcorr", "meanshift", "projection", "fused"] = Field(
        "fused",
        description="'shadowcorr': the paper's volumetric consensus (network + MeanShift); 'meanshift': the "
        "paper's no-network baseline; 'projection': the training-free cross-view check; 'fused': "
        "cross-view surface evidence and the network's volumetric evidence resolved together",
    )

    # cross-view surface evidence (methods 'projection' and 'fused')
    projection_samples: int = Field(1000, ge=1, description="points drawn from each segment and projected into the other views")
    projection_depth_tolerance: float = Field(3.0, gt=0, description="a projected point is visible when its depth "
                                              "agrees with the view's depth within max(this, rel * depth) (units)")
    projection_depth_tolerance_rel: float = Field(0.015, ge=0, lt=1)
    projection_depth_tolerance_unverified_rel: float = Field(
        0.025, ge=0, lt=1, description="the relative depth tolerance where the pose of either view, the segment's or "
        "the one it is projected into, was declared and pose refinement could not verify it (status "
        "'not_registered', 'correction_too_large' or 'not_confirmed'): such a pose keeps its declared error, which "
        "moves a point's depth along the other view's ray in proportion to its distance; never narrower than "
        "projection_depth_tolerance_rel")
    projection_pixel_tolerance: int | None = Field(
        None, ge=0, le=16, description="a visible point on a pixel of no segment lands on the nearest segment within "
        "this many pixels (masks that stop short of the outline); None: 6 for 'fused' (measured on the quality "
        "benchmark), 0 for 'projection' (the training-free check as specified, which measured better without)")
    projection_min_points: int = Field(20, ge=1, description="'projection': a link needs this many visible points ...")
    projection_min_share: float = Field(0.05, ge=0, le=1, description="... and this share of the segment visible")
    projection_link_share: float = Field(0.5, gt=0, le=1, description="'projection': share of the visible points "
                                         "that must land on the other segment")

    # resolving the evidence (method 'fused', see shadowcorr.stages, stage 09 grouping)
    fusion_surface_prior: float = Field(20.0, gt=0, description="landing points that make surface evidence half-sure")
    fusion_neutral_share: float = Field(0.2, gt=0, lt=1, description="share of a group's landings on another "
                                        "group that is neither for nor against joining them")
    fusion_surface_symmetry: float = Field(0.25, ge=0, le=1, description="weight of the weaker direction of the "
                                           "surface evidence (0: the stronger direction alone)")
    fusion_volume_weight: float = Field(1.0, ge=0, description="weight of the network's volumetric evidence")
    fusion_volume_prior: float = Field(1.0, gt=0, description="shared-voxel mass that makes volumetric evidence half-sure")
    fusion_volume_distance: float = Field(1.0, gt=0, description="embedding distance at which volumetric evidence is neutral")
    fusion_volume_scale: float = Field(0.5, gt=0, description="embedding distance over which the evidence saturates")
    fusion_volume_voxels: float = Field(10.0, gt=0, description="shared voxels that give a segment pair full mass")
    fusion_cannot_link: float = Field(0.6, ge=0, description="penalty times the share of the views seeing both "
                                      "groups in which they wear different mask ids")
    fusion_cannot_link_apart: float = Field(0.5, ge=0, description="the cannot-link grows by this share of "
                                            "itself for every view beyond the first in which the two groups' mask "
                                            "ids differ along a seam that shows two surfaces (stage 03 apart seams)")
    fusion_cannot_link_apart_max: float = Field(1.0, ge=0, description="... by at most this share of itself")
    fusion_same_mask: float = Field(0.5, ge=0, description="bonus times the share of the views seeing both groups "
                                    "in which they wear one mask id (blobs of one mask)")
    fusion_split_views: int = Field(2, ge=0, description="views in which two segments of one view with different "
                                    "mask ids must co-land on one segment for their masks to count as one split mask "
                                    "(0: never)")
    fusion_split_landing: float = Field(0.8, gt=0, le=1, description="share of a segment's landings in a view that "
                                        "must fall on one segment there for it to co-land")
    fusion_split_share: float = Field(0.66, ge=0, le=1, description="... and the share of the views where both land "
                                      "on a mask (see shadowcorr.stages.split_mask_ids)")
    fusion_split_cover: float = Field(0.1, gt=0, le=1, description="... while the segment they land on lands back on "
                                      "each of them with this share of its landings in their view")
    fusion_seam_gap: int = Field(16, ge=0, description="widest run of unlabelled pixels between two masks of one "
                                 "view that is still read as their shared border (eroded masks leave one: 3 px of "
                                 "erosion either side of a cut, 6-9 px across it and up to 1.4 times that along a "
                                 "row or column; 0: seams are not read, see shadowcorr.stages.smooth_seams)")
    fusion_seam_tolerance: float = Field(0.006, ge=0, description="median depth step across a seam, relative to "
                                         "depth, below which two masks of one view read as one smooth surface (a "
                                         "candidate split mask) ...")
    fusion_seam_noise: float = Field(1.25, ge=0, description="... when this many standard errors of that median, "
                                     "under the view's estimated depth noise, are within the same tolerance (0: "
                                     "no such check)")
    fusion_seam_min_pixels: int = Field(30, ge=1, description="pixel pairs sampled along a seam before it is read")
    fusion_seam_unsure: float = Field(1.0, ge=0, description="a seam that is not smooth but whose median step lies within "
                                      "this many standard errors of fusion_seam_tolerance decides nothing: its view "
                                      "neither joins nor parts the pair (0: such pairs are two masks)")
    fusion_seam_apart: float = Field(3.0, ge=0, description="a seam of at least fusion_seam_min_pixels whose median "
                                     "step exceeds fusion_seam_tolerance by more than this many standard errors "
                                     "shows two surfaces: its masks are not made one id because they co-land in other "
                                     "views, where a merged mask may draw two rocks as one (0: no such veto)")
    fusion_seam_crease: float = Field(0.5, ge=0, description="a seam across which the depth's slope (depth per unit "
                                      "of sideways distance) falls by more than this, sure by fusion_seam_noise "
                                      "standard errors, is a crease between two surfaces, as where two rocks meet side "
                                      "by side, and its masks stay two (0: not read)")
    fusion_merge_share: float = Field(0.25, ge=0, le=0.5, description="a segment whose landings in another view "
                                      "split, at least this share on each, over two segments that both land mostly "
                                      "on it and that a third view sees apart (or that meet across a depth step in "
                                      "their own view), is read as a merged mask: landings on "
                                      "it are no evidence (see shadowcorr.stages.merged_mask_segments; 0: never)")
    fusion_merge_reach: float = Field(15.0, gt=0, description="a merged mask of which other views see too few "
                                      "points joins the group whose surface lies nearest to most of its points, "
                                      "counting those within this distance (units; see "
                                      "shadowcorr.stages.join_nearest_surface)")
    fusion_isolated_reach: float = Field(12.0, ge=0, description="a segment without any evidence with another "
                                         "segment that stands alone joins the group of the nearest surface another "
                                         "view saw within this distance, unless that group holds a segment of its "
                                         "view (units; see shadowcorr.stages.join_isolated; 0: never)")
    fusion_threshold: float = Field(0.0, description="groups merge while their linkage exceeds this")
    fusion_confidence_slope: float = Field(4.0, gt=0, description="slope of the logistic turning a segment's "
                                           "linkage margin into its confidence")

    # steps 11-12: clustering (methods 'shadowcorr' and 'meanshift')
    bandwidth: float = Field(0.7, gt=0, description="MeanShift bandwidth on the network embeddings")
    baseline_bandwidth: float = Field(0.2, gt=0, description="MeanShift bandwidth of the 'meanshift' baseline")
    min_cluster_size: int = Field(5, ge=1, description="smaller clusters merge into the nearest larger one")
    orphan_max_gap: float = Field(
        2.0, ge=0, description="a segment without kept voxels joins an object only if its shadow comes within "
        "this many voxels of that object's kept voxels; otherwise it is an object of its own"
    )

    # each object's geometry (see shadowcorr.stages, stages 05 occupancy and 11 geometry)
    up_axis: UpAxis = Field(
        "auto", description="the world axis pointing up (against gravity) in the bundle's frame, about which oriented "
        "boxes turn; auto: the axis nearest to the cameras' mean up (z for REP 103 worlds, Unreal scenes and the "
        "synthetic generator)")
    volume_subdivisions: int = Field(2, ge=1, le=6, description="samples per voxel edge at which the depth images "
                                     "rule out a shadow voxel's parts (volume resolution: voxel_size / this)")
    volume_mask_margin: int = Field(3, ge=0, description="background pixels within this many pixels of a labelled "
                                    "one do not rule out the parts of a shadow behind them: a segmenter that draws "
                                    "masks inside the objects' outlines leaves such pixels on the object (0: every "
                                    "background pixel counts)")
    volume_relative_std: float = Field(0.12, ge=0, description="relative error of an object's volume added to its "
                                       "volume_std: the spread of volume / mesh volume on synthetic scenes "
                                       "(benchmarks/bench_geometry.py), parts no view saw")

    @model_validator(mode="after")
    def _geometry(self) -> "ShadowCorrConfig":
        if self.downsample_size >= self.voxel_size:
            raise ValueError("downsample_size must be smaller than voxel_size")
        return self

    def _by_method(self, value, fused, paper):
        """``value`` if it was set, else the default of the method: ``fused``'s or the paper's methods'."""
        if value is not None:
            return value
        return fused if self.method == "fused" else paper

    @property
    def cut_step(self) -> float:
        """``depth_cut_step`` with the method's default filled in (0: blobs are not cut)."""
        return self._by_method(self.depth_cut_step, 0.02, 0.0)

    @property
    def pixel_tolerance(self) -> int:
        """``projection_pixel_tolerance`` with the method's default filled in."""
        return self._by_method(self.projection_pixel_tolerance, 6, 0)

    @property
    def distance_cell(self) -> float:
        """``surface_distance_cell`` with the method's default filled in (0: no averaging)."""
        return self._by_method(self.surface_distance_cell, self.voxel_size / 2, 0.0)

    @property
    def outlier_removal(self) -> bool:
        """``remove_outliers`` with the method's default filled in."""
        return self._by_method(self.remove_outliers, False, True)

    @property
    def embedding_steps(self) -> int:
        """``segment_embedding_steps`` with the method's default filled in."""
        return self._by_method(self.segment_embedding_steps, 25, 200)

    @property
    def embedding_lr(self) -> float:
        """``segment_embedding_lr`` with its default, 0.2 / ``embedding_steps``, filled in."""
        if self.segment_embedding_lr is not None:
            return self.segment_embedding_lr
        return 0.2 / max(self.embedding_steps, 1)

    @property
    def feature_dim(self) -> int:
        return 4 + self.segment_embedding_dim

    def with_options(self, **options: object) -> "ShadowCorrConfig":
        """A copy with some fields changed, validated again."""
        return ShadowCorrConfig.model_validate({**self.model_dump(), **options})
