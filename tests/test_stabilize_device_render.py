"""The stabilize render on a torch device (``Renderer.device``: what ``--device cuda`` uses),
against the render with OpenCV's warps: the same frames out, within a grey level, with and
without the rolling shutter's row warps and the side-by-side ``--compare`` video; and which
device ``--device`` gives the render."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mosaic_cli.stabilize.render import Renderer
from mosaic_cli.stabilize.rolling import RollingCorrection
from mosaic_cli.video import open_video, probe

SIZE = (320, 180)
FRAMES = 12


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    from mosaic_cli.simulate import SimulateOptions, simulate_flight

    out = tmp_path_factory.mktemp("device_render") / "shaky.mp4"
    simulate_flight(out, None, SimulateOptions(profile="shaky", frames=FRAMES, size=SIZE, seed=3), show_progress=False)
    return out


def warps(n: int) -> np.ndarray:
    """A similarity a frame, a few px and a degree or so, with a slight perspective."""
    t = np.arange(n)
    a, s = np.radians(1.2 * np.sin(t)), 1.0 + 0.02 * np.cos(t)
    W = np.zeros((n, 3, 3))
    W[:, 0, 0], W[:, 0, 1], W[:, 0, 2] = s * np.cos(a), -s * np.sin(a), 3.3 * np.sin(0.7 * t)
    W[:, 1, 0], W[:, 1, 1], W[:, 1, 2] = s * np.sin(a), s * np.cos(a), -2.1 * np.cos(0.4 * t)
    W[:, 2, 0], W[:, 2, 2] = 1e-5, 1.0
    return W


class Rows:
    """A rolling shutter's per_row as the pipeline's RowWarpLater gives it: the CPU warp, and
    the correction the device warps with."""

    def __init__(self, rolling: RollingCorrection, border: str):
        from mosaic_cli.stabilize.render import BORDERS, YUV_BLACK

        self.rolling = rolling
        self._warp = rolling.warper(BORDERS[border], YUV_BLACK)

    def __call__(self, frame, t, warp):
        return self._warp(frame, t, warp)

    def correction(self):
        return self.rolling


def decoded(path) -> np.ndarray:
    with open_video(path, yuv420p=True) as stream:
        return np.stack(list(stream)).astype(np.int16)


@pytest.mark.parametrize("border, rows, compare", [("black", False, False), ("replicate", True, True), ("reflect", False, True)])
def test_the_device_render_writes_the_frames_opencv_writes(clip, tmp_path, border, rows, compare, monkeypatch):
    from mosaic_cli.stabilize import device_render

    streamed = []
    real = device_render.DeviceWarper.stream
    monkeypatch.setattr(device_render.DeviceWarper, "stream", lambda self, items, depth=2: streamed.append(self.device) or real(self, items, depth))
    info = probe(clip)
    W = warps(FRAMES)
    per_row = None
    if rows:
        tau = np.arange(FRAMES)[:, None] + np.arange(8)[None] / 8
        bands = np.stack([3.0 * np.sin(2 * tau), 1.5 * np.cos(tau), 0.004 * np.sin(3 * tau), 0.002 * np.cos(tau)], -1)
        per_row = Rows(RollingCorrection(0.8, bands, SIZE, estimated=True), border)
    outs = {}
    for name, device in (("opencv", None), ("torch", "cpu")):
        out = tmp_path / f"{name}.mp4"
        side = tmp_path / f"{name}_side.mp4" if compare else None
        written = Renderer(border=border, crf=0, preset="ultrafast", device=device).render(
            clip, out, W, info, compare=side, show_progress=False, per_row=per_row)
        assert written == FRAMES
        outs[name] = (decoded(out), decoded(side) if side is not None else None)
    assert [str(d) for d in streamed] == ["cpu"]  # the torch render ran, once
    (a, a_side), (b, b_side) = outs["opencv"], outs["torch"]
    diff = np.abs(a - b)
    assert diff.mean() < 0.05 and diff.max() <= 2  # crf 0: what differs is the warps' last grey level
    assert np.abs(a - decoded(clip)).mean() > 2  # (the frames were warped: the input is not what came out)
    if compare:
        assert np.abs(a_side - b_side).mean() < 0.05


def test_the_render_warps_on_a_gpu_only_where_device_finds_one(monkeypatch):
    assert Renderer().warp_device() is None
    assert Renderer(device="cpu").warp_device() == "cpu"  # torch's CPU, asked for by name (tests)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert Renderer(device="auto").warp_device() is None
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert Renderer(device="auto").warp_device().startswith("cuda")


def test_stabilize_device_cpu_keeps_opencvs_render():
    from mosaic_cli.stabilize.pipeline import _render_device

    assert _render_device("cpu") is None
    assert _render_device("auto") == "auto" and _render_device("cuda") == "cuda"


def can_write_video() -> bool:
    """An encoder to make the clip with: ffmpeg's binary or PyAV (the GPU machine's training call
    carries neither; its throughput call carries PyAV)."""
    for name in ("imageio_ffmpeg", "av"):
        try:
            __import__(name)
            return True
        except ImportError:
            pass
    return False


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
@pytest.mark.skipif(not can_write_video(), reason="no video encoder here")
def test_the_gpu_render_writes_the_frames_opencv_writes(clip, tmp_path):
    info = probe(clip)
    W = warps(FRAMES)
    a_path, b_path = tmp_path / "cpu.mp4", tmp_path / "gpu.mp4"
    Renderer(crf=0, preset="ultrafast").render(clip, a_path, W, info, show_progress=False)
    Renderer(crf=0, preset="ultrafast", device="cuda").render(clip, b_path, W, info, show_progress=False)
    diff = np.abs(decoded(a_path) - decoded(b_path))
    assert diff.mean() < 0.05 and diff.max() <= 2
