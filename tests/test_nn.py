"""Tests of shadowcorr.nn: sparse conv, k-NN attention, the network and model files.

(Over 500 lines on purpose: the tests of one package, sharing its fixtures and reference
implementations; the packaged-model file has its own tests in test_model_file.py.)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from shadowcorr.nn import (
    DEFAULT_MODEL_PATH,
    LocalAttention,
    ModelCard,
    NetConfig,
    ShadowCorrNet,
    SubmanifoldConv3d,
    VoxelHash,
    convert_checkpoint,
    kernel_offsets,
    knn_on_grid,
    knn_within_scene,
    load_model,
    neighbour_index,
    reference_card,
    run_batched,
    save_model,
)
from shadowcorr.nn import local_attention as la_mod

from .paths import REFERENCE_CHECKPOINT

REFERENCE_PTH = REFERENCE_CHECKPOINT


@pytest.fixture(autouse=True)
def _threads():
    # The machine is small and shared, and these tensors are tiny: one thread avoids
    # OpenMP spin-waiting when the cores are oversubscribed.
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


# --------------------------------------------------------------------------- helpers
def random_sparse(rng: np.random.Generator, n_scenes: int, side: int, density: float) -> tuple[np.ndarray, np.ndarray]:
    """Unique random voxels of a side^3 box per scene; scenes share coordinates on purpose."""
    coords, batch = [], []
    for b in range(n_scenes):
        occ = np.argwhere(rng.random((side, side, side)) < density)
        coords.append(occ - side // 2)
        batch.append(np.full(len(occ), b))
    return np.concatenate(coords).astype(np.int64), np.concatenate(batch).astype(np.int64)


def shell(radius: float, centre=(0, 0, 0), thickness: float = 1.0) -> np.ndarray:
    """Grid indices of a spherical shell: a voxel set shaped like a segment surface."""
    r = int(np.ceil(radius + thickness))
    g = np.stack(np.meshgrid(*[np.arange(-r, r + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    d = np.linalg.norm(g, axis=1)
    return (g[(d <= radius) & (d > radius - thickness)] + np.asarray(centre)).astype(np.int64)


def brute_knn(pos: np.ndarray, batch: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per point: same-scene points by (squared distance, row), self first; pad with self."""
    n = len(pos)
    idx = np.empty((n, k), np.int64)
    valid = np.ones((n, k), bool)
    for i in range(n):
        cand = np.flatnonzero(batch == batch[i])
        d = ((pos[cand] - pos[i]) ** 2).sum(1)
        d[cand == i] = -1
        order = cand[np.lexsort((cand, d))][:k]
        idx[i, : len(order)] = order
        idx[i, len(order) :] = i
        valid[i, len(order) :] = False
    return idx, valid


def randomise_bn(net: torch.nn.Module, seed: int = 0) -> None:
    """Non-trivial running statistics so that BatchNorm matters in eval-mode tests."""
    g = torch.Generator().manual_seed(seed)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm1d):
            m.running_mean.copy_(torch.randn(m.num_features, generator=g) * 0.3)
            m.running_var.copy_(torch.rand(m.num_features, generator=g) + 0.5)
            m.weight.data.copy_(torch.rand(m.num_features, generator=g) + 0.5)
            m.bias.data.copy_(torch.randn(m.num_features, generator=g) * 0.1)


def two_scenes(rng: np.random.Generator) -> tuple[list[np.ndarray], list[np.ndarray]]:
    idx = [
        np.concatenate([shell(4.0, (0, 0, 0)), shell(3.0, (9, 1, 0))]),
        np.concatenate([shell(3.5, (0, 0, 0)), shell(2.5, (-2, 7, 1))]),  # overlaps scene 0's coordinates
    ]
    feats = [rng.normal(size=(len(i), 16)).astype(np.float32) for i in idx]
    return feats, idx


