"""The network on a GPU gives the CPU's labels; asking for a GPU where there is none is a clear error."""

from __future__ import annotations

import pytest
import torch

from shadowcorr import ShadowCorrConfig, correspond, load_model
from shadowcorr.cli import main

from .scenes import sphere_scene

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


@needs_cuda
def test_network_on_cuda_gives_the_cpu_labels():
    bundle = sphere_scene([[0.0, 0.0, 45.0], [160.0, 30.0, 45.0]], [44.0, 40.0], width=160, height_px=90)
    config = ShadowCorrConfig(refine_poses=False)
    on_cpu = correspond(bundle, load_model(), config)
    on_gpu = correspond(bundle, load_model(device="cuda"), config)
    assert [s.object for s in on_gpu.segments] == [s.object for s in on_cpu.segments]


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA GPU")
def test_cuda_without_a_gpu_is_refused_by_name():
    with pytest.raises(ValueError, match="sees no CUDA GPU"):
        load_model(device="cuda")


def test_cli_refuses_an_unknown_device(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["correspond", "nowhere", "--device", "tpu"])
    assert exit_info.value.code == 2
    assert "expected cpu, cuda or cuda:N" in capsys.readouterr().err
