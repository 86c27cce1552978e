"""Training loop of ``shadowcorr train``: Adam on the multi-objective loss, selection by validation ARI.

Recipe (SPEC §2, Training): Adam, lr 5e-5, one scene per step (``batch_scenes``),
loss = discriminative + prototypical + graph (:mod:`.losses`), per-voxel target =
:func:`shadowcorr.evaluation.voxel_truth`.  After every epoch the network is validated
through the real inference path - :func:`shadowcorr.pipeline.assign` (MeanShift, small
cluster merge, majority vote) - and the epoch with the best mean validation voxel ARI
(ties: average purity) is kept.

Run directory (``--out``):

* ``run.json`` - the configuration, data summary, per-epoch losses / metrics / times,
  the best epoch; rewritten after every epoch.
* ``checkpoints/last.pt`` - model, optimizer, completed epochs, RNG states, best-so-far
  state: only tensors and primitive types, read with ``torch.load(weights_only=True)``.
  ``--resume`` continues from it exactly (same shuffles, same optimizer moments).
* ``model.safetensors`` - the best epoch's network with its complete model card
  (:func:`shadowcorr.nn.save_model`), rewritten whenever validation improves.

Determinism: the scene order of epoch ``e`` is a permutation drawn from a generator
seeded with ``(seed, e)``, so it does not depend on how many epochs ran before a resume;
the network has no other randomness after its seeded initialisation.
"""

from __future__ import annotations

import json
import math
import os
import platform
import time
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from .._version import __version__
from ..config import ShadowCorrConfig
from ..evaluation import summarize
from ..pipeline import assign
from ..nn import ModelCard, NetConfig, ShadowCorrNet, save_model
from ..nn.checkpoint import REFERENCE_FEATURES
from .dataset import TrainScene, find_bundles, prepare_scenes, training_pipeline
from .losses import LossConfig, graph_neighbours, multi_objective_loss
from .model_files import init_from_model

__all__ = ["TrainConfig", "Trainer", "train", "evaluate_scenes", "init_from_model", "CHECKPOINT_FORMAT"]

CHECKPOINT_FORMAT = "shadowcorr-train-checkpoint-1"
METRIC_KEYS = ("average_purity", "rock_purity", "cluster_purity", "voxel_ari", "perfect_one_to_one_share", "coverage")


class TrainConfig(BaseModel):
    """Everything that defines a training run (stored in run.json and the model card)."""

    model_config = ConfigDict(extra="forbid")

    data: str = Field(description="directory of training bundles")
    val: str | None = Field(None, description="directory of validation bundles (model selection)")
    test: str | None = Field(None, description="held-out bundles evaluated once with the best model at the end")
    out: str = Field(description="run directory")
    epochs: int = Field(10, ge=0)
    lr: float = Field(5e-5, gt=0)
    batch_scenes: int = Field(1, ge=1, description="scenes per optimizer step (paper: 1)")
    grad_clip: float | None = Field(None, gt=0, description="clip the gradient norm (off in the paper recipe)")
    neighbourhood: Literal["reference", "grid"] = "grid"
    seed: int = 0
    init: str | None = Field(None, description="model file to start from (e.g. the reference checkpoint)")
    device: str = Field("auto", description="'auto' (cuda when present), 'cpu', 'cuda', 'cuda:1', ...")
    workers: int = Field(2, ge=1, description="processes preparing scenes")
    cache_dir: str | None = None
    max_train_scenes: int | None = Field(None, ge=1)
    max_val_scenes: int | None = Field(None, ge=1)
    max_test_scenes: int | None = Field(None, ge=1)
    name: str = "shadowcorr-trained"
    version: str = "1.0"
    loss: LossConfig = Field(default_factory=LossConfig)
    pipeline: ShadowCorrConfig = Field(default_factory=training_pipeline)

    def resume_key(self) -> dict[str, Any]:
        """Fields that must not change between a run and its resumption (epochs may grow).

        Nested configurations are compared without their default-valued fields, so a
        field added to them later (whose default keeps the old behaviour) does not make
        an old run impossible to resume.
        """
        d = self.model_dump(mode="json")
        d["loss"] = self.loss.model_dump(mode="json", exclude_defaults=True)
        d["pipeline"] = self.pipeline.model_dump(mode="json", exclude_defaults=True)
        for k in ("epochs", "device", "workers", "cache_dir", "test", "max_test_scenes"):
            d.pop(k)
        return d