# --------------------------------------------------------------------------- sparse conv
def test_kernel_offsets_order():
    o3, o5 = kernel_offsets(3), kernel_offsets(5)
    assert o3.shape == (27, 3) and o5.shape == (125, 3)
    assert o3[13].tolist() == [0, 0, 0] and o5[62].tolist() == [0, 0, 0]
    assert o3[0].tolist() == [-1, -1, -1] and o3[1].tolist() == [-1, -1, 0] and o3[9].tolist() == [0, -1, -1]
    with pytest.raises(ValueError):
        kernel_offsets(4)


@pytest.fixture(params=["dense", "sorted"])
def hash_mode(request, monkeypatch):
    """Run a test with both lookup strategies of VoxelHash."""
    if request.param == "sorted":
        monkeypatch.setattr(VoxelHash, "dense_cells", 0)
    return request.param


def test_neighbour_index_matches_dictionary_lookup(hash_mode):
    rng = np.random.default_rng(1)
    coords, batch = random_sparse(rng, 3, 6, 0.4)
    offsets = kernel_offsets(3)
    got = neighbour_index(torch.from_numpy(coords), torch.from_numpy(batch), offsets).numpy()
    table = {(int(b), *map(int, c)): i for i, (b, c) in enumerate(zip(batch, coords))}
    for o, off in enumerate(offsets.numpy()):
        want = [table.get((int(b), *map(int, c + off)), -1) for b, c in zip(batch, coords)]
        np.testing.assert_array_equal(got[o], want)


def test_neighbour_index_rejects_duplicates(hash_mode):
    coords = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 0, 0]])
    with pytest.raises(ValueError, match="duplicate voxel site"):
        neighbour_index(coords, torch.zeros(3, dtype=torch.int64), kernel_offsets(3))
    # The same coordinates in different scenes are fine.
    neighbour_index(coords, torch.tensor([0, 0, 1]), kernel_offsets(3))


@pytest.mark.parametrize("kernel_size,bias", [(3, False), (5, True)])
def test_sparse_conv_equals_dense_conv(kernel_size, bias, hash_mode):
    rng = np.random.default_rng(kernel_size)
    side = 7
    coords, batch = random_sparse(rng, 2, side, 0.3)
    cin, cout = 4, 5
    torch.manual_seed(0)
    conv = SubmanifoldConv3d(cin, cout, kernel_size, bias=bias).double()
    feats = torch.randn(len(coords), cin, dtype=torch.float64)
    out = conv(feats, torch.from_numpy(coords), torch.from_numpy(batch))

    # Dense reference: scatter into a zero grid, cross-correlate, read the input sites.
    r = kernel_size // 2
    shift = coords - coords.min(0)
    dense = torch.zeros(2, cin, side, side, side, dtype=torch.float64)
    dense[batch, :, shift[:, 0], shift[:, 1], shift[:, 2]] = feats
    # kernel[o, in, out] with o = lexicographic (dx, dy, dz) -> weight[out, in, dx+r, dy+r, dz+r]
    weight = conv.kernel.detach().reshape(kernel_size, kernel_size, kernel_size, cin, cout).permute(4, 3, 0, 1, 2)
    ref = F.conv3d(dense, weight, conv.bias.detach() if bias else None, padding=r)
    want = ref[batch, :, shift[:, 0], shift[:, 1], shift[:, 2]]
    torch.testing.assert_close(out, want, rtol=1e-10, atol=1e-10)


def test_sparse_conv_on_reference_positions_uses_only_centre_tap():
    # Positions in scene units (index * 8): no offset of reach <= 2 finds a voxel.
    idx = shell(4.0)
    conv = SubmanifoldConv3d(3, 4, 5)
    feats = torch.randn(len(idx), 3)
    batch = torch.zeros(len(idx), dtype=torch.int64)
    on_positions = conv(feats, torch.from_numpy(idx * 8), batch)
    centre_tap = feats @ conv.kernel[conv.centre]  # what a 'reference' network keeps: a per-voxel linear map
    torch.testing.assert_close(on_positions, centre_tap)
    # ...while on grid indices the neighbours do contribute.
    assert not torch.allclose(conv(feats, torch.from_numpy(idx), batch), centre_tap)


