"""The torch warps (geometry/warp.py) and the render's device warper (stabilize/device_render.py),
checked on the CPU against OpenCV's warpPerspective and remap and against the render's own
warps (render.warp_yuv, render.warp_frame, RollingCorrection.warper): within one grey level
everywhere, borders included, on pixel-scale noise, a procedural texture and a real photo.
One CUDA test (skipped without a GPU) checks that the GPU gives what the CPU gives."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from conftest import textured_image
from mosaic_cli.geometry.warp import border_index, perspective_maps, remap, remap_nearest, warp_perspective, warp_yuv420
from mosaic_cli.stabilize.device_render import DeviceWarper
from mosaic_cli.stabilize.render import BORDERS, YUV_BLACK, warp_frame, warp_yuv
from mosaic_cli.stabilize.rolling import RollingCorrection

pytestmark = pytest.mark.usefixtures("one_torch_thread")

CV_BORDERS = {"constant": cv2.BORDER_CONSTANT, "replicate": cv2.BORDER_REPLICATE, "reflect": cv2.BORDER_REFLECT}
RENDER_BORDER = {"black": "constant", "replicate": "replicate", "reflect": "reflect"}
SRC = (160, 120)  # (w, h) of the source images
DST = (150, 130)  # of the outputs: not the source's, so that a swapped axis shows
VALUE = 37.0  # the constant border's value: neither 0 nor a level the images are full of


def _opencv_samples_exactly() -> bool:
    """OpenCV 4.11 and later sample at the exact coordinate; earlier ones round it to 1/32 px,
    which moves an output by up to 255/64 levels on pixel-scale detail."""
    step = np.array([[0, 0, 255, 255]], np.uint8)
    shift = np.array([[1.0, 0.0, -3 / 128], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    out = cv2.warpPerspective(step, shift, (4, 1), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return int(out[0, 1]) == 6  # 255 * 3/128 = 5.98 exactly; 255 / 32 = 7.97 at 1/32 px


exact_opencv = pytest.mark.skipif(not _opencv_samples_exactly(), reason="this OpenCV rounds coordinates to 1/32 px (before 4.11)")


def _images() -> dict[str, np.ndarray]:
    w, h = SRC
    noise = np.random.default_rng(0).integers(0, 256, (h, w), dtype=np.uint8)
    texture = cv2.cvtColor(textured_image(w, h, seed=3), cv2.COLOR_RGB2GRAY)
    return {"noise": noise, "texture": texture}


IMAGES = _images()


def _photo(shared_data) -> np.ndarray:
    photo = cv2.imread(str(shared_data / "aerial_stills" / "opencv_aero" / "aero1.jpg"), cv2.IMREAD_GRAYSCALE)
    assert photo is not None
    return np.ascontiguousarray(photo[100:100 + SRC[1], 200:200 + SRC[0]])


def _rotation(angle: float, scale: float, centre: tuple[float, float], shift: tuple[float, float]) -> np.ndarray:
    c, s = scale * np.cos(angle), scale * np.sin(angle)
    cx, cy = centre
    return np.array([[c, -s, cx - c * cx + s * cy + shift[0]], [s, c, cy - s * cx - c * cy + shift[1]], [0.0, 0.0, 1.0]])


WARPS = {
    "identity": np.eye(3),
    "translation": np.array([[1.0, 0.0, 6.37], [0.0, 1.0, -4.61], [0.0, 0.0, 1.0]]),
    "rotation_scale": _rotation(0.3, 1.15, (80.0, 60.0), (-5.3, 8.2)),
    "perspective": np.array([[0.97, 0.05, 9.3], [-0.03, 1.04, -6.1], [6e-4, -4e-4, 1.0]]),
}


def _taps_inside(M: np.ndarray, dsize: tuple[int, int], size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the output pixels whose four bilinear taps all lie inside / all outside the source."""
    w, h = size
    xs, ys = np.meshgrid(np.arange(dsize[0], dtype=np.float64), np.arange(dsize[1], dtype=np.float64))
    Mi = np.linalg.inv(M)
    z = Mi[2, 0] * xs + Mi[2, 1] * ys + Mi[2, 2]
    x = (Mi[0, 0] * xs + Mi[0, 1] * ys + Mi[0, 2]) / z
    y = (Mi[1, 0] * xs + Mi[1, 1] * ys + Mi[1, 2]) / z
    x0, y0 = np.floor(x), np.floor(y)
    inside = (x0 >= 0) & (x0 + 1 <= w - 1) & (y0 >= 0) & (y0 + 1 <= h - 1)
    outside = (x0 + 1 < 0) | (x0 > w - 1) | (y0 + 1 < 0) | (y0 > h - 1)
    return inside, outside


