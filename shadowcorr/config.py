"""One validated configuration object for the whole method (SPEC §2 defaults).

Every length is expressed in ``units`` (the model's units: centimetres for the
reference data and the shipped model).  A bundle in other units is converted to
these units when its segments are extracted, so the parameters never need editing
by hand for metre or millimetre data.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

#: Options a remote caller may change per request without making the model's
#: inputs inconsistent with its training (used by the HTTP service).
REQUEST_OPTIONS = ("bandwidth", "split_components", "min_blob_pixels", "min_cluster_size", "refine_poses")


class ShadowCorrConfig(BaseModel):
    """Parameters of the volumetric-consensus method, in the order the stages use them."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    units: Literal["m", "cm", "mm"] = "cm"

    # step 0: pose refinement (shadowcorr.pose_refinement)
    refine_poses: bool = Field(False, description="register the views' full depth to each other and correct their poses first")
    pose_point_spacing: float = Field(12.0, gt=0, description="registration point cloud: one point per cell of this size (units)")
    pose_max_rotation_deg: float = Field(5.0, gt=0, le=30, description="larger corrections are refused (the pose is kept)")
    pose_max_translation: float = Field(50.0, gt=0, description="camera centre moves beyond this are refused (units)")
    pose_min_rotation_deg: float = Field(0.1, ge=0, description="when no view needs more (and no more than pose_min_translation), all poses are kept")
    pose_min_translation: float = Field(1.0, ge=0, description="see pose_min_rotation_deg (units)")
    pose_min_overlap: float = Field(0.2, gt=0, le=1, description="view pairs sharing less of their surface are not registered")
    pose_max_residual: float = Field(5.0, gt=0, description="registrations fitting worse (RMS point-to-plane, units) are not used")

    # segments
    split_components: bool = Field(True, description="split disconnected blobs of one mask value into segments")
    min_blob_pixels: int = Field(50, ge=0, description="blobs with fewer pixels are ignored")
    max_depth: float = Field(2000.0, gt=0, description="depth beyond this is invalid (units)")

    # step 1: per-segment clean-up
    downsample_size: float = Field(2.0, gt=0, description="voxel-grid downsampling cell (units)")
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
    min_confidence: float = Field(0.05, ge=0, lt=1)

    # step 7: consensus filter
    gamma_percentile: float = Field(50.0, ge=0, le=100)

    # step 8: segment-id embeddings
    segment_embedding_dim: int = Field(12, ge=1)
    segment_embedding_steps: int = Field(200, ge=0)
    segment_embedding_lr: float = Field(1e-3, gt=0)
    segment_embedding_tau: float = Field(0.1, gt=0)
    segment_embedding_init_std: float = Field(0.5, gt=0)
    segment_embedding_weights: Literal["row_normalised", "raw"] = "row_normalised"
    seed: int = 0

    # steps 11-12: clustering
    method: Literal["shadowcorr", "meanshift"] = Field(
        "shadowcorr", description="'meanshift' is the paper's baseline: no network, no segment ids"
    )
    bandwidth: float = Field(0.7, gt=0, description="MeanShift bandwidth on the network embeddings")
    baseline_bandwidth: float = Field(0.2, gt=0, description="MeanShift bandwidth of the 'meanshift' baseline")
    min_cluster_size: int = Field(5, ge=1, description="smaller clusters merge into the nearest larger one")
    orphan_max_gap: float = Field(
        2.0, ge=0, description="a segment without kept voxels joins an object only if its shadow comes within "
        "this many voxels of that object's kept voxels; otherwise it is an object of its own"
    )

    @model_validator(mode="after")
    def _geometry(self) -> "ShadowCorrConfig":
        if self.downsample_size >= self.voxel_size:
            raise ValueError("downsample_size must be smaller than voxel_size")
        return self

    @property
    def feature_dim(self) -> int:
        return 4 + self.segment_embedding_dim

    def with_options(self, **options: object) -> "ShadowCorrConfig":
        """A copy with some fields changed, validated again."""
        return ShadowCorrConfig.model_validate({**self.model_dump(), **options})