# --------------------------------------------------------------------------- k-NN / attention
@pytest.mark.parametrize("grid", [False, True])
def test_knn_equals_brute_force_and_stays_in_scene(grid, monkeypatch):
    rng = np.random.default_rng(3)
    sizes = [60, 5, 37]  # the middle scene is smaller than k
    batch = np.repeat([2, 0, 1], sizes)  # scene ids not sorted
    batch = rng.permutation(batch)  # and not contiguous
    if grid:  # integer positions: many exactly tied distances
        pos = rng.integers(-3, 4, size=(len(batch), 3)).astype(np.float64) * 8.0
    else:
        pos = rng.normal(size=(len(batch), 3))
    k = 9
    want_idx, want_valid = brute_knn(pos, batch, k)
    # Small blocks force the chunked path (several row blocks per scene).
    monkeypatch.setattr(la_mod, "_KNN_BLOCK", 100)
    got_idx, got_valid = knn_within_scene(torch.from_numpy(pos), torch.from_numpy(batch), k, return_valid=True)
    np.testing.assert_array_equal(got_idx.numpy(), want_idx)
    np.testing.assert_array_equal(got_valid.numpy(), want_valid)
    assert (batch[got_idx.numpy()] == batch[:, None]).all()
    assert (got_idx[:, 0].numpy() == np.arange(len(batch))).all()


@pytest.mark.parametrize("key_bits", [32, 64])
@pytest.mark.parametrize("radius_sq", [1, 4, 16])
def test_knn_on_grid_equals_brute_force(radius_sq, key_bits, monkeypatch, hash_mode):
    rng = np.random.default_rng(radius_sq)
    coords, batch = random_sparse(rng, 2, 9, 0.25)
    # Far-away isolated voxels and a tiny third scene exercise the brute-force fallback.
    coords = np.concatenate([coords, [[40, 0, 0], [0, -35, 3]], [[0, 0, 0], [5, 5, 5], [1, 0, 0]]])
    batch = np.concatenate([batch, [0, 1], [7, 7, 7]])
    perm = rng.permutation(len(batch))
    coords, batch = coords[perm], batch[perm]
    k = 12
    want_idx, want_valid = brute_knn(coords.astype(np.float64), batch, k)
    monkeypatch.setattr(la_mod, "_KNN_BLOCK", 2000)  # several row blocks
    if key_bits == 64:  # the keys of scenes beyond about 14 million voxels
        monkeypatch.setattr(la_mod, "_INT32_KEYS", 0)
    got_idx, got_valid = knn_on_grid(torch.from_numpy(coords), torch.from_numpy(batch), k, radius_sq=radius_sq, return_valid=True)
    np.testing.assert_array_equal(got_idx.numpy(), want_idx)
    np.testing.assert_array_equal(got_valid.numpy(), want_valid)


@pytest.mark.parametrize("n_scenes", [1, 3])
def test_site_major_int32_offset_lookup_is_the_transpose(n_scenes, hash_mode):
    coords, batch = random_sparse(np.random.default_rng(n_scenes), n_scenes, 8, 0.3)
    table = VoxelHash(torch.from_numpy(coords), torch.from_numpy(batch), reach=2)
    offsets = kernel_offsets(5)
    rows = torch.arange(0, len(batch), 3)
    want = table.offset_lookup(offsets, rows)  # (K, R) int64
    got = table.offset_lookup(offsets, rows, site_major=True, dtype=torch.int32)
    assert got.dtype == torch.int32 and (want >= 0).any() and (want < 0).any()
    np.testing.assert_array_equal(got.numpy(), want.T.numpy())
    with pytest.raises(ValueError, match="dtype"):
        table.offset_lookup(offsets, rows, dtype=torch.int16)


def test_voxel_hash_lookup_misses_outside_box_and_other_scenes(hash_mode):
    table = VoxelHash(torch.tensor([[0, 0, 0], [2, 1, 0], [0, 0, 1]]), torch.tensor([0, 0, 1]))
    q = torch.tensor([[2, 1, 0], [0, 0, 1], [0, 0, 1], [3, 1, 0], [-1, 0, 0], [2, 1, 0]])
    b = torch.tensor([0, 0, 1, 0, 0, 2])
    assert table.lookup(q, b).tolist() == [1, -1, 2, -1, -1, -1]


