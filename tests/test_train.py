"""Tests of shadowcorr.train: losses, the scene cache, the training loop, resume and export."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from shadowcorr.io import write_bundle
from shadowcorr.nn import NetConfig, ShadowCorrNet, load_model
from shadowcorr.train import TrainConfig, Trainer, find_bundles, load_scene, prepare_scenes, save_scene
from shadowcorr.train.losses import (
    LossConfig,
    discriminative_loss,
    graph_loss,
    graph_neighbours,
    instance_ids,
    multi_objective_loss,
    prototypical_loss,
)
from shadowcorr.train.trainer import CHECKPOINT_FORMAT, init_from_model

from .scenes import sphere_scene


@pytest.fixture(autouse=True)
def _threads():
    # Shared, oversubscribed CI machine: with several threads every small op waits at an
    # OpenMP barrier for a descheduled thread (measured 100x slower); one thread is fastest.
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


# --------------------------------------------------------------------------- losses
def _blobs(centres: np.ndarray, n: int, spread: float, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Embeddings scattered around ``centres`` (one instance each) and a line of voxels."""
    rng = np.random.default_rng(seed)
    x = np.concatenate([c + spread * rng.standard_normal((n, centres.shape[1])) for c in centres])
    labels = np.repeat(np.arange(len(centres)), n)
    # Voxels of one instance form one contiguous run on a line, so k-NN edges are mostly same-instance.
    vox = np.stack([np.arange(len(x)), np.zeros(len(x)), np.zeros(len(x))], axis=1)
    return torch.tensor(x, dtype=torch.float32), torch.tensor(labels), torch.tensor(vox, dtype=torch.int64)


def test_losses_vanish_for_separated_embeddings_and_grow_for_mixed():
    d = 32
    centres = np.zeros((3, d))
    centres[0, 0], centres[1, 1], centres[2, 0] = 3.0, 3.0, -3.0  # > 2 * delta_dist apart, distinct directions
    x, y, v = _blobs(centres, 40, 0.0)
    batch = torch.zeros(len(x), dtype=torch.int64)
    total, parts = multi_objective_loss(x, y, batch, v)
    assert parts["var"] == 0.0 and parts["dist"] == 0.0
    assert parts["reg"] == pytest.approx(3.0, rel=1e-5)  # only the mean-norm regulariser remains (w 1e-4)
    assert parts["prototypical"] < 1e-3 and parts["graph"] < 1e-4
    assert total.item() < 2e-3

    # Same labels, embeddings drawn from one blob: every term is much larger.
    mixed, _, _ = _blobs(np.zeros((3, d)), 40, 1.0, seed=1)
    total_mixed, p = multi_objective_loss(mixed, y, batch, v)
    assert p["var"] > 0 and p["dist"] > 0.3 and p["prototypical"] > 0.5 and p["graph"] > 0.5
    assert total_mixed.item() > 100 * total.item()


def test_losses_are_per_scene_means_on_ragged_batches():
    # Two scenes that reuse label ids: the batched loss is the mean of the per-scene losses.
    xa, ya, va = _blobs(np.eye(4)[:2] * 2, 10, 0.5, seed=2)
    xb, yb, vb = _blobs(np.eye(4)[:3] * 1.5, 25, 0.7, seed=3)
    cfg = LossConfig()
    la, _ = multi_objective_loss(xa, ya, torch.zeros(len(xa), dtype=torch.int64), va, cfg)
    lb, _ = multi_objective_loss(xb, yb, torch.zeros(len(xb), dtype=torch.int64), vb, cfg)
    x = torch.cat([xa, xb]).requires_grad_(True)
    batch = torch.cat([torch.zeros(len(xa)), torch.ones(len(xb))]).long()
    lab = torch.cat([ya, yb])
    vox = torch.cat([va, vb])  # same coordinates in both scenes on purpose: neighbours stay inside a scene
    lab_ab, _ = multi_objective_loss(x, lab, batch, vox, cfg)
    assert lab_ab.item() == pytest.approx(0.5 * (la.item() + lb.item()), rel=1e-5)
    lab_ab.backward()
    assert torch.isfinite(x.grad).all()


