"""The multi-objective training loss of SPEC §2 (Training): discriminative + prototypical + graph.

All three terms work on ragged batches: the voxels of several scenes concatenated, with
``batch`` (scene id per voxel) and ``labels`` (ground-truth object per voxel, ids only
need to be unique *within* a scene).  Instances are the distinct ``(scene, label)``
pairs; nothing compares instances or voxels of different scenes.  Every term is first
averaged inside a scene and then over the scenes, so a large scene does not outweigh a
small one (with one scene per step this is simply the per-scene loss).

Terms (defaults are the paper's):

* **discriminative** (De Brabandere et al. 2017) on the raw embeddings ``x``, the space
  MeanShift clusters later:
  ``w_var * mean_c mean_{i in c} [||mu_c - x_i|| - d_var]_+^2
  + w_dist * mean_{c != c'} [2 d_dist - ||mu_c - mu_c'||]_+^2 + w_reg * mean_c ||mu_c||``.
  The push margin is ``2 * delta_dist`` as in the original paper: with a pull radius of
  0.9 two clusters whose means are 2.0 apart cannot overlap, while a margin of 1.0 would
  allow pulled clusters to interpenetrate (and MeanShift with bandwidth 0.7 to merge them).
* **prototypical** on L2-normalised embeddings ``z``: prototypes are the L2-normalised
  means of ``z`` per instance; logits are ``-||z_i - p_c|| / tau`` over the instances of
  the voxel's own scene; cross-entropy to the voxel's own prototype.
* **graph**: every voxel's ``k`` nearest voxels of its scene (Euclidean on the grid, the
  voxel itself excluded); on edges joining two voxels of the same instance we maximise
  the scaled cosine similarity via ``softplus(-scale * cos) = -log sigmoid(scale * cos)``,
  which is ~0 (4.5e-5 at scale 10) for aligned embeddings and keeps a useful gradient
  for misaligned ones (unlike ``1 - cos``, whose gradient vanishes at cos = -1).
  Cross-instance edges are left to the other two terms, as the paper specifies.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field

from ..nn import knn_on_grid

__all__ = ["LossConfig", "instance_ids", "discriminative_loss", "prototypical_loss", "graph_loss",
           "multi_objective_loss"]


class LossConfig(BaseModel):
    """Weights and hyper-parameters of the three loss terms (SPEC §2 defaults)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    w_discriminative: float = Field(1.0, ge=0)
    w_prototypical: float = Field(1.0, ge=0)
    w_graph: float = Field(1.0, ge=0)
    delta_var: float = Field(0.9, ge=0)
    delta_dist: float = Field(1.0, ge=0)
    w_var: float = Field(0.8, ge=0)
    w_dist: float = Field(0.35, ge=0)
    w_reg: float = Field(1e-4, ge=0)
    push_margin_factor: float = Field(2.0, gt=0, description="means are pushed apart to factor * delta_dist")
    tau: float = Field(0.1, gt=0)
    graph_k: int = Field(8, ge=1)
    graph_scale: float = Field(10.0, gt=0)


@dataclass
class Instances:
    """Instance bookkeeping of a ragged batch (computed once, shared by the terms)."""

    inst: torch.Tensor  # (N,) instance index per voxel, 0..C-1
    scene_of_inst: torch.Tensor  # (C,) scene index (0..B-1) per instance
    count: torch.Tensor  # (C,) voxels per instance (float)
    scene: torch.Tensor  # (N,) scene index 0..B-1 per voxel
    num_scenes: int

    @property
    def num_instances(self) -> int:
        return int(self.scene_of_inst.numel())


def instance_ids(labels: torch.Tensor, batch: torch.Tensor) -> Instances:
    """Number the distinct (scene, label) pairs 0..C-1 (labels may repeat across scenes)."""
    scenes, scene = torch.unique(batch, return_inverse=True)
    lab_u, lab = torch.unique(labels, return_inverse=True)
    key = scene * lab_u.numel() + lab  # unique per (scene, label), no overflow for real sizes
    keys, inst = torch.unique(key, return_inverse=True)
    count = torch.bincount(inst, minlength=keys.numel()).to(torch.float32)
    return Instances(inst=inst, scene_of_inst=keys // lab_u.numel(), count=count, scene=scene,
                     num_scenes=int(scenes.numel()))


def _scene_mean(values: torch.Tensor, scene_of: torch.Tensor, num_scenes: int) -> torch.Tensor:
    """Mean over scenes of the per-scene mean of ``values`` (scenes without values are skipped)."""
    if values.numel() == 0:
        return values.sum() * 0.0  # keeps the graph (and dtype/device) for an empty term
    sums = values.new_zeros(num_scenes).index_add(0, scene_of, values)
    counts = values.new_zeros(num_scenes).index_add(0, scene_of, torch.ones_like(values))
    present = counts > 0
    return (sums[present] / counts[present]).mean()


def _instance_means(x: torch.Tensor, ins: Instances) -> torch.Tensor:
    sums = x.new_zeros((ins.num_instances, x.shape[1])).index_add(0, ins.inst, x)
    return sums / ins.count.to(x.dtype).unsqueeze(1)