def test_knn_prefix_property():
    # The first k1 columns of the k2-NN are the k1-NN (the network relies on it).
    idx = torch.from_numpy(shell(4.0)).double()
    batch = torch.zeros(len(idx), dtype=torch.int64)
    torch.testing.assert_close(knn_within_scene(idx, batch, 32)[:, :16], knn_within_scene(idx, batch, 16))


def test_local_attention_matches_manual_and_masks_padding():
    torch.manual_seed(0)
    att = LocalAttention(8, 2, 4).double()
    pos = torch.tensor([[0, 0, 0], [1, 0, 0], [3, 0, 0], [0, 0, 0], [0, 2, 0]], dtype=torch.float64)
    batch = torch.tensor([0, 0, 0, 1, 1])  # scene 1 has 2 < k voxels
    x = torch.randn(5, 8, dtype=torch.float64)
    out = att(x, pos, batch)
    nbrs = {0: [0, 1, 2], 1: [1, 0, 2], 2: [2, 1, 0], 3: [3, 4], 4: [4, 3]}
    q, kk, v = att.to_q(x), att.to_k(x), att.to_v(x)
    for i, nb in nbrs.items():
        heads = []
        for h in range(2):
            s = slice(4 * h, 4 * h + 4)
            a = torch.softmax(kk[nb, s] @ q[i, s] / 2.0, 0)
            heads.append(a @ v[nb, s])
        torch.testing.assert_close(out[i], att.out_proj(torch.cat(heads)))