def _torch_warp(image: np.ndarray, M: np.ndarray, border: str) -> np.ndarray:
    out = warp_perspective(torch.from_numpy(image)[None, None], torch.from_numpy(M)[None], DST, border, VALUE)  # type: ignore[arg-type]
    return out[0, 0].numpy()


def _check_levels(got: np.ndarray, want: np.ndarray, inside: np.ndarray) -> None:
    diff = np.abs(got.astype(np.int16) - want.astype(np.int16))
    assert diff[inside].max() <= 1 and diff[inside].mean() < 0.02, (diff[inside].max(), diff[inside].mean())
    assert diff.max() <= 1 and diff.mean() < 0.02, (diff.max(), diff.mean())  # the borders as well


def _check_against_opencv(image: np.ndarray, name: str, border: str) -> None:
    M = WARPS[name]
    want = cv2.warpPerspective(image, M, DST, flags=cv2.INTER_LINEAR, borderMode=CV_BORDERS[border], borderValue=VALUE)
    got = _torch_warp(image, M, border)
    assert got.dtype == np.uint8 and got.shape == (DST[1], DST[0])
    inside, outside = _taps_inside(M, DST, SRC)
    assert inside.mean() > 0.5 and outside.any()  # every warp has a border to get right (the output is larger)
    _check_levels(got, want, inside)
    if border == "constant":
        assert np.all(got[outside] == VALUE)
    # the border modes differ there, so that the comparison above could tell them apart
    others = [b for b in CV_BORDERS if b != border]
    for other in others:
        assert np.abs(_torch_warp(image, M, other).astype(int) - want)[~inside].max() > 1
    # float32: the same sampling, unrounded
    want_f = cv2.warpPerspective(image.astype(np.float32), M, DST, flags=cv2.INTER_LINEAR, borderMode=CV_BORDERS[border], borderValue=VALUE)
    got_f = _torch_warp(image.astype(np.float32), M, border)
    assert got_f.dtype == np.float32
    assert np.abs(got_f - want_f).max() < 0.05


@exact_opencv
@pytest.mark.parametrize("border", list(CV_BORDERS))
@pytest.mark.parametrize("name", list(WARPS))
@pytest.mark.parametrize("kind", list(IMAGES))
def test_warp_perspective_matches_opencv(kind, name, border):
    _check_against_opencv(IMAGES[kind], name, border)


@exact_opencv
@pytest.mark.parametrize("border", list(CV_BORDERS))
@pytest.mark.parametrize("name", ["translation", "perspective"])
def test_warp_perspective_matches_opencv_on_a_photo(shared_data, name, border):
    _check_against_opencv(_photo(shared_data), name, border)


@exact_opencv
def test_warp_perspective_batch_and_channels():
    """Three images of three channels, each by its own warp, with a value per channel."""
    rgb = textured_image(*SRC, seed=5)
    images = np.stack([rgb, np.roll(rgb, 17, axis=1), IMAGES["noise"][..., None].repeat(3, -1)])
    Ms = np.stack([WARPS["translation"], WARPS["rotation_scale"], WARPS["perspective"]])
    value = (10.0, 200.0, 77.0)
    got = warp_perspective(torch.from_numpy(images).permute(0, 3, 1, 2), torch.from_numpy(Ms), DST, "constant", value)
    assert got.shape == (3, 3, DST[1], DST[0])
    for b in range(3):
        want = cv2.warpPerspective(images[b], Ms[b], DST, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=value)
        inside, outside = _taps_inside(Ms[b], DST, SRC)
        _check_levels(got[b].permute(1, 2, 0).numpy(), want, inside)
        assert np.all(got[b].permute(1, 2, 0).numpy()[outside] == np.array(value, np.uint8))


def _wobble_maps() -> tuple[np.ndarray, np.ndarray]:
    """Smooth float32 maps with a row-by-row wobble (as the rolling shutter's), partly off the image."""
    xs, ys = np.meshgrid(np.arange(DST[0], dtype=np.float32), np.arange(DST[1], dtype=np.float32))
    map_x = (1.08 * xs - 0.06 * ys - 7.3 + 2.5 * np.sin(ys / 9.0)).astype(np.float32)
    map_y = (0.95 * ys + 0.04 * xs - 3.9 + 0.8 * np.cos(ys / 7.0)).astype(np.float32)
    return map_x, map_y