def discriminative_loss(x: torch.Tensor, ins: Instances, cfg: LossConfig) -> dict[str, torch.Tensor]:
    """Pull (variance), push (distance) and regularisation terms; see the module docstring."""
    mu = _instance_means(x, ins)  # (C, D)
    # Pull: hinge on the distance to the own mean, averaged per instance, then per scene.
    d = (x - mu[ins.inst]).norm(dim=1)
    hinge = F.relu(d - cfg.delta_var).square()
    per_inst = x.new_zeros(ins.num_instances).index_add(0, ins.inst, hinge) / ins.count.to(x.dtype)
    l_var = _scene_mean(per_inst, ins.scene_of_inst, ins.num_scenes)
    # Push: all ordered pairs of distinct instances of the same scene (C is ~20 per scene).
    same = ins.scene_of_inst.unsqueeze(0) == ins.scene_of_inst.unsqueeze(1)
    same.fill_diagonal_(False)
    a, b = same.nonzero(as_tuple=True)
    margin = cfg.push_margin_factor * cfg.delta_dist
    # Pairwise distances via differences (no sqrt of a cancellation-prone |a|^2+|b|^2-2ab);
    # the clamp keeps the gradient finite for coinciding means.
    pair_d = (mu[a] - mu[b]).square().sum(dim=1).clamp_min(1e-12).sqrt()
    push = F.relu(margin - pair_d).square()
    l_dist = _scene_mean(push, ins.scene_of_inst[a], ins.num_scenes)
    # Regularisation: keep the means near the origin.
    l_reg = _scene_mean(mu.norm(dim=1), ins.scene_of_inst, ins.num_scenes)
    total = cfg.w_var * l_var + cfg.w_dist * l_dist + cfg.w_reg * l_reg
    return {"discriminative": total, "var": l_var, "dist": l_dist, "reg": l_reg}


def prototypical_loss(x: torch.Tensor, ins: Instances, cfg: LossConfig) -> torch.Tensor:
    """Cross-entropy of each voxel to its own instance prototype (normalised space)."""
    z = F.normalize(x, dim=1)
    proto = F.normalize(_instance_means(z, ins), dim=1)  # (C, D)
    # (N, C) Euclidean distances; the clamp keeps sqrt differentiable at 0 (a one-voxel
    # instance coincides with its prototype).
    d = (z.unsqueeze(1) - proto.unsqueeze(0)).square().sum(dim=2).clamp_min(1e-12).sqrt()
    logits = -d / cfg.tau
    # Only prototypes of the voxel's own scene compete.
    other_scene = ins.scene.unsqueeze(1) != ins.scene_of_inst.unsqueeze(0)
    logits = logits.masked_fill(other_scene, float("-inf"))
    ce = F.cross_entropy(logits, ins.inst, reduction="none")
    return _scene_mean(ce, ins.scene, ins.num_scenes)


def graph_neighbours(voxel_index: torch.Tensor, batch: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Edges (i, j) from each voxel to its ``k`` nearest voxels of the same scene (self excluded)."""
    knn, valid = knn_on_grid(voxel_index.to(torch.int64), batch.to(torch.int64), k + 1, return_valid=True)
    # Column 0 is the voxel itself (see knn_on_grid); padding columns are invalid.
    nb, ok = knn[:, 1:], valid[:, 1:]
    src = torch.arange(voxel_index.shape[0], device=voxel_index.device).unsqueeze(1).expand_as(nb)
    return src[ok], nb[ok]


def graph_loss(x: torch.Tensor, ins: Instances, src: torch.Tensor, dst: torch.Tensor, cfg: LossConfig) -> torch.Tensor:
    """``-log sigmoid(scale * cos)`` on same-instance k-NN edges, per-scene mean."""
    keep = ins.inst[src] == ins.inst[dst]
    src, dst = src[keep], dst[keep]
    cos = F.cosine_similarity(x[src], x[dst], dim=1, eps=1e-8)
    return _scene_mean(F.softplus(-cfg.graph_scale * cos), ins.scene[src], ins.num_scenes)


def multi_objective_loss(
    embeddings: torch.Tensor,
    labels: torch.Tensor,
    batch: torch.Tensor,
    voxel_index: torch.Tensor,
    cfg: LossConfig | None = None,
    *,
    edges: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Weighted sum of the three terms and a dict of their values (for logging).

    Args:
        embeddings: (N, D) network output.
        labels: (N,) int64 ground-truth object per voxel (unique within a scene).
        batch: (N,) int64 scene id per voxel.
        voxel_index: (N, 3) int64 grid indices (for the graph term's neighbours).
        cfg: loss hyper-parameters (SPEC defaults).
        edges: optional precomputed ``graph_neighbours(voxel_index, batch, cfg.graph_k)``;
            they depend only on the geometry, so callers may cache them per scene.
    """
    cfg = cfg or LossConfig()
    ins = instance_ids(labels, batch)
    disc = discriminative_loss(embeddings, ins, cfg)
    proto = prototypical_loss(embeddings, ins, cfg)
    src, dst = edges if edges is not None else graph_neighbours(voxel_index, batch, cfg.graph_k)
    graph = graph_loss(embeddings, ins, src, dst, cfg)
    total = cfg.w_discriminative * disc["discriminative"] + cfg.w_prototypical * proto + cfg.w_graph * graph
    parts = {k: float(v.detach()) for k, v in disc.items()}
    parts.update(prototypical=float(proto.detach()), graph=float(graph.detach()), total=float(total.detach()))
    return total, parts