def test_loss_terms_individually():
    cfg = LossConfig()
    # Two instances whose means are 1.0 apart (< margin 2.0): push = (2 - 1)^2, averaged over ordered pairs.
    x = torch.tensor([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [1.0, 0.0]])
    ins = instance_ids(torch.tensor([5, 5, 9, 9]), torch.zeros(4, dtype=torch.int64))
    parts = discriminative_loss(x, ins, cfg)
    assert parts["dist"].item() == pytest.approx(1.0)
    assert parts["var"].item() == 0.0
    # A voxel 2.0 from its mean (1.1 beyond delta_var) costs 1.1^2, averaged within its instance.
    x2 = torch.tensor([[0.0, 0.0], [4.0, 0.0], [10.0, 0.0], [10.0, 0.0]])
    var = discriminative_loss(x2, ins, cfg)["var"].item()
    assert var == pytest.approx(0.5 * (2 * 1.1**2 / 2), rel=1e-5)
    # Prototypical: a voxel exactly at its own prototype and far from the other is ~free.
    proto = prototypical_loss(torch.tensor([[1.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [-1.0, 0.0]]), ins, cfg)
    assert proto.item() < 1e-6
    # Graph: only same-instance edges count; opposite directions inside an instance are penalised.
    src, dst = torch.tensor([0, 1, 0]), torch.tensor([1, 0, 2])
    aligned = graph_loss(torch.tensor([[1.0, 0.0], [2.0, 0.0], [-1.0, 0.0], [0.0, 1.0]]), ins, src, dst, cfg)
    opposed = graph_loss(torch.tensor([[1.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), ins, src, dst, cfg)
    assert aligned.item() < 1e-4 and opposed.item() == pytest.approx(10.0, abs=1e-3)


def test_graph_neighbours_stay_within_scene_and_exclude_self():
    coords = torch.tensor([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 0, 0], [1, 0, 0]])
    batch = torch.tensor([0, 0, 0, 1, 1])
    src, dst = graph_neighbours(coords, batch, k=8)
    assert (src != dst).all()
    assert (batch[src] == batch[dst]).all()
    assert sorted(zip(src.tolist(), dst.tolist())) == [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1), (3, 4), (4, 3)]


# --------------------------------------------------------------------------- data and training
CENTRES = [[0.0, 0.0, 40.0], [110.0, 10.0, 40.0], [-20.0, 120.0, 50.0]]
RADII = [40.0, 40.0, 50.0]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    """Three small sphere scenes written as bundle directories (npy depth: fast to read)."""
    root = tmp_path_factory.mktemp("spheres")
    for i, shift in enumerate([0.0, 25.0, -30.0]):
        centres = np.array(CENTRES) + [shift, -shift, 0.0]
        bundle = sphere_scene(centres, RADII, cameras=4, start_deg=45.0 + 20 * i)
        write_bundle(bundle, root / f"scene_{i:05d}", depth_format="npy", mask_format="npy")
    return root


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("cache")


def _config(data_dir: Path, cache_dir: Path, out: Path, **kw) -> TrainConfig:
    base = dict(data=str(data_dir), val=str(data_dir), out=str(out), epochs=2, lr=3e-3, seed=7,
                neighbourhood="grid", workers=1, cache_dir=str(cache_dir), device="cpu")  # fmt: skip
    return TrainConfig(**{**base, **kw})


def test_scene_cache_round_trip_without_pickle(data_dir, cache_dir):
    bundles = find_bundles(data_dir)
    assert [b.name for b in bundles] == ["scene_00000", "scene_00001", "scene_00002"]
    scenes, summary = prepare_scenes(bundles, cache_dir=cache_dir, progress=False)
    assert summary["failures"] == 0 and len(scenes) == 3
    again, summary2 = prepare_scenes(bundles, cache_dir=cache_dir, progress=False)
    assert summary2["cached"] == 3 and summary2["prepared"] == 0
    ts = again[0]
    assert ts.target.shape == (ts.num_voxels,) and set(np.unique(ts.target)) <= {1, 2, 3}
    for f in cache_dir.glob("*.npz"):
        with np.load(f, allow_pickle=False) as z:  # raises if anything needed unpickling
            assert all(z[k].dtype != object for k in z.files)
    # Save/load keeps every array and the configuration.
    save_scene(cache_dir / "copy.npz", ts.scene, ts.target, ts.path)
    back = load_scene(cache_dir / "copy.npz")
    (cache_dir / "copy.npz").unlink()
    np.testing.assert_array_equal(back.scene.features, ts.scene.features)
    np.testing.assert_array_equal(back.scene.member_segment, ts.scene.member_segment)
    np.testing.assert_array_equal(back.scene.segment_truth, ts.scene.segment_truth)
    assert back.scene.config == ts.scene.config and back.scene.view_names == ts.scene.view_names


def test_tiny_training_lowers_the_loss_and_exports_a_loadable_model(data_dir, cache_dir, tmp_path):
    cfg = _config(data_dir, cache_dir, tmp_path / "run", epochs=3, lr=1e-2)
    record = Trainer(cfg, progress=False).run()
    losses = [e["loss"]["total"] for e in record["epochs"]]
    assert len(losses) == 3 and losses[-1] < losses[0], losses
    assert all("voxel_ari" in e["val"] and "average_purity" in e["val"] for e in record["epochs"])

    model = load_model(tmp_path / "run" / "model.safetensors")
    card = model.card
    assert card.architecture.neighbourhood == "grid"
    assert card.voxel_size == 8.0 and card.units == "cm" and len(card.features) == 16
    t = card.training
    assert t["lr"] == 1e-2 and t["optimizer"] == "Adam" and t["epochs"] == 3 and t["seed"] == 7
    assert t["best_epoch"] == record["best_epoch"] and t["training_time_s"] >= 0
    assert t["data"]["train"]["scenes_used"] == 3 and t["loss"]["prototypical"]["tau"] == 0.1
    assert "validation" in card.metrics and "voxel_ari" in card.metrics["validation"]
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["best_epoch"] == record["best_epoch"] and len(run["epochs"]) == 3


def test_resume_continues_at_the_right_epoch_with_identical_state(data_dir, cache_dir, tmp_path):
    # No validation set here (selection by training loss): resuming is about the training state.
    straight = Trainer(_config(data_dir, cache_dir, tmp_path / "a", epochs=2, val=None), progress=False)
    straight.run()
    Trainer(_config(data_dir, cache_dir, tmp_path / "b", epochs=1, val=None), progress=False).run()
    with pytest.raises(ValueError, match="--resume"):
        Trainer(_config(data_dir, cache_dir, tmp_path / "b", epochs=2, val=None), progress=False).run()
    saved = torch.load(tmp_path / "b" / "checkpoints" / "last.pt", weights_only=True)
    resumed = Trainer(_config(data_dir, cache_dir, tmp_path / "b", epochs=2, val=None), resume=True, progress=False)
    restored = {}
    original = resumed._load_checkpoint

    def spy() -> int:  # capture the state right after loading, before training goes on
        epoch = original()
        restored.update(epoch=epoch, opt=resumed.opt.state_dict(), model=resumed.net.state_dict())
        restored["opt"] = {p: {k: v.clone() for k, v in st.items()} for p, st in restored["opt"]["state"].items()}
        restored["model"] = {k: v.clone() for k, v in restored["model"].items()}
        return epoch

    resumed._load_checkpoint = spy
    record = resumed.run()
    assert restored["epoch"] == 1
    for p, st in saved["optimizer"]["state"].items():  # restored bit for bit
        for k, v in st.items():
            assert torch.equal(restored["opt"][p][k], v)
    for k, v in saved["model"].items():
        assert torch.equal(restored["model"][k], v)
    assert [e["epoch"] for e in record["epochs"]] == [1, 2] and record["resumed_at_epoch"] == [1]

    a = torch.load(tmp_path / "a" / "checkpoints" / "last.pt", weights_only=True)
    b = torch.load(tmp_path / "b" / "checkpoints" / "last.pt", weights_only=True)
    assert a["format"] == b["format"] == CHECKPOINT_FORMAT and a["epoch"] == b["epoch"] == 2
    # Same data order, same optimizer moments and step counts.  Values agree to float
    # rounding only: BLAS kernels may sum in a different order for differently aligned
    # (freshly loaded) tensors.
    for k in a["model"]:
        torch.testing.assert_close(a["model"][k], b["model"][k], rtol=1e-4, atol=1e-6)
    sa, sb = a["optimizer"]["state"], b["optimizer"]["state"]
    assert sa.keys() == sb.keys()
    for p in sa:
        assert float(sa[p]["step"]) == float(sb[p]["step"]) == 2 * 3  # 2 epochs x 3 scenes
        for k in sa[p]:
            torch.testing.assert_close(sa[p][k], sb[p][k], rtol=1e-4, atol=1e-8)
    assert a["optimizer"]["param_groups"] == b["optimizer"]["param_groups"]
    # A changed recipe cannot silently resume.
    with pytest.raises(ValueError, match="different configuration"):
        Trainer(_config(data_dir, cache_dir, tmp_path / "b", epochs=3, lr=1e-3, val=None), resume=True,
                progress=False).run()


def test_grid_network_initialised_from_reference_computes_the_reference(data_dir, cache_dir):
    ref = load_model()  # the packaged default (reference weights, neighbourhood "reference")
    if ref.card.architecture.neighbourhood != "reference":
        pytest.skip("packaged default is not a reference-neighbourhood model")
    net = ShadowCorrNet(NetConfig(neighbourhood="grid"))
    info = init_from_model(net, ref.path)
    assert info["zeroed_off_centre_taps"] == ["conv1", "conv2"]
    net.eval()
    (ts,), _ = prepare_scenes(find_bundles(data_dir, 1), cache_dir=cache_dir, progress=False)
    f = torch.from_numpy(ts.scene.features)
    v = torch.from_numpy(ts.scene.voxel_index)
    with torch.inference_mode():
        torch.testing.assert_close(net(f, v, 8.0), ref.net(f, v, 8.0), rtol=1e-4, atol=1e-5)


def test_train_subcommand_is_wired():
    from shadowcorr.cli import build_parser

    args = build_parser().parse_args(["train", "--data", "d", "--out", "o", "--epochs", "3", "--neighbourhood",
                                      "reference", "--resume", "--init", "m.pth"])  # fmt: skip
    assert args.command == "train" and args.epochs == 3 and args.lr == 5e-5 and args.resume and args.init == "m.pth"