@exact_opencv
@pytest.mark.parametrize("border", list(CV_BORDERS))
def test_remap_matches_opencv(border):
    """Smooth maps with a row-by-row wobble (as the rolling shutter's), partly off the image."""
    map_x, map_y = _wobble_maps()
    for image in (*IMAGES.values(), IMAGES["noise"].astype(np.float32)):
        want = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=CV_BORDERS[border], borderValue=VALUE)
        got = remap(torch.from_numpy(image)[None, None], torch.from_numpy(map_x)[None], torch.from_numpy(map_y)[None], border, VALUE)[0, 0].numpy()  # type: ignore[arg-type]
        assert got.dtype == image.dtype
        diff = np.abs(got.astype(np.float64) - want)
        assert diff.max() <= (1 if image.dtype == np.uint8 else 0.05) and diff.mean() < 0.02, (diff.max(), diff.mean())
    outside = (map_x < -1) | (map_y < -1)
    assert outside.any()
    if border == "constant":
        assert np.all(got[outside] == VALUE)


@pytest.mark.parametrize("border", list(CV_BORDERS))
def test_remap_nearest_is_opencv_s(border):
    """remap_nearest against cv2.remap(INTER_NEAREST), to the pixel: the wobbling maps, maps on
    exact half pixels (OpenCV rounds them half to even) and far off the image; three channels
    with a value each, one pair of maps for two images."""
    xs, ys = np.meshgrid(np.arange(DST[0], dtype=np.float32), np.arange(DST[1], dtype=np.float32))
    halves = (xs * 1.5 - 20.5, ys / 2 - 3)  # x.5 and y.5 throughout, some of them off the image
    far = (xs * 40 - 3000, ys * 30 - 1900)
    rgb = textured_image(*SRC, seed=5)
    images = np.stack([rgb, np.roll(rgb, 17, axis=1)])
    value = (10.0, 200.0, 77.0)
    for map_x, map_y in (_wobble_maps(), halves, far):
        assert ((map_x < -0.5) | (map_x > SRC[0] - 0.5)).any()
        got = remap_nearest(torch.from_numpy(images).permute(0, 3, 1, 2), torch.from_numpy(map_x)[None], torch.from_numpy(map_y)[None], border, value)
        assert got.dtype == torch.uint8 and got.shape == (2, 3, DST[1], DST[0])
        for b in range(2):
            want = cv2.remap(images[b], map_x, map_y, cv2.INTER_NEAREST, borderMode=CV_BORDERS[border], borderValue=value)
            assert np.array_equal(got[b].permute(1, 2, 0).numpy(), want)
    # float images and a single value; non-finite coordinates read as outside
    image = IMAGES["noise"].astype(np.float32)
    map_x, map_y = _wobble_maps()
    map_x[0, :3] = (np.nan, np.inf, -np.inf)
    got = remap_nearest(torch.from_numpy(image)[None, None], torch.from_numpy(map_x)[None], torch.from_numpy(map_y)[None], border, VALUE)[0, 0].numpy()
    want = cv2.remap(image, map_x, map_y, cv2.INTER_NEAREST, borderMode=CV_BORDERS[border], borderValue=VALUE)
    assert np.array_equal(got[1:], want[1:]) and np.array_equal(got[0, 3:], want[0, 3:])
    if border == "constant":
        assert np.all(got[0, :3] == VALUE)


@pytest.mark.parametrize("name", list(WARPS))
def test_remap_nearest_of_perspective_maps_is_warp_perspective_nearest(name):
    """remap_nearest at perspective_maps' float64 coordinates against
    cv2.warpPerspective(INTER_NEAREST): the same pixels, the border's value outside."""
    M = WARPS[name]
    x, y = perspective_maps(torch.from_numpy(M)[None], DST, torch.float64)
    assert x.dtype == torch.float64 and x.shape == (1, DST[1], DST[0])
    for image in IMAGES.values():
        want = cv2.warpPerspective(image, M, DST, flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=VALUE)
        got = remap_nearest(torch.from_numpy(image)[None, None], x, y, "constant", VALUE)[0, 0].numpy()
        assert np.array_equal(got, want)
    # the float64 maps are the float32 ones, made exact
    x32, y32 = perspective_maps(torch.from_numpy(M)[None], DST)
    assert x32.dtype == torch.float32 and (x - x32).abs().max() < 1e-4 and (y - y32).abs().max() < 1e-4


