"""stitch's canvas warps and multi-band blend in torch (mosaic_cli/stitch/device_blend.py, issue
39 item 4) against OpenCV's, on torch's CPU device:

- ``pyrDown``/``pyrUp`` of int16 images to the bit, of float weights within float rounding;
- the blenders against ``cv2.detail.MultiBandBlender``, ``FeatherBlender`` and ``Blender`` on
  the same textured images and masks (hard and soft edges, band counts 1-7, sharpnesses, canvas
  rectangles at the origin and offset), and the feather's L1 distance transform;
- compose's device warp of a tile against ``warp_into``/``_tile_part`` (shrunk sources, a
  use mask, a rolling shutter's row maps, exposure gains);
- compose and a whole ``stitch`` of a simulated flight with ``ComposeOptions(torch_device="cpu")``
  against OpenCV's path;
- ``--device``: which compose a stitch gets.

The CUDA test (marked ``cuda``) checks that the GPU gives the CPU torch path's result; it skips
without a GPU.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch
from test_stitch import fast_orb, fly

from conftest import textured_image
from mosaic_cli.errors import BadInput
from mosaic_cli.stitch import StitchOptions, stitch
from mosaic_cli.stitch import pipeline as stitch_pipeline
from mosaic_cli.stitch.compose import (
    ComposeOptions,
    PlacedImage,
    Roi,
    _device_part,
    _host_source,
    _seam_at,
    _tile_part,
    _upload,
    bounding_roi,
    compose,
)
from mosaic_cli.stitch.device_blend import FeatherBlender, MultiBandBlender, PlainBlender, distance_l1, pyr_down, pyr_up

pytestmark = pytest.mark.usefixtures("one_torch_thread")

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")


@pytest.fixture(scope="module")
def ground() -> np.ndarray:
    return textured_image(1024, 1024, seed=5)


def _inputs(ground: np.ndarray, roi: tuple[int, int, int, int], count: int, seed: int):
    """``count`` overlapping int16 images inside ``roi`` (x, y, w, h) with elliptic masks, one
    of them soft-edged (values between 0 and 255, as compose's resized seam masks have), each
    brightened or darkened, and a few pixels outside 0..255 (exposure gains never make them,
    but the blender takes any int16)."""
    rng = np.random.default_rng(seed)
    x0, y0, W, H = roi
    out = []
    for k in range(count):
        w, h = int(rng.integers(W // 3, W * 2 // 3)), int(rng.integers(H // 3, H * 2 // 3))
        x, y = x0 + int(rng.integers(0, W - w)), y0 + int(rng.integers(0, H - h))
        gx, gy = int(rng.integers(0, ground.shape[1] - w)), int(rng.integers(0, ground.shape[0] - h))
        image = (ground[gy:gy + h, gx:gx + w] * (0.8 + 0.4 * rng.random())).astype(np.int16)
        image[0, :3] = (-7, 300, 260)
        mask = np.zeros((h, w), np.uint8)
        cv2.ellipse(mask, (w // 2, h // 2), (w // 2 - 2, h // 2 - 2), 0, 0, 360, 255, -1)
        if k == 1:
            mask = cv2.GaussianBlur(mask, (9, 9), 0)
        out.append((image, mask, (x, y)))
    return out


def _blends(blenders: list, roi: tuple[int, int, int, int], inputs: list) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each of ``blenders`` prepared on ``roi``, fed the same ``inputs`` (:func:`_inputs`) in the
    same order, and blended: its (image, mask)."""
    for blender in blenders:
        blender.prepare(roi)
    for image, mask, tl in inputs:
        for blender in blenders:
            blender.feed(image, mask, tl)
    return [blender.blend(None, None) for blender in blenders]


# --- pyramids and the blender against OpenCV --------------------------------------------------


@pytest.mark.parametrize("size", [(1, 1), (1, 6), (2, 3), (7, 9), (33, 50), (64, 128)])
def test_pyramid_steps_are_opencv_s(size):
    rng = np.random.default_rng(size[0] * 100 + size[1])
    h, w = size
    image = rng.integers(-300, 300, (h, w, 3)).astype(np.int16)
    tensor = torch.from_numpy(image.astype(np.float32)).permute(2, 0, 1)
    down = pyr_down(tensor).permute(1, 2, 0).numpy()
    up = pyr_up(tensor).permute(1, 2, 0).numpy()
    assert np.array_equal(down.reshape(-1), cv2.pyrDown(image).astype(np.float32).reshape(-1))
    assert np.array_equal(up.reshape(-1), cv2.pyrUp(image).astype(np.float32).reshape(-1))
    weights = rng.random((h, w)).astype(np.float32)
    expected = cv2.pyrDown(weights).reshape(-1)
    assert np.abs(pyr_down(torch.from_numpy(weights), integer=False).numpy().reshape(-1) - expected).max() < 1e-6


@pytest.mark.parametrize("bands", [1, 3, 5, 7])
@pytest.mark.parametrize("roi,count", [((0, 0, 400, 300), 2), ((13, 27, 431, 290), 3), ((-40, 55, 350, 371), 4)])
def test_multiband_blender_matches_opencv(ground, bands, roi, count):
    blenders = [cv2.detail.MultiBandBlender(0, bands), MultiBandBlender(bands)]
    (expected, expected_mask), (result, result_mask) = _blends(blenders, roi, _inputs(ground, roi, count, seed=bands + count))
    assert result.dtype == np.int16 and result.shape == expected.shape == (roi[3], roi[2], 3)
    assert np.array_equal(result_mask, expected_mask)
    assert 0 < (expected_mask > 0).mean() < 1
    diff = np.abs(result.astype(int) - expected.astype(int))
    assert diff.mean() < 0.01 and np.percentile(diff, 99) <= 1 and diff.max() <= 2


def test_l1_distance_is_opencv_s():
    rng = np.random.default_rng(4)
    mask = np.where(rng.random((60, 80)) < 0.01, 0, 255).astype(np.uint8)
    mask[40:, :3] = 0
    expected = cv2.distanceTransform(mask, cv2.DIST_L1, 3)
    assert expected.max() > 5
    assert np.array_equal(distance_l1(torch.from_numpy(mask)).numpy(), expected)
    assert torch.isinf(distance_l1(torch.full((5, 7), 255, dtype=torch.uint8))).all()  # no zero: as far as can be


@pytest.mark.parametrize("sharpness", [0.02, 0.1, 0.5])
@pytest.mark.parametrize("roi,count", [((0, 0, 400, 300), 2), ((-40, 55, 350, 371), 4)])
def test_feather_and_plain_blenders_match_opencv(ground, sharpness, roi, count):
    blenders = [(cv2.detail.FeatherBlender(sharpness), FeatherBlender(sharpness)),
                (cv2.detail.Blender_createDefault(cv2.detail.Blender_NO), PlainBlender())]
    for pair in blenders:
        (expected, expected_mask), (result, result_mask) = _blends(list(pair), roi, _inputs(ground, roi, count, seed=count))
        assert result.dtype == np.int16 and result.shape == expected.shape
        assert np.array_equal(result_mask, expected_mask)  # the plain blender's soft mask values too
        assert np.abs(result.astype(int) - expected.astype(int)).max() <= 1


# --- compose's warps and compose itself ---------------------------------------------------------


def _rows(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A rolling shutter's row map of a kind compose gets: each row shifted and stretched."""
    return x + 0.01 * (y - 120) + 0.3 * np.sin(y / 20), y + 0.002 * y


@pytest.mark.parametrize("scale", [1.0, 0.5])  # 0.5: the source is shrunk first (INTER_AREA)
@pytest.mark.parametrize("use", [False, True])
@pytest.mark.parametrize("rows", [None, _rows])
def test_device_tile_part_is_opencv_s_warp(ground, scale, use, rows):
    image = ground[100:340, 200:520].copy()
    keep = None
    if use:  # an overlay's pixels are not drawn; the mask held smaller than the image, as scans hold it
        keep = np.full((120, 160), 255, np.uint8)
        keep[10:30, 100:150] = 0
    H = np.array([[0.95 * scale, 0.1 * scale, 50.3], [-0.08 * scale, 1.02 * scale, 31.7], [1e-4, 2e-5, 1.0]])
    roi = bounding_roi(H, (320, 240), (2000, 2000), 3.0 if rows else 0.0)
    assert roi is not None
    seam = np.zeros((roi.h // 4 + 1, roi.w // 4 + 1), np.uint8)
    seam[2:-5, 3:-2] = 255
    rng = np.random.default_rng(0)
    for gain, tolerance in ((None, 1), (np.array([[1.1]]), 2), (0.8 + 0.4 * rng.random((5, 6)), 2)):
        placed = PlacedImage(image, H, keep, rows)
        source, S = _upload(placed, roi, gain, seam, "cpu")
        _, small_seam, full_gain = _host_source(placed, roi, gain, seam)
        full_seam = _seam_at(small_seam, roi)
        for part in (roi, Roi(roi.x, roi.y + 7, roi.w, roi.h // 2 - 7), Roi(roi.x + 11, roi.y + 5, roi.w // 3, roi.h // 2)):
            expected, expected_mask = _tile_part(image, H, roi, part, full_gain, full_seam, keep, rows)
            warped, mask = _device_part(source, S, placed, roi, part)
            warped = warped.permute(1, 2, 0).numpy()
            # A gain scales the warp's one level of difference before rounding.
            diff = np.abs(warped - expected)
            assert diff.max() <= tolerance and diff.mean() < 0.01
            assert np.array_equal(mask.numpy(), expected_mask)
            assert 0 < (expected_mask > 0).mean() < 1


def _tiles(ground: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(1)
    tiles = []
    for k in range(9):
        x, y = 40 + 190 * (k % 3) + rng.uniform(-10, 10), 30 + 170 * (k // 3) + rng.uniform(-10, 10)
        H = np.array([[1.0, 0.02, x], [-0.02, 1.0, y], [1e-5, 0, 1]])
        gain = 0.85 + 0.3 * rng.random()  # uneven exposure, for the compensator to even out
        view = cv2.warpPerspective(ground, np.linalg.inv(H), (256, 200), flags=cv2.INTER_LINEAR)
        tiles.append((np.clip(view * gain, 0, 255).astype(np.uint8), H))
    return tiles


@pytest.mark.parametrize("blend", ["multiband", "feather", "none"])
@pytest.mark.parametrize("tile", [10**6, 64])  # one tile; 64-px tiles
def test_compose_on_torch_matches_opencv(ground, blend, tile):
    canvas = (700, 620)
    results = {}
    for device in (None, "cpu"):
        placed = [PlacedImage(image.copy(), H) for image, H in _tiles(ground)]
        results[device] = compose(placed, canvas, ComposeOptions(blend=blend, tile=tile, torch_device=device))
        assert all(p.image is None for p in placed)  # pixels dropped once drawn
    expected, result = results[None].astype(int), results["cpu"].astype(int)
    assert np.array_equal(result[..., 3], expected[..., 3])
    assert (expected[..., 3] == 255).mean() > 0.6
    diff = np.abs(result[..., :3] - expected[..., :3])
    assert diff.mean() < 0.01 and np.percentile(diff, 99) <= 1 and diff.max() <= 5


def test_a_torch_device_is_spelled_as_device():
    with pytest.raises(BadInput, match="--device"):
        ComposeOptions(torch_device="gpu")


def test_stitch_on_the_torch_path_gives_opencv_s_panorama(tmp_path, ground):
    flight = fly(tmp_path / "flight.mp4", ground, frames=60)
    panoramas = {}
    for device in (None, "cpu"):
        out = tmp_path / f"{device}.png"
        options = StitchOptions(compose=ComposeOptions(torch_device=device))
        stitch(flight.path, out, fast_orb(), options, show_progress=False)
        panoramas[device] = cv2.imread(str(out), cv2.IMREAD_UNCHANGED).astype(int)
    expected, result = panoramas[None], panoramas["cpu"]
    assert result.shape == expected.shape
    assert np.array_equal(result[..., 3], expected[..., 3])
    assert (expected[..., 3] == 255).mean() > 0.3
    diff = np.abs(result[..., :3] - expected[..., :3])
    assert diff.mean() < 1.0 and np.percentile(diff, 99) <= 2


def test_device_option_puts_compose_on_the_gpu_only(monkeypatch):
    options = StitchOptions(device="cpu")
    assert stitch_pipeline._compose_options(options).torch_device is None
    asked = dataclasses.replace(options, compose=ComposeOptions(torch_device="cpu"))
    assert stitch_pipeline._compose_options(asked).torch_device == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert stitch_pipeline._compose_options(StitchOptions(device="auto")).torch_device is None
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert stitch_pipeline._compose_options(StitchOptions(device="auto")).torch_device == "cuda"
    assert stitch_pipeline._compose_options(StitchOptions(device="cuda:0")).torch_device == "cuda:0"


@pytest.mark.cuda
@cuda
def test_compose_on_the_gpu_is_the_cpu_torch_path(ground):
    canvas = (700, 620)
    for blend in ("multiband", "feather"):
        results = {}
        for device in ("cpu", "cuda"):
            placed = [PlacedImage(image.copy(), H) for image, H in _tiles(ground)]
            options = ComposeOptions(blend=blend, tile=64, torch_device=device)
            results[device] = compose(placed, canvas, options).astype(int)
        assert np.array_equal(results["cuda"][..., 3], results["cpu"][..., 3])
        assert np.abs(results["cuda"] - results["cpu"]).max() <= 1
    roi = (13, 27, 431, 290)
    (a, a_mask), (b, b_mask) = _blends([MultiBandBlender(5, device) for device in ("cpu", "cuda")], roi, _inputs(ground, roi, 3, seed=9))
    assert np.array_equal(a_mask, b_mask) and np.abs(a.astype(int) - b.astype(int)).max() <= 1
