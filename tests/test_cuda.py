"""The CUDA path, run where a GPU is (``python -m benchmarks gpu`` runs ``pytest -m cuda`` on the lent
machine); every test here skips cleanly without one, as in CI.

- ``lstm`` and ``cnn`` on cuda agree with the fp32 CPU path on a flight over real imagery (a
  carried still when there is one, else a procedural map): the networks alone within 0.5 px
  (1280x720-equivalent; the GPU's convolutions may run in TF32, 10 mantissa bits: about 1e-3 of
  offsets of tens of px), and the default path (the polish settles both) within 0.1 px;
- the LSTM state is carried across chunks on the GPU exactly as on the CPU: chunks of 4 and of
  16 pairs give the same estimates;
- one training step of every variant under mixed precision: finite terms, finite non-zero
  gradients;
- a one-process nccl DistributedDataParallel step gives the gradients of the plain model;
- the int8 ranges and head error of a net on the GPU (what ``mosaic train --device cuda`` stores
  in its final weights) are those of the same net on the CPU, and the net stays on the GPU;
- the benchmark warms the GPU up before timing and times chunks of 1, 16 and 64 pairs.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

import numpy as np
import pytest
import torch

pytestmark = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")]

STILLS = Path(__file__).resolve().parents[1] / ".gpu" / "stills"


@pytest.fixture(scope="module")
def flight():
    """A fast flight (10-20 px a frame) of 49 frames at 640x360 over real imagery when carried."""
    from mosaic_cli.simulate import SimulateOptions, load_map, plan_simulated_flight, render_frames

    still = next(iter(sorted(STILLS.glob("*.jpg"))), None) if STILLS.is_dir() else None
    ground = load_map(still, seed=3)
    plan = plan_simulated_flight((ground.shape[1], ground.shape[0]), SimulateOptions(profile="fast", frames=49, size=(640, 360), seed=3))
    return list(render_frames(ground, plan)), plan.pairwise


def estimates(name: str, frames, device: str, **options):
    from mosaic_cli.estimators import make_estimator

    est = make_estimator(name, device=device, **options)
    est.reset((frames[0].shape[1], frames[0].shape[0]))
    out = []
    for f in frames:
        out += est.feed(f)
    out += est.finish()
    return np.array([e.H for e in out]), np.array([e.confidence for e in out])


def corner_gap(A: np.ndarray, B: np.ndarray, size=(640, 360)) -> np.ndarray:
    from mosaic_cli.geometry import corner_error

    scale = 1280.0 / size[0]
    return np.array([corner_error(a, b, size) for a, b in zip(A, B)]) * scale


@pytest.mark.parametrize("name", ["lstm", "cnn"])
def test_cuda_agrees_with_the_fp32_cpu_path(flight, name):
    frames, truth = flight
    alone = {"refine": "none", "fallback": "none"}
    cpu, _ = estimates(name, frames, "cpu", precision="fp32", **alone)
    gpu, _ = estimates(name, frames, "cuda", **alone)
    assert corner_gap(cpu, gpu).max() < 0.5
    cpu_default, cpu_conf = estimates(name, frames, "cpu", precision="fp32")
    gpu_default, gpu_conf = estimates(name, frames, "cuda")
    assert np.median(corner_gap(cpu_default, gpu_default)) < 0.1
    assert np.mean(corner_gap(gpu_default, truth) < 10) >= np.mean(corner_gap(cpu_default, truth) < 10) - 0.03


def test_the_lstm_state_is_carried_across_chunks_on_the_gpu(flight):
    frames, _ = flight
    alone = {"refine": "none", "fallback": "none"}
    small, _ = estimates("lstm", frames, "cuda", chunk=4, **alone)
    large, _ = estimates("lstm", frames, "cuda", chunk=16, **alone)
    assert corner_gap(small, large).max() < 0.05
    reset, _ = estimates("lstm", frames, "cuda", chunk=4, reset_every=4, **alone)
    assert corner_gap(small, reset).max() > corner_gap(small, large).max()  # the carried state matters


@pytest.mark.parametrize("variant", ["base", "reg-p", "reg-s", "reg-t", "reg-all", "lstm", "lstm-reg-t", "lstm-reg-all"])
def test_one_mixed_precision_training_step_of_every_variant(variant):
    from mosaic_cli.model import HomographyNet, NetConfig
    from mosaic_cli.train.loop import AutocastNet
    from mosaic_cli.train.objective import Objective

    torch.manual_seed(0)
    objective = Objective(variant, patch=64)
    net = HomographyNet(NetConfig(preset="compact", head=objective.head, patch=64)).cuda()
    model = AutocastNet(net, torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16)
    K = objective.window
    frames = torch.rand(2, K, 1, 96, 128, device="cuda") * 2 - 1
    positions = torch.randint(0, 32, (2, objective.positions, 2), device="cuda")
    terms = objective(model, {"frames": frames, "positions": positions})
    terms["total"].backward()
    assert all(torch.isfinite(v).item() for v in terms.values())
    grads = [p.grad for p in net.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all().item() for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0


def test_a_one_process_nccl_ddp_step_gives_the_plain_gradients():
    import torch.distributed as dist

    from mosaic_cli.model import HomographyNet, NetConfig
    from mosaic_cli.train.objective import Objective

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("nccl", rank=0, world_size=1)
    try:
        torch.manual_seed(1)
        objective = Objective("base", patch=64)
        net = HomographyNet(NetConfig(preset="compact", head="cnn", patch=64)).cuda().eval()
        twin = HomographyNet(NetConfig(preset="compact", head="cnn", patch=64)).cuda().eval()
        twin.load_state_dict(net.state_dict())
        frames = torch.rand(4, 2, 1, 96, 128, device="cuda") * 2 - 1
        batch = {"frames": frames, "positions": torch.randint(0, 32, (4, 1, 2), device="cuda")}
        ddp = torch.nn.parallel.DistributedDataParallel(net, device_ids=[torch.cuda.current_device()])
        objective(ddp, batch)["total"].backward()
        objective(twin, batch)["total"].backward()
        for a, b in zip(net.parameters(), twin.parameters()):
            # cuDNN's weight gradients sum in no fixed order (1.9e-6 apart on an H200 for a
            # gradient of 1e-3): the tolerance follows each tensor's scale; a wrong DDP
            # averaging would be off by whole factors.
            scale = float(b.grad.abs().max())
            torch.testing.assert_close(a.grad, b.grad, rtol=1e-3, atol=1e-4 * scale)
    finally:
        dist.destroy_process_group()


def test_the_gpu_benchmark_warms_the_device_up_and_times_chunks_of_1_16_and_64(flight):
    from mosaic_cli.bench.timing import gpu_batch, warm_up
    from mosaic_cli.estimators import make_estimator

    frames, _ = flight
    est = make_estimator("lstm", device="cuda")
    assert warm_up(est, frames, (640, 360)) > 0
    assert warm_up(make_estimator("lstm", device="cpu"), frames, (640, 360)) is None  # a CPU starts cold, as a command does
    batch = gpu_batch("lstm", 320, None, frames[:33], (640, 360))
    assert set(batch) == {"chunk_1", "chunk_16", "chunk_64"} and all(v["fps"] > 0 for v in batch.values())


def test_int8_calibration_of_a_net_on_the_gpu_is_that_of_its_cpu_copy():
    """The int8 LSTM exists only on the CPU: ``train --device cuda`` failed when it saved its
    final weights (quantized::make_quantized_cell_params_dynamic has no CUDA kernel)."""
    from mosaic_cli.model import HomographyNet, NetConfig, quantize

    if quantize.engine() is None:
        pytest.skip("this PyTorch has no int8 engine")
    torch.manual_seed(0)
    cpu = HomographyNet(NetConfig(head="lstm", patch=64)).eval()
    gpu = HomographyNet(NetConfig(head="lstm", patch=64)).eval()
    gpu.load_state_dict(cpu.state_dict())
    gpu.cuda()
    pairs = torch.rand(16, 2, 64, 64, generator=torch.Generator().manual_seed(1)) * 2 - 1
    on_cpu = quantize.calibrate(cpu, pairs)
    on_gpu = quantize.calibrate(gpu, pairs.cuda())
    assert on_gpu["head_error"] == on_cpu["head_error"]
    assert on_gpu["activations"] == on_cpu["activations"]
    assert all(p.is_cuda for p in gpu.parameters())