def test_border_index_is_opencv_s():
    """border_index against cv2.copyMakeBorder of a row of indices, any pad, n from 1."""
    modes = {"replicate": cv2.BORDER_REPLICATE, "reflect": cv2.BORDER_REFLECT, "reflect101": cv2.BORDER_REFLECT_101}
    for n in (1, 2, 3, 7):
        row = np.arange(n, dtype=np.int32)[None]
        for mode, cv_mode in modes.items():
            pad = 3 * n + 2
            want = cv2.copyMakeBorder(row, 0, 0, pad, pad, cv_mode)[0]
            got = border_index(torch.arange(-pad, n + pad), n, mode)  # type: ignore[arg-type]
            assert np.array_equal(got.numpy(), want), (n, mode)


def test_shapes_are_checked():
    image = torch.zeros(1, 1, 8, 8, dtype=torch.uint8)
    with pytest.raises(ValueError, match="images"):
        warp_perspective(image[0], torch.eye(3)[None], (8, 8))
    with pytest.raises(ValueError, match="one matrix per image"):
        warp_perspective(image, torch.eye(3).expand(2, 3, 3), (8, 8))
    with pytest.raises(ValueError, match="border"):
        warp_perspective(image, torch.eye(3)[None], (8, 8), "wrap")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="value"):
        warp_perspective(image, torch.eye(3)[None], (8, 8), "constant", (1.0, 2.0))
    with pytest.raises(ValueError, match="even"):
        warp_yuv420(torch.zeros(1, 9, 7, dtype=torch.uint8), torch.eye(3)[None], (7, 6))
    with pytest.raises(ValueError, match="yuv420p"):
        DeviceWarper("cpu", (8, 6), "black").warp(np.zeros((6, 8), np.uint8), np.eye(3))


# --- the render's warps ---------------------------------------------------------------------

FRAME = (320, 180)  # (w, h) of the render's frames: even, as yuv420p needs
RENDER_WARPS = {
    "affine": np.array([[1.02, 0.03, -6.3], [-0.025, 0.99, 5.7], [0.0, 0.0, 1.0]]),  # render's warpAffine path
    "perspective": np.array([[1.01, 0.02, 3.37], [-0.015, 0.99, -4.71], [1.5e-4, -1e-4, 1.0]]),
}