def resolve_device(spec: str) -> torch.device:
    if spec == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(spec)


# --------------------------------------------------------------------------- evaluation
@torch.inference_mode()
def embed_scene(net: ShadowCorrNet, ts: TrainScene, device: torch.device) -> np.ndarray:
    """Eval-mode embeddings of one prepared scene (the same computation as ``run_batched``)."""
    s = ts.scene
    f = torch.from_numpy(np.ascontiguousarray(s.features, dtype=np.float32)).to(device)
    v = torch.from_numpy(np.ascontiguousarray(s.voxel_index, dtype=np.int64)).to(device)
    return net(f, v, float(s.config.voxel_size)).float().cpu().numpy()


def evaluate_scenes(
    net: ShadowCorrNet, scenes: Sequence[TrainScene], device: torch.device | str = "cpu", *, progress: bool = False,
    desc: str = "validate",
) -> tuple[dict[str, dict[str, float]], list[dict[str, Any]]]:
    """Metrics of ``net`` on prepared scenes through the real ``assign`` path.

    Returns ``(summary, rows)``: per metric ``{"mean", "std", "n"}`` over the scenes, and
    the per-scene metric dicts.  The network is put in eval mode (and left there).
    """
    from tqdm import tqdm

    device = torch.device(device)
    was_training = net.training
    net.eval()
    rows = []
    for ts in tqdm(scenes, desc=desc, unit="scene", disable=not progress, leave=False):
        emb = embed_scene(net, ts, device)
        res = assign(ts.scene, emb, metrics=True)
        if res.metrics is not None:
            rows.append({"scene": ts.scene.name, "path": ts.path, **res.metrics})
    if was_training:
        net.train()
    summary = summarize([{k: r[k] for k in METRIC_KEYS if k in r} for r in rows])
    return summary, rows


def _dataset_info(directory: str | None, used: int) -> dict[str, Any] | None:
    """What the bundles under ``directory`` are: generator record (dataset.json) and count used."""
    if directory is None:
        return None
    info: dict[str, Any] = {"path": str(Path(directory).resolve()), "scenes_used": used}
    rec = Path(directory) / "dataset.json"
    if rec.is_file():
        try:
            d = json.loads(rec.read_text())
            info["generator"] = {k: d.get(k) for k in ("format", "shadowcorr_version", "seed", "n_scenes", "seed_rule",
                                                        "config")}  # fmt: skip
            if "field" in d:  # a field-distribution dataset (synth --field): the distribution, not one config
                info["generator"]["field"] = d["field"]
        except (OSError, ValueError):
            info["generator"] = "dataset.json unreadable"
    return info


class _Batch:
    """Tensors of one optimizer step (one or a few scenes concatenated)."""

    def __init__(self, scenes: Sequence[TrainScene], edges: Sequence[tuple[torch.Tensor, torch.Tensor]],
                 device: torch.device) -> None:
        sizes = [ts.num_voxels for ts in scenes]
        offsets = np.cumsum([0, *sizes[:-1]])
        self.features = torch.from_numpy(np.concatenate([ts.scene.features for ts in scenes]).astype(np.float32)).to(device)
        self.voxel_index = torch.from_numpy(np.concatenate([ts.scene.voxel_index for ts in scenes]).astype(np.int64)).to(device)
        self.target = torch.from_numpy(np.concatenate([ts.target for ts in scenes]).astype(np.int64)).to(device)
        self.batch = torch.repeat_interleave(torch.arange(len(scenes)), torch.tensor(sizes)).to(device)
        self.edges = (torch.cat([e[0] + int(o) for e, o in zip(edges, offsets)]).to(device),
                      torch.cat([e[1] + int(o) for e, o in zip(edges, offsets)]).to(device))
        self.voxel_size = float(scenes[0].scene.config.voxel_size)