# --------------------------------------------------------------------------- network
def manual_reference_forward(sd: dict[str, torch.Tensor], feats: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Reference network written out per voxel in float64: centre taps only, k-NN by hand."""
    p = {k: v.double().numpy() for k, v in sd.items()}

    def bn(x, name):
        return (x - p[f"{name}.running_mean"]) / np.sqrt(p[f"{name}.running_var"] + 1e-5) * p[f"{name}.weight"] + p[f"{name}.bias"]

    def attn(x, name, k, heads):
        q, kk, v = x @ p[f"{name}.to_q.weight"].T, x @ p[f"{name}.to_k.weight"].T, x @ p[f"{name}.to_v.weight"].T
        dh = x.shape[1] // heads
        out = np.empty_like(x)
        pos = idx * 8.0  # positions in scene units
        for i in range(len(x)):
            d = ((pos - pos[i]) ** 2).sum(1)
            d[i] = -1
            nb = np.lexsort((np.arange(len(x)), d))[:k]
            for h in range(heads):
                s = slice(h * dh, (h + 1) * dh)
                logit = kk[nb, s] @ q[i, s] / np.sqrt(dh)
                w = np.exp(logit - logit.max())
                out[i, s] = (w / w.sum()) @ v[nb, s]
        return out @ p[f"{name}.out_proj.weight"].T + p[f"{name}.out_proj.bias"]

    x = bn(feats.astype(np.float64), "input_bn")
    x = np.maximum(bn(x @ p["conv1.kernel"][13], "bn1"), 0)
    x = attn(x, "local_attn1", 16, 4)
    x = np.maximum(bn(x @ p["conv2.kernel"][62], "bn2"), 0)
    x = attn(x, "local_attn2", 32, 8)
    return x @ p["conv3.kernel"] + p["conv3.bias"]


def test_reference_mode_equals_hand_written_centre_tap_network():
    model = load_model(REFERENCE_PTH)
    assert model.card.architecture.neighbourhood == "reference"
    rng = np.random.default_rng(5)
    idx = np.concatenate([shell(3.5), shell(2.5, (7, 0, 1))])
    feats = rng.normal(size=(len(idx), 16)).astype(np.float32)
    with torch.inference_mode():
        got = model.net(torch.from_numpy(feats), torch.from_numpy(idx), 8.0).numpy()
    sd = torch.load(REFERENCE_PTH, weights_only=True, map_location="cpu")
    want = manual_reference_forward(sd, feats, idx)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("neighbourhood", ["reference", "grid"])
def test_batched_equals_scenes_alone(neighbourhood):
    torch.manual_seed(1)
    net = ShadowCorrNet(NetConfig(neighbourhood=neighbourhood)).eval()
    randomise_bn(net)
    feats, idx = two_scenes(np.random.default_rng(2))
    with torch.inference_mode():
        alone = [net(torch.from_numpy(f), torch.from_numpy(i), 8.0) for f, i in zip(feats, idx)]
        both = net(
            torch.from_numpy(np.concatenate(feats)),
            torch.from_numpy(np.concatenate(idx)),
            8.0,
            torch.repeat_interleave(torch.tensor([0, 1]), torch.tensor([len(i) for i in idx])),
        )
    torch.testing.assert_close(both, torch.cat(alone), rtol=1e-5, atol=1e-5)


def test_grid_mode_differs_from_reference_mode():
    torch.manual_seed(1)
    grid = ShadowCorrNet(NetConfig(neighbourhood="grid")).eval()
    ref = ShadowCorrNet(NetConfig(neighbourhood="reference")).eval()
    state = grid.state_dict()  # the same weights; 'reference' keeps the centre taps of the kernels
    ref.load_state_dict({**state, "conv1.kernel": state["conv1.kernel"][grid.conv1.centre],
                         "conv2.kernel": state["conv2.kernel"][grid.conv2.centre]})
    feats, idx = two_scenes(np.random.default_rng(2))
    with torch.inference_mode():
        a = ref(torch.from_numpy(feats[0]), torch.from_numpy(idx[0]), 8.0)
        b = grid(torch.from_numpy(feats[0]), torch.from_numpy(idx[0]), 8.0)
    assert not torch.allclose(a, b, atol=1e-3)


def test_voxel_size_does_not_change_outputs():
    torch.manual_seed(1)
    net = ShadowCorrNet(NetConfig(neighbourhood="grid")).eval()
    feats, idx = two_scenes(np.random.default_rng(2))
    f, i = torch.from_numpy(feats[0]), torch.from_numpy(idx[0])
    with torch.inference_mode():
        torch.testing.assert_close(net(f, i, 8.0), net(f, i, 0.08), rtol=0, atol=0)


def test_grid_mode_trains():
    # Gradients reach every parameter through the gather / index_add paths.
    torch.manual_seed(0)
    net = ShadowCorrNet(NetConfig(neighbourhood="grid")).train()
    feats, idx = two_scenes(np.random.default_rng(9))
    out = net(
        torch.from_numpy(np.concatenate(feats)),
        torch.from_numpy(np.concatenate(idx)),
        8.0,
        torch.repeat_interleave(torch.tensor([0, 1]), torch.tensor([len(i) for i in idx])),
    )
    out.square().mean().backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name
    # Off-centre taps get gradient only in grid mode.
    assert net.conv1.kernel.grad[0].abs().sum() > 0 or net.conv1.kernel.grad[1].abs().sum() > 0


def test_net_config_validation():
    with pytest.raises(ValueError):
        NetConfig(widths=(30, 64))  # 30 not divisible by 4 heads
    with pytest.raises(ValueError):
        NetConfig(kernel_sizes=(3, 4))
    with pytest.raises(ValueError):
        NetConfig(neighbourhood="radius")


# --------------------------------------------------------------------------- files
def test_reference_checkpoint_and_its_converted_copy_agree(tmp_path):
    ref = load_model(REFERENCE_PTH)
    convert_checkpoint(REFERENCE_PTH, tmp_path / "ref.safetensors")
    converted = load_model(tmp_path / "ref.safetensors")
    assert converted.name == "shadowcorr-reference" and ref.name == converted.name
    assert converted.card.voxel_size == 8 and converted.card.units == "cm"
    assert "reference weights" in converted.card.notes
    assert len(converted.sha256) == 64 and converted.sha256 != ref.sha256
    assert not converted.net.training
    feats, idx = two_scenes(np.random.default_rng(4))
    a = run_batched(ref, feats, idx)
    b = run_batched(converted, feats, idx)
    for x, y in zip(a, b):
        assert x.dtype == np.float32 and x.shape[1] == 32
        np.testing.assert_array_equal(x, y)


def test_packaged_default_is_a_trained_model_with_its_card():
    default = load_model()
    assert default.card.voxel_size == 8 and default.card.units == "cm"
    assert default.card.training and default.card.metrics
    assert not default.net.training


def test_packaged_default_exists_and_carries_license():
    assert DEFAULT_MODEL_PATH.is_file()
    assert (DEFAULT_MODEL_PATH.parent / "LICENSE-reference").is_file()
    from safetensors import safe_open

    with safe_open(str(DEFAULT_MODEL_PATH), "pt") as f:
        meta = f.metadata()
    assert meta["format"] == "shadowcorr-model"
    assert "MIT License" in meta["license_text"]
    ModelCard.model_validate_json(meta["model_card"])


def test_run_batched_matches_single_scene_runs_and_handles_empty():
    torch.manual_seed(0)
    net = ShadowCorrNet(NetConfig(neighbourhood="grid")).eval()
    randomise_bn(net)
    from shadowcorr.nn import Model

    model = Model(net=net, card=reference_card().model_copy(update={"architecture": net.config}), sha256="0" * 64, device=torch.device("cpu"))
    feats, idx = two_scenes(np.random.default_rng(6))
    empty_f, empty_i = np.zeros((0, 16), np.float32), np.zeros((0, 3), np.int64)
    out = run_batched(model, [feats[0], empty_f, feats[1]], [idx[0], empty_i, idx[1]])
    assert [o.shape for o in out] == [(len(idx[0]), 32), (0, 32), (len(idx[1]), 32)]
    for o, f, i in zip([out[0], out[2]], feats, idx):
        np.testing.assert_allclose(o, run_batched(model, [f], [i])[0], rtol=1e-5, atol=1e-5)
    assert run_batched(model, [], []) == []
    with pytest.raises(ValueError, match="scene 1"):
        run_batched(model, [feats[0], feats[1][:, :15]], idx)
    with pytest.raises(ValueError, match="integer"):
        run_batched(model, feats[:1], [idx[0].astype(np.float64)])


def _reference_state() -> dict[str, torch.Tensor]:
    torch.manual_seed(0)
    return ShadowCorrNet().state_dict()


@pytest.mark.parametrize(
    "mutate,key",
    [
        (lambda sd: sd.pop("conv2.kernel"), "conv2.kernel"),
        (lambda sd: sd.__setitem__("conv1.kernel", torch.zeros(27, 16, 16)), "conv1.kernel"),
        (lambda sd: sd.__setitem__("extra.weight", torch.zeros(3)), "extra.weight"),
        (lambda sd: sd["bn1.weight"].fill_(float("nan")), "bn1.weight"),
        (lambda sd: sd.__setitem__("conv3.bias", torch.zeros(32, dtype=torch.int64)), "conv3.bias"),
    ],
)
def test_mismatched_state_dict_gives_clear_error(tmp_path, mutate, key):
    sd = _reference_state()
    mutate(sd)
    p = tmp_path / "bad.pth"
    torch.save(sd, p)
    with pytest.raises(ValueError, match=f"'{key}'"):
        load_model(p)


def test_unreadable_files_give_clear_errors(tmp_path):
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"this is not a checkpoint")
    with pytest.raises(ValueError, match="state dict"):
        load_model(junk)
    with pytest.raises(FileNotFoundError):
        load_model(tmp_path / "missing.safetensors")
    # A pickle that would run code is refused by weights_only loading.
    evil = tmp_path / "evil.pth"
    torch.save({"conv1.kernel": torch.zeros(1), "x": Path("/")}, evil)
    with pytest.raises(ValueError):
        load_model(evil)
    # safetensors without a model card
    from safetensors.torch import save_file

    nocard = tmp_path / "nocard.safetensors"
    save_file(_reference_state(), str(nocard))
    with pytest.raises(ValueError, match="model_card"):
        load_model(nocard)
    # truncated project file
    good = tmp_path / "good.safetensors"
    save_model(ShadowCorrNet(), reference_card(), good)
    trunc = tmp_path / "trunc.safetensors"
    trunc.write_bytes(good.read_bytes()[:-1000])
    with pytest.raises(ValueError):
        load_model(trunc)


def test_card_shape_mismatch_names_key(tmp_path):
    # A file whose card promises a different architecture than its tensors.
    p = tmp_path / "m.safetensors"
    save_model(ShadowCorrNet(), reference_card(), p)
    data = p.read_bytes()
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + n])
    card = json.loads(header["__metadata__"]["model_card"])
    card["architecture"]["embed_dim"] = 16
    header["__metadata__"]["model_card"] = json.dumps(card)
    head = json.dumps(header).encode()
    head += b" " * (-len(head) % 8)
    p.write_bytes(len(head).to_bytes(8, "little") + head + data[8 + n :])
    with pytest.raises(ValueError, match="'conv3.kernel'"):
        load_model(p)


def test_save_load_round_trip(tmp_path):
    torch.manual_seed(3)
    cfg = NetConfig(neighbourhood="grid")
    net = ShadowCorrNet(cfg).eval()
    randomise_bn(net)
    card = ModelCard(
        name="test-model",
        version="0.1",
        architecture=cfg,
        voxel_size=0.08,
        units="m",
        features=["f"] * 16,
        training={"steps": 1},
        metrics={"voxel_ari": 0.5},
        notes="round trip",
    )
    p1, p2 = tmp_path / "a.safetensors", tmp_path / "b.safetensors"
    sha = save_model(net, card, p1)
    assert save_model(net, card, p2) == sha and p1.read_bytes() == p2.read_bytes()  # deterministic
    m = load_model(p1)
    assert m.sha256 == sha and m.card == card and m.name == "test-model" and m.version == "0.1"
    for k, v in net.state_dict().items():
        assert torch.equal(v, m.net.state_dict()[k]), k
    feats, idx = two_scenes(np.random.default_rng(8))
    with torch.inference_mode():
        want = net(torch.from_numpy(feats[0]), torch.from_numpy(idx[0]), 0.08)
    np.testing.assert_array_equal(run_batched(m, feats[:1], idx[:1])[0], want.numpy())
    with pytest.raises(ValueError, match="architecture"):
        save_model(net, reference_card(), tmp_path / "c.safetensors")


def test_voxel_hash_squeezes_empty_stretches_and_keeps_every_lookup():
    # Clusters kilometres apart (in voxels), two scenes: the squeezed box is dense, and every
    # site + offset lookup and every arbitrary lookup answers what a dictionary of sites does.
    rng = np.random.default_rng(7)
    centres = np.array([[0, 0, 0], [125_000, 3, 0], [0, 125_000, 40], [250_000, 250_000, 1]])
    sites = {}
    for scene in (0, 1):
        for c in centres[: 3 + scene]:
            for p in np.unique(c + rng.integers(-6, 7, size=(60, 3)), axis=0):
                sites[(scene, *p.tolist())] = len(sites)
    keys = list(sites)
    coords = torch.tensor([k[1:] for k in keys], dtype=torch.int64)
    batch = torch.tensor([k[0] for k in keys], dtype=torch.int64)
    reach = 3
    table = VoxelHash(coords, batch, reach=reach)
    assert table.dense is not None  # unsqueezed, the box would hold about 1e15 cells
    offsets = torch.from_numpy(rng.integers(-reach, reach + 1, size=(40, 3)))
    got = table.offset_lookup(offsets)
    for o, off in enumerate(offsets.tolist()):
        want = [sites.get((k[0], k[1] + off[0], k[2] + off[1], k[3] + off[2]), -1) for k in keys]
        assert got[o].tolist() == want
    # Arbitrary queries: sites, points in the squeezed gaps, other scenes, outside every box.
    queries = [k[1:] for k in keys[::7]] + [[60_000, 0, 0], [0, 0, 20], [7, 7, 7], [-10**6, 0, 0], [125_000, 3, 0]]
    scenes = [k[0] for k in keys[::7]] + [0, 0, 1, 0, 2]
    found = table.lookup(torch.tensor(queries), torch.tensor(scenes))
    assert found.tolist() == [sites.get((b, *q), -1) for q, b in zip(queries, scenes)]