def _frames() -> dict[str, np.ndarray]:
    w, h = FRAME
    rgb = textured_image(w, h, seed=2)
    return {"rgb": rgb, "yuv": cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_I420),
            "yuv_noise": np.random.default_rng(1).integers(0, 256, (h * 3 // 2, w), dtype=np.uint8)}


FRAMES = _frames()


def _rolling(frames: int = 5, bands: int = 8) -> RollingCorrection:
    """A synthetic rolling shutter: each band's correction (dx, dy px, rotation, scale) varying
    over the frame's rows and from frame to frame, of a few px."""
    tau = np.arange(frames)[:, None] + np.arange(bands)[None] / bands
    corrections = np.stack([3.0 * np.sin(2 * tau), 1.5 * np.cos(tau), 0.004 * np.sin(3 * tau), 0.002 * np.cos(tau)], -1)
    return RollingCorrection(0.8, corrections, FRAME, estimated=True)


def _max_mean(a: np.ndarray, b: np.ndarray) -> tuple[int, float]:
    diff = np.abs(a.astype(np.int16) - b.astype(np.int16))
    return int(diff.max()), float(diff.mean())


@exact_opencv
@pytest.mark.parametrize("border", list(BORDERS))
def test_yuv420_warp_matches_render(border):
    """warp_yuv420 (a batch of two, one warp each) and DeviceWarper.warp against render.warp_yuv,
    chroma planes and their black included; RGB frames against render.warp_frame."""
    frames = np.stack([FRAMES["yuv"], FRAMES["yuv_noise"]])
    Ms = np.stack(list(RENDER_WARPS.values()))
    got = warp_yuv420(torch.from_numpy(frames), torch.from_numpy(Ms), FRAME, RENDER_BORDER[border], YUV_BLACK).numpy()  # type: ignore[arg-type]
    warper = DeviceWarper("cpu", FRAME, border)
    for b in range(2):
        want = warp_yuv(frames[b], Ms[b], FRAME, border)
        for out in (got[b], warper.warp(frames[b], Ms[b])):
            top, mean = _max_mean(out, want)
            assert top <= 1 and mean < 0.02, (b, top, mean)
    if border == "black":  # the corners fall outside: Y, U and V black there
        out = warper.warp(FRAMES["yuv"], RENDER_WARPS["affine"])
        w, h = FRAME
        assert out[h - 1, w - 1] == YUV_BLACK[0]
        assert out[h + h // 4 - 1, w - 1] == YUV_BLACK[1] and out[-1, w - 1] == YUV_BLACK[2]
    rgb = warper.warp(FRAMES["rgb"], RENDER_WARPS["perspective"])
    top, mean = _max_mean(rgb, warp_frame(FRAMES["rgb"], RENDER_WARPS["perspective"], FRAME, border))
    assert rgb.shape == FRAMES["rgb"].shape and top <= 1 and mean < 0.02


@exact_opencv
@pytest.mark.parametrize("border", list(BORDERS))
def test_row_warper_matches_rolling(border):
    """DeviceWarper.row_warper(rolling) against RollingCorrection.warper, frame by frame: the
    maps built on the chroma grid and resized, each row's correction undone, for yuv420p and RGB."""
    rolling = _rolling()
    want_warp = rolling.warper(BORDERS[border], YUV_BLACK)
    got_warp = DeviceWarper("cpu", FRAME, border).row_warper(rolling)
    for t, (kind, name) in enumerate([("yuv", "affine"), ("yuv_noise", "perspective"), ("rgb", "perspective")]):
        frame, M = FRAMES[kind], RENDER_WARPS[name]
        want = want_warp(frame, t + 1, M)
        got = got_warp(frame, t + 1, M)
        top, mean = _max_mean(got, want)
        assert got.shape == frame.shape and top <= 1 and mean < 0.02, (kind, top, mean)
        # the rows' corrections matter: the plain warp differs
        assert _max_mean(want, warp_yuv(frame, M, FRAME, border) if frame.ndim == 2 else warp_frame(frame, M, FRAME, border))[1] > 1


def test_stream_and_batch_keep_order():
    """stream gives each input frame with its own warp's output, in order (two in flight), plain
    and per-row frames mixed; warp_many gives what warp gives."""
    rolling = _rolling()
    warper = DeviceWarper("cpu", FRAME, "black")
    frames = [FRAMES["yuv"], FRAMES["yuv_noise"], FRAMES["yuv"]]
    Ms = [RENDER_WARPS["affine"], RENDER_WARPS["perspective"], np.eye(3)]
    items = [(frames[0], Ms[0]), (frames[1], Ms[1], rolling, 2), (frames[2], Ms[2])]
    results = list(warper.stream(iter(items)))
    assert len(results) == 3
    assert all(inp is f for (inp, _), f in zip(results, frames))
    np.testing.assert_array_equal(results[0][1], warper.warp(frames[0], Ms[0]))
    np.testing.assert_array_equal(results[1][1], warper.row_warper(rolling)(frames[1], 2, Ms[1]))
    np.testing.assert_array_equal(results[2][1], frames[2])  # identity: the frame itself
    for got, frame, M in zip(warper.warp_many(frames, Ms), frames, Ms):
        np.testing.assert_array_equal(got, warper.warp(frame, M))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_cuda_warps_agree_with_the_cpu():
    """The GPU's warps (streamed, two in flight; batched; per row) within a level of the CPU's."""
    rolling = _rolling()
    for border in BORDERS:
        cpu, gpu = DeviceWarper("cpu", FRAME, border), DeviceWarper("cuda", FRAME, border)
        items = [(FRAMES["yuv"], RENDER_WARPS["affine"]), (FRAMES["yuv_noise"], RENDER_WARPS["perspective"], rolling, 1),
                 (FRAMES["rgb"], RENDER_WARPS["perspective"]), (FRAMES["rgb"], RENDER_WARPS["affine"], rolling, 3)] * 3
        for (_, got), (_, want) in zip(gpu.stream(iter(items)), cpu.stream(iter(items))):
            top, mean = _max_mean(got, want)
            assert top <= 1 and mean < 0.01, (border, top, mean)
        frames = [FRAMES["yuv"], FRAMES["yuv_noise"]]
        Ms = list(RENDER_WARPS.values())
        for got, want in zip(gpu.warp_many(frames, Ms), cpu.warp_many(frames, Ms)):
            top, mean = _max_mean(got, want)
            assert top <= 1 and mean < 0.01, (border, top, mean)