# --------------------------------------------------------------------------- trainer
class Trainer:
    """One training run; see the module docstring.  ``Trainer(cfg).run()`` does everything."""

    def __init__(self, cfg: TrainConfig, *, resume: bool = False, progress: bool = True) -> None:
        self.cfg = cfg
        self.resume = resume
        self.progress = progress
        self.out = Path(cfg.out)
        self.ckpt_path = self.out / "checkpoints" / "last.pt"
        self.model_path = self.out / "model.safetensors"
        self.device = resolve_device(cfg.device)

    # ----------------------------------------------------------------- persistence
    def _write_json(self, record: dict[str, Any]) -> None:
        tmp = self.out / "run.json.tmp"
        tmp.write_text(json.dumps(record, indent=1, default=str))
        os.replace(tmp, self.out / "run.json")

    def _save_checkpoint(self, epoch: int) -> None:
        state = {
            "format": CHECKPOINT_FORMAT,
            "epoch": epoch,  # completed epochs
            "model": self.net.state_dict(),
            "optimizer": self.opt.state_dict(),
            "rng_torch": torch.get_rng_state(),
            "rng_cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
            "best_epoch": self.best_epoch,
            "best_score": list(self.best_score) if self.best_score is not None else [],
            "best_model": self.best_state if self.best_state is not None else {},
            "resume_key": json.dumps(self.cfg.resume_key(), sort_keys=True),
            "train_seconds": self.train_seconds,
        }
        self.ckpt_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.ckpt_path.with_suffix(".tmp")
        torch.save(state, tmp)
        os.replace(tmp, self.ckpt_path)

    def _load_checkpoint(self) -> int:
        ck = torch.load(self.ckpt_path, map_location="cpu", weights_only=True)
        if ck.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"{self.ckpt_path}: not a {CHECKPOINT_FORMAT} file")
        stored = json.loads(ck["resume_key"])
        # Older checkpoints stored the nested configs in full: normalise them the same way.
        stored["loss"] = LossConfig.model_validate(stored["loss"]).model_dump(mode="json", exclude_defaults=True)
        stored["pipeline"] = ShadowCorrConfig.model_validate(stored["pipeline"]).model_dump(mode="json", exclude_defaults=True)
        if json.dumps(stored, sort_keys=True) != json.dumps(self.cfg.resume_key(), sort_keys=True):
            raise ValueError(
                f"{self.ckpt_path}: the run was made with a different configuration; only --epochs, --device, "
                "--workers, --cache and --test may change on --resume"
            )
        self.net.load_state_dict(ck["model"])
        self.opt.load_state_dict(ck["optimizer"])
        torch.set_rng_state(ck["rng_torch"])
        if ck["rng_cuda"] and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(ck["rng_cuda"])
        self.best_epoch = int(ck["best_epoch"])
        self.best_score = tuple(ck["best_score"]) if ck["best_score"] else None
        self.best_state = ck["best_model"] or None
        self.train_seconds = float(ck["train_seconds"])
        return int(ck["epoch"])

    # ----------------------------------------------------------------- model card
    def card(self, metrics: dict[str, Any]) -> ModelCard:
        cfg = self.cfg
        training = {
            "framework": f"shadowcorr {__version__} `shadowcorr train`, torch {torch.__version__}",
            "loss": {
                "discriminative": {"weight": cfg.loss.w_discriminative, "delta_var": cfg.loss.delta_var,
                                   "delta_dist": cfg.loss.delta_dist, "push_margin": cfg.loss.push_margin_factor * cfg.loss.delta_dist,
                                   "w_var": cfg.loss.w_var, "w_dist": cfg.loss.w_dist, "w_reg": cfg.loss.w_reg},
                "prototypical": {"weight": cfg.loss.w_prototypical, "tau": cfg.loss.tau},
                "graph": {"weight": cfg.loss.w_graph, "k": cfg.loss.graph_k, "scale": cfg.loss.graph_scale,
                          "form": "-log sigmoid(scale * cos) on same-instance k-NN edges"},
            },  # fmt: skip
            "target": "per-voxel object with the highest summed segment confidence (evaluation.voxel_truth)",
            "optimizer": "Adam",
            "lr": cfg.lr,
            "batch": f"{cfg.batch_scenes} scene(s) per step",
            "grad_clip": cfg.grad_clip,
            "epochs": self.epochs_done,
            "best_epoch": self.best_epoch,
            "seed": cfg.seed,
            "init": self.init_info,
            "model_selection": "mean validation voxel ARI (ties: average purity), via assign()",
            "data": {"train": self.data_info.get("train"), "val": self.data_info.get("val"),
                     "test": self.data_info.get("test")},
            "pipeline_config": cfg.pipeline.model_dump(mode="json"),
            "training_time_s": round(self.train_seconds, 1),
            "device": str(self.device),
            "host": platform.node() or "unknown",
        }  # fmt: skip
        return ModelCard(
            name=cfg.name,
            version=cfg.version,
            architecture=self.net.config,
            voxel_size=cfg.pipeline.voxel_size,
            units=cfg.pipeline.units,
            features=list(REFERENCE_FEATURES),
            training=training,
            metrics=metrics,
            notes=(f"Trained with `shadowcorr train` (neighbourhood '{cfg.neighbourhood}'). "
                   + ("Convolutions see true voxel-grid neighbours." if cfg.neighbourhood == "grid" else
                      "Centre-tap convolutions, as the reference computes (SPEC §3).")),
            license="MIT",
        )

    def _export(self, state: dict[str, torch.Tensor], metrics: dict[str, Any]) -> None:
        net = ShadowCorrNet(self.net.config)
        net.load_state_dict(state)
        save_model(net, self.card(metrics), self.model_path)

    # ----------------------------------------------------------------- run
    def _previous_run(self) -> dict[str, Any]:
        path = self.out / "run.json"
        return json.loads(path.read_text()) if self.resume and path.is_file() else {}

    def _train_bundles(self, previous: dict[str, Any]) -> list[Path]:
        """The training bundles; on resume exactly those of the interrupted run.

        A data directory may grow between a run and its resumption (a generator still
        writing); continuing on another scene set would silently change the run.
        """
        found = find_bundles(self.cfg.data, self.cfg.max_train_scenes)
        names = previous.get("train_bundles")
        if names is None and previous:  # runs logged before the list was recorded: the first N by name
            n = previous.get("data", {}).get("train", {}).get("scenes_used")
            return found[:n] if n else found
        if names is None:
            return found
        by_name = {b.name: b for b in find_bundles(self.cfg.data)}
        missing = [n for n in names if n not in by_name]
        if missing:
            raise FileNotFoundError(f"--resume: training bundles of the run are gone: {missing[:5]}")
        return [by_name[n] for n in names]

    def _data(self, previous: dict[str, Any]) -> None:
        cfg = self.cfg
        t0 = time.perf_counter()
        self.data_info: dict[str, Any] = {}
        train_b = self._train_bundles(previous)
        self.train_scenes, s_train = prepare_scenes(train_b, cfg.pipeline, cfg.cache_dir, workers=cfg.workers,
                                                    progress=self.progress, desc="prepare train")
        # BatchNorm in training mode needs at least two voxels.
        self.train_scenes = [s for s in self.train_scenes if s.num_voxels >= 2]
        self.data_info["train"] = _dataset_info(cfg.data, len(self.train_scenes))
        self.val_scenes: list[TrainScene] = []
        if cfg.val:
            val_b = find_bundles(cfg.val, cfg.max_val_scenes)
            self.val_scenes, s_val = prepare_scenes(val_b, cfg.pipeline, cfg.cache_dir, workers=cfg.workers,
                                                    progress=self.progress, desc="prepare val")
            self.data_info["val"] = _dataset_info(cfg.val, len(self.val_scenes))
        if not self.train_scenes:
            raise ValueError(f"{cfg.data}: no usable training scene")
        self.prepare_seconds = time.perf_counter() - t0
        # Graph-loss edges depend only on the geometry: compute them once per scene.
        self.edges = [graph_neighbours(torch.from_numpy(ts.scene.voxel_index.astype(np.int64)),
                                       torch.zeros(ts.num_voxels, dtype=torch.int64), cfg.loss.graph_k)
                      for ts in self.train_scenes]  # fmt: skip

    def _epoch_order(self, epoch: int) -> list[int]:
        g = torch.Generator().manual_seed(self.cfg.seed * 1_000_003 + epoch)
        return torch.randperm(len(self.train_scenes), generator=g).tolist()

    def _train_epoch(self, epoch: int) -> dict[str, float]:
        from tqdm import tqdm

        self.net.train()
        order = self._epoch_order(epoch)
        bs = self.cfg.batch_scenes
        steps = [order[i : i + bs] for i in range(0, len(order), bs)]
        sums: dict[str, float] = {}
        bar = tqdm(steps, desc=f"epoch {epoch + 1}/{self.cfg.epochs}", unit="step", disable=not self.progress)
        for n, idx in enumerate(bar, 1):
            b = _Batch([self.train_scenes[i] for i in idx], [self.edges[i] for i in idx], self.device)
            emb = self.net(b.features, b.voxel_index, b.voxel_size, b.batch)
            loss, parts = multi_objective_loss(emb, b.target, b.batch, b.voxel_index, self.cfg.loss, edges=b.edges)
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            if self.cfg.grad_clip:
                torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.cfg.grad_clip)
            self.opt.step()
            for k, v in parts.items():
                sums[k] = sums.get(k, 0.0) + v
            bar.set_postfix(loss=f"{sums['total'] / n:.4f}")
        return {k: v / len(steps) for k, v in sums.items()}

    def run(self) -> dict[str, Any]:
        """Train (or resume), validate every epoch, export the best model; returns the run record."""
        cfg = self.cfg
        self.out.mkdir(parents=True, exist_ok=True)
        if self.ckpt_path.exists() and not self.resume:
            raise ValueError(f"{self.out} already holds a run; pass --resume to continue it or choose another --out")
        if self.resume and not self.ckpt_path.exists():
            raise FileNotFoundError(f"--resume: no checkpoint at {self.ckpt_path}")

        torch.manual_seed(cfg.seed)
        self.net = ShadowCorrNet(NetConfig(neighbourhood=cfg.neighbourhood))
        self.init_info = init_from_model(self.net, cfg.init) if cfg.init else "random (torch default init, seeded)"
        self.net.to(self.device)
        self.opt = torch.optim.Adam(self.net.parameters(), lr=cfg.lr)
        self.best_epoch, self.best_score, self.best_state = -1, None, None
        self.train_seconds = 0.0
        start = self._load_checkpoint() if self.resume else 0
        self.epochs_done = start

        previous = self._previous_run()
        self._data(previous)
        record: dict[str, Any] = {"format": "shadowcorr-train-run-1", "config": cfg.model_dump(mode="json"),
                                  "device": str(self.device), "init": self.init_info, "epochs": [],
                                  "train_bundles": [Path(ts.path).name for ts in self.train_scenes]}  # fmt: skip
        if previous:
            record["epochs"] = [e for e in previous.get("epochs", []) if e["epoch"] <= start]  # drop unsaved epochs
            record["resumed_at_epoch"] = previous.get("resumed_at_epoch", []) + [start]
        if start == 0 and cfg.init and self.val_scenes:
            # Epoch 0 = the starting model: selection keeps it when training never beats it.
            t1 = time.perf_counter()
            summary, _ = evaluate_scenes(self.net, self.val_scenes, self.device, progress=self.progress)
            means = {k: v["mean"] for k, v in summary.items()}
            self.best_score, self.best_epoch = (means.get("voxel_ari", -math.inf), means.get("average_purity", -math.inf)), 0
            self.best_state = {k: v.detach().to("cpu").clone() for k, v in self.net.state_dict().items()}
            record["epochs"].append({"epoch": 0, "loss": {}, "val": self._val_record(summary), "train_seconds": 0.0,
                                     "val_seconds": round(time.perf_counter() - t1, 2), "best": True})
            if self.progress:
                print(f"epoch 0 (--init model): val ARI {means.get('voxel_ari', float('nan')):.4f} "
                      f"avg purity {means.get('average_purity', float('nan')):.2f}", flush=True)
        record["data"] = {**self.data_info, "prepare_seconds": round(self.prepare_seconds, 1),
                          "train_voxels_mean": float(np.mean([s.num_voxels for s in self.train_scenes]))}  # fmt: skip

        for epoch in range(start, cfg.epochs):
            t0 = time.perf_counter()
            losses = self._train_epoch(epoch)
            t_train = time.perf_counter() - t0
            self.train_seconds += t_train
            t1 = time.perf_counter()
            val_summary: dict[str, dict[str, float]] = {}
            if self.val_scenes:
                val_summary, _ = evaluate_scenes(self.net, self.val_scenes, self.device, progress=self.progress)
            t_val = time.perf_counter() - t1
            means = {k: v["mean"] for k, v in val_summary.items()}
            # Without validation data the lowest training loss selects (a weaker criterion).
            score = ((means.get("voxel_ari", -math.inf), means.get("average_purity", -math.inf)) if self.val_scenes
                     else (-losses["total"], 0.0))  # fmt: skip
            improved = self.best_score is None or score > self.best_score
            self.epochs_done = epoch + 1
            if improved:
                self.best_score, self.best_epoch = score, epoch + 1
                self.best_state = {k: v.detach().to("cpu").clone() for k, v in self.net.state_dict().items()}
                self._export(self.best_state, {"validation": self._val_record(val_summary)})
            self._save_checkpoint(epoch + 1)
            entry = {"epoch": epoch + 1, "loss": losses, "val": self._val_record(val_summary),
                     "train_seconds": round(t_train, 2), "val_seconds": round(t_val, 2),
                     "seconds_per_scene": round(t_train / len(self.train_scenes), 4), "best": improved}  # fmt: skip
            record["epochs"].append(entry)
            record["best_epoch"] = self.best_epoch
            record["train_seconds"] = round(self.train_seconds, 1)
            self._write_json(record)
            if self.progress:
                v = f"val ARI {means.get('voxel_ari', float('nan')):.4f} avg purity {means.get('average_purity', float('nan')):.2f}"
                print(f"epoch {epoch + 1}: loss {losses['total']:.4f} ({t_train:.0f} s), {v}{' *' if improved else ''}",
                      flush=True)

        if self.best_state is None:  # zero epochs (e.g. evaluating an --init model): the start state
            self.best_state = {k: v.detach().to("cpu").clone() for k, v in self.net.state_dict().items()}
            self.best_epoch = self.epochs_done
        metrics = self._final_metrics(record)
        self._export(self.best_state, metrics)
        record["model"] = {"path": str(self.model_path), "metrics": metrics}
        self._write_json(record)
        return record

    @staticmethod
    def _val_record(summary: dict[str, dict[str, float]]) -> dict[str, Any]:
        return {k: {"mean": round(v["mean"], 5), "std": round(v["std"], 5)} for k, v in summary.items()
                if k in METRIC_KEYS} | ({"scenes": next(iter(summary.values()))["n"]} if summary else {})

    def _final_metrics(self, record: dict[str, Any]) -> dict[str, Any]:
        """Best epoch's validation figures, plus the test set when given."""
        metrics: dict[str, Any] = {}
        best = [e for e in record["epochs"] if e["epoch"] == self.best_epoch]
        if best and best[0]["val"]:
            metrics["validation"] = {**best[0]["val"], "epoch": self.best_epoch}
        if self.cfg.test:
            net = ShadowCorrNet(self.net.config).to(self.device)
            net.load_state_dict(self.best_state)
            test_b = find_bundles(self.cfg.test, self.cfg.max_test_scenes)
            scenes, _ = prepare_scenes(test_b, self.cfg.pipeline, self.cfg.cache_dir, workers=self.cfg.workers,
                                       progress=self.progress, desc="prepare test")
            summary, rows = evaluate_scenes(net, scenes, self.device, progress=self.progress, desc="test")
            metrics["synthetic_test"] = self._val_record(summary)
            self.data_info["test"] = _dataset_info(self.cfg.test, len(scenes))
            (self.out / "test_scenes.json").write_text(json.dumps(rows, indent=1))
        return metrics


def train(cfg: TrainConfig, *, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    """Run a training job; see :class:`Trainer`."""
    return Trainer(cfg, resume=resume, progress=progress).run()
