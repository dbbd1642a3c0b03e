"""``mosaic stabilize``: the L1 path keeps the crop inside every frame and removes a known
jitter; the Gaussian option; output frames, rate and audio; the warps JSON against the
pixels; border fills; errors.

Truth comes from camera paths built here (a smooth pan plus a known 3-8 Hz shake), rendered
over a procedural texture where a video is needed; jitter is measured with a plain moving
average written here, independent of mosaic's metrics module."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import assert_one_line_error, ffmpeg, render, run_cli, textured_image, write_clip
from mosaic_cli.geometry import frame_corners, project
from mosaic_cli.stabilize.crop import BORDER_CHUNK, border_fraction, output_warps
from mosaic_cli.stabilize.metrics import cropping_ratio, distortion
from mosaic_cli.stabilize.path import MODELS, camera_motion
from mosaic_cli.stabilize.render import warp_frame, warp_yuv, yuv_planes
from mosaic_cli.stabilize.smoothing import GaussianSmoother, L1Smoother
from mosaic_cli.video import open_video, probe

SIZE = (320, 180)
FPS = 30.0


# --- known shaky camera paths ------------------------------------------------------------------

def _about_centre(angle: float, dx: float, dy: float, size=SIZE) -> np.ndarray:
    cx, cy = (size[0] - 1) / 2, (size[1] - 1) / 2
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, cx - c * cx + s * cy + dx], [s, c, cy - s * cx - c * cy + dy], [0, 0, 1.0]])


def shaky_path(n: int, seed: int = 0, size=SIZE, shake_px: float = 3.0, shake_deg: float = 0.5):
    """(map -> frame with shake, map -> frame without) for a pan with a slow turn, plus a
    shake of three 3-8 Hz sinusoids in x, y and rotation (``shake_px`` at 1280 px wide)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FPS
    amp = shake_px * size[0] / 1280 * 4  # a clearly visible shake at this small size

    def shake():
        f, phase = rng.uniform(3, 8, 3), rng.uniform(0, 2 * np.pi, 3)
        return np.sin(2 * np.pi * f[:, None] * t + phase[:, None]).mean(axis=0)

    jx, jy, ja = amp * shake(), amp * shake(), np.radians(shake_deg) * shake()
    smooth = np.stack([_about_centre(0.1 * k / n, -40 - 1.5 * k, -30 - 0.5 * k, size) for k in range(n)])
    shaken = np.stack([_about_centre(ja[k], jx[k], jy[k], size) @ smooth[k] for k in range(n)])
    return shaken, smooth


def pairwise_of(map_to_frame: np.ndarray) -> np.ndarray:
    H = map_to_frame[1:] @ np.linalg.inv(map_to_frame[:-1])
    return H / H[:, 2:3, 2:3]


def high_frequency(map_to_frame, smooth, warps=None, size=SIZE, window: int = 9) -> float:
    """RMS (pixels) of what a moving average leaves of the output outline's motion, seen by
    the jitter-free camera: 0 for a perfectly steady output."""
    W = np.eye(3) if warps is None else warps
    outline = project(smooth @ np.linalg.inv(W @ map_to_frame), frame_corners(*size))  # (N, 4, 2)
    kernel = np.ones(window) / window
    low = np.apply_along_axis(lambda x: np.convolve(x, kernel, mode="same"), 0, outline)
    half = window
    residual = (outline - low)[half:-half]
    return float(np.sqrt(np.mean(np.sum(residual ** 2, axis=-1))))


def outside_by(warps: np.ndarray, size=SIZE) -> np.ndarray:
    """(N,) how far (pixels) the output frame's corners, mapped back into the input, fall
    outside the input frame (0 when all four are inside)."""
    w, h = size
    back = project(np.linalg.inv(warps), frame_corners(w, h))
    over = np.stack([-0.5 - back[..., 0], back[..., 0] - (w - 0.5), -0.5 - back[..., 1], back[..., 1] - (h - 0.5)], -1)
    return np.clip(over, 0, None).max(axis=(-1, -2))


def plan_warps(map_to_frame, smoother, model="similarity", crop=None, size=SIZE):
    motion = camera_motion(pairwise_of(map_to_frame), size, MODELS[model])
    return output_warps(smoother.smooth(motion, size, MODELS[model], crop), size)


# --- the L1 path -------------------------------------------------------------------------------

@pytest.mark.parametrize("model", ["similarity", "affine", "homography"])
def test_l1_path_keeps_crop_inside_and_removes_jitter(model):
    shaken, smooth = shaky_path(150, seed=1)
    warps = plan_warps(shaken, L1Smoother(window=60, overlap=20), model)  # several windows
    assert outside_by(warps).max() < 0.01  # every output corner inside its input frame
    before, after = high_frequency(shaken, smooth), high_frequency(shaken, smooth, warps)
    assert before > 1.5
    assert after < 0.25 * before, (before, after)
    # A small, undistorted zoom: the crop is only what the shake needs.
    assert 0.85 < cropping_ratio(warps, SIZE) < 1.0
    assert distortion(warps, SIZE) > 0.95


@pytest.mark.slow
def test_l1_windows_join_without_jumps():
    """Sliding windows give (almost) the path a single program over all frames gives."""
    shaken, smooth = shaky_path(120, seed=2)
    whole = plan_warps(shaken, L1Smoother(window=120))
    windowed = plan_warps(shaken, L1Smoother(window=50, overlap=20))
    assert high_frequency(shaken, smooth, windowed) < 1.5 * high_frequency(shaken, smooth, whole) + 0.1
    # The view moves smoothly across every seam: no frame-to-frame step of the output
    # outline is much larger than the steps of the single-program solution.
    def steps(warps):
        outline = project(smooth @ np.linalg.inv(warps @ shaken), frame_corners(*SIZE))
        return np.linalg.norm(np.diff(outline, 2, axis=0), axis=-1).max()
    assert steps(windowed) < 2.0 * steps(whole) + 0.5


def test_l1_fixed_crop_keeps_its_zoom():
    shaken, smooth = shaky_path(90, seed=3)
    warps = plan_warps(shaken, L1Smoother(), crop=0.9)
    assert cropping_ratio(warps, SIZE) == pytest.approx(0.9, abs=0.01)
    assert high_frequency(shaken, smooth, warps) < 0.25 * high_frequency(shaken, smooth)


def test_gaussian_smoother_removes_jitter_without_border():
    shaken, smooth = shaky_path(120, seed=4)
    warps = plan_warps(shaken, GaussianSmoother(radius=15))
    assert outside_by(warps).max() < 0.05
    assert high_frequency(shaken, smooth, warps) < 0.5 * high_frequency(shaken, smooth)
    # A fixed crop gives exactly that zoom.
    fixed = plan_warps(shaken, GaussianSmoother(radius=15), crop=0.8)
    assert cropping_ratio(fixed, SIZE) == pytest.approx(0.8, abs=0.01)


def test_still_camera_is_left_alone():
    still = np.repeat(np.eye(3)[None], 40, axis=0)
    warps = plan_warps(still, L1Smoother())
    np.testing.assert_allclose(warps, np.repeat(np.eye(3)[None], 40, axis=0), atol=1e-6)


# --- border fills ------------------------------------------------------------------------------

def test_border_fills():
    frame = textured_image(64, 48, seed=5)
    shift = np.array([[1, 0, 5.0], [0, 1, 0], [0, 0, 1]])  # input x -> output x + 5
    black = warp_frame(frame, shift, (64, 48), "black")
    assert (black[:, :5] == 0).all()
    np.testing.assert_array_equal(black[:, 5:], frame[:, :-5])
    replicate = warp_frame(frame, shift, (64, 48), "replicate")
    np.testing.assert_array_equal(replicate[:, :5], np.repeat(frame[:, :1], 5, axis=1))
    reflect = warp_frame(frame, shift, (64, 48), "reflect")
    np.testing.assert_array_equal(reflect[:, :5], frame[:, 4::-1])  # fedcba|abcdef
    perspective = shift.copy()
    perspective[2, 0] = 1e-5  # the warpPerspective path gives the same fill
    assert (warp_frame(frame, perspective, (64, 48), "black")[:, :4] == 0).all()


def test_border_fraction_in_chunks_is_each_frames_own():
    """Measured a chunk of frames at a time (memory bounded), each frame's share is still its own:
    a shift of d pixels to the right uncovers d columns of the output, here over more frames
    than one chunk holds."""
    w, h = 64, 40
    shifts = np.arange(2 * BORDER_CHUNK + 17) % 20
    warps = np.stack([np.array([[1, 0, d], [0, 1, 0], [0, 0, 1.0]]) for d in shifts])
    share = border_fraction(warps, (w, h), grid=w)  # the grid on every pixel centre
    np.testing.assert_allclose(share, shifts / w, atol=1e-12)


def test_yuv_planes_warp_like_rgb():
    """The yuv420p path (chroma warped at half resolution) gives the RGB path's picture."""
    frame = textured_image(160, 96, seed=6)
    size = (160, 96)
    warp = np.array([[0.98, -0.05, 6.3], [0.05, 0.98, -3.7], [0, 0, 1]])
    yuv = cv2.cvtColor(frame, cv2.COLOR_RGB2YUV_I420)  # (h * 3 / 2, w) planes, as ffmpeg's yuv420p
    via_yuv = cv2.cvtColor(warp_yuv(yuv, warp, size, "black"), cv2.COLOR_YUV2RGB_I420)
    via_rgb = warp_frame(frame, warp, size, "black")
    inner = (slice(12, -12), slice(12, -12))
    reference = cv2.cvtColor(cv2.cvtColor(via_rgb, cv2.COLOR_RGB2YUV_I420), cv2.COLOR_YUV2RGB_I420)
    assert cv2.PSNR(via_yuv[inner], reference[inner]) > 35
    # A chroma plane warped with the luma matrix would be off by pixels: much worse.
    wrong = yuv.copy()
    y, u, v = yuv_planes(wrong, size)
    u[...] = warp_frame(u, warp, (80, 48))
    v[...] = warp_frame(v, warp, (80, 48))
    y[...] = warp_frame(y, warp, size)
    assert cv2.PSNR(cv2.cvtColor(wrong, cv2.COLOR_YUV2RGB_I420)[inner], reference[inner]) < cv2.PSNR(via_yuv[inner], reference[inner]) - 3
    # Black in yuv420p is (16, 128, 128), which decodes to RGB black.
    shifted = warp_yuv(yuv, np.array([[1, 0, 8.0], [0, 1, 0], [0, 0, 1]]), size, "black")
    assert (cv2.cvtColor(shifted, cv2.COLOR_YUV2RGB_I420)[:, :6] <= 2).all()


# --- the command, on a rendered shaky clip with sound ------------------------------------------

@pytest.mark.parametrize("source", ["video", "folder"])
def test_compare_halves_are_labelled_input_and_stabilised(tmp_path, source):
    """--compare's video: every frame, the input on the left and the output on the right, each
    with its label in the top-left corner ("input", and the wider "stabilised" on the output),
    written on the frames and nowhere else.  A video stays in yuv420p, a folder of images goes
    through RGB: both paths write the labels."""
    from mosaic_cli.stabilize.render import Renderer

    n = 12
    texture = textured_image(420, 300, seed=3)
    shifts = [_about_centre(0.0, 2.0 * t, 1.0 * t) for t in range(n)]
    frames = [render(texture, np.linalg.inv(M), SIZE) for M in shifts]
    if source == "video":
        clip = write_clip(tmp_path / "in.mp4", frames, fps=FPS)
    else:
        clip = tmp_path / "in"
        clip.mkdir()
        for t, f in enumerate(frames):
            cv2.imwrite(str(clip / f"frame_{t:03d}.png"), cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    warps = np.repeat(_about_centre(0.0, 3.0, -2.0)[None], n, axis=0)
    out, side = tmp_path / "out.mp4", tmp_path / "side.mp4"
    written = Renderer(crf=8).render(clip, out, warps, probe(clip), compare=side, show_progress=False)
    assert written == n
    inputs, outputs, sides = decoded(clip), decoded(out), decoded(side)
    assert len(sides) == len(inputs) == n
    w, h = SIZE
    for t in (0, n // 2, n - 1):
        frame = sides[t].astype(int)
        assert frame.shape == (h, 2 * w, 3)
        plain = np.hstack([inputs[t], outputs[t]]).astype(int)  # the same frame without labels
        changed = np.abs(frame - plain).max(axis=2) > 80
        top, rest = changed[: h // 4], changed[h // 4:]
        assert rest.mean() < 0.002  # nothing written below the labels
        left, right = top[:, :w], top[:, w:]
        assert left.sum() > 40 and right.sum() > 40  # each half has its label
        assert not left[:, w // 2:].any() and not right[:, w // 2:].any()  # in its top-left corner
        # "stabilised" (10 letters) on the output, "input" (5) on the input: wider, more ink
        cols_left, cols_right = np.flatnonzero(left.sum(axis=0) >= 2), np.flatnonzero(right.sum(axis=0) >= 2)
        assert np.ptp(cols_right) > 1.5 * np.ptp(cols_left) and right.sum() > 1.5 * left.sum()
        # white letters outlined in black: both extremes are there, in each half
        for half in (frame[: h // 4, :w], frame[: h // 4, w:]):
            assert (half.min(axis=2) > 225).sum() > 20 and (half.max(axis=2) < 30).sum() > 20


@pytest.fixture(scope="module")
def shaky_clip(tmp_path_factory):
    """60 frames, 320x180, 30 fps, a shaky pan over a procedural texture, with a sine sound
    track; and its exact map -> frame paths (shaken and smooth)."""
    folder = tmp_path_factory.mktemp("shaky")
    shaken, smooth = shaky_path(60, seed=7)
    texture = textured_image(700, 500, seed=7)
    frames = [render(texture, np.linalg.inv(M), SIZE) for M in shaken]
    silent = write_clip(folder / "silent.mp4", frames, fps=FPS)
    clip = folder / "shaky.mp4"
    ffmpeg("-i", str(silent), "-f", "lavfi", "-i", "sine=frequency=440:duration=2", "-c:v", "copy", "-c:a", "aac",
           "-shortest", str(clip))
    return clip, shaken, smooth


def decoded(path) -> list[np.ndarray]:
    with open_video(path) as stream:
        return list(stream)


@pytest.mark.slow
def test_stabilize_keeps_frames_rate_and_audio(tmp_path, capsys, shaky_clip):
    clip, shaken, smooth = shaky_clip
    out, warps_json, side = tmp_path / "steady.mp4", tmp_path / "warps.json", tmp_path / "side.mp4"
    code, err = run_cli(capsys, "stabilize", clip, out, "--warps", warps_json, "--compare", side, "-q")
    assert code == 0, err
    source, result = probe(clip), probe(out)
    assert source.audio_codec is not None and result.audio_codec is not None
    assert result.fps == pytest.approx(source.fps)
    assert result.source_size == source.source_size
    inputs, outputs = decoded(clip), decoded(out)
    assert len(outputs) == len(inputs) == 60
    side_info = probe(side)
    assert side_info.source_size == (2 * SIZE[0], SIZE[1]) and side_info.audio_codec is not None
    assert len(decoded(side)) == 60

    data = json.loads(warps_json.read_text())
    assert data["frames"] == 60 and data["size"] == list(SIZE)
    warps = np.array(data["warps"])
    assert warps.shape == (60, 3, 3)
    # The estimator tracked the rendered shake: the warps steady the known path.
    assert high_frequency(shaken, smooth, warps) < 0.3 * high_frequency(shaken, smooth)
    assert outside_by(warps).max() < 0.5

    # Each warp says where an input pixel went: a patch of the output around W(p) is found in
    # the input at p (template matching, to a pixel).
    for t in (5, 30, 55):
        for p in ((100.0, 70.0), (220.0, 110.0)):
            q = project(warps[t], np.array([p]))[0]
            qi = np.round(q).astype(int)
            patch = cv2.cvtColor(outputs[t], cv2.COLOR_RGB2GRAY)[qi[1] - 12:qi[1] + 13, qi[0] - 12:qi[0] + 13]
            gray = cv2.cvtColor(inputs[t], cv2.COLOR_RGB2GRAY)
            score = cv2.matchTemplate(gray, patch, cv2.TM_CCOEFF_NORMED)
            _, best, _, loc = cv2.minMaxLoc(score)
            found = np.array(loc) + 12 + (q - qi)  # patch centre, with q's sub-pixel part
            assert best > 0.8
            assert np.linalg.norm(found - np.array(p)) < 1.5, (t, p, found)


@pytest.mark.slow
def test_gaussian_option_end_to_end(tmp_path, capsys, shaky_clip):
    clip, shaken, smooth = shaky_clip
    out, warps_json = tmp_path / "steady.mp4", tmp_path / "warps.json"
    code, err = run_cli(capsys, "stabilize", clip, out, "--smoothing", "gaussian", "--radius", "10",
                        "--model", "affine", "--warps", warps_json, "-q")
    assert code == 0, err
    warps = np.array(json.loads(warps_json.read_text())["warps"])
    assert len(decoded(out)) == 60
    assert high_frequency(shaken, smooth, warps) < 0.6 * high_frequency(shaken, smooth)


@pytest.mark.slow
@pytest.mark.parametrize("border", ["black", "replicate", "reflect"])
def test_full_view_with_border_fill(tmp_path, capsys, shaky_clip, border):
    clip, _, _ = shaky_clip
    out, warps_json = tmp_path / "steady.mp4", tmp_path / "warps.json"
    code, err = run_cli(capsys, "stabilize", clip, out, "--crop", "1", "--border", border, "--crf", "10",
                        "--warps", warps_json, "-q")
    assert code == 0, err
    warps = np.array(json.loads(warps_json.read_text())["warps"])
    assert cropping_ratio(warps, SIZE) == pytest.approx(1.0, abs=0.01)
    # Output pixels that no input pixel reaches (well clear of the edge, for the codec).
    w, h = SIZE
    ys, xs = np.mgrid[0:h, 0:w]
    pts = np.stack([xs, ys], -1).reshape(-1, 2).astype(float)
    outputs = decoded(out)
    dark = []
    for t in range(0, 60, 3):
        src = project(np.linalg.inv(warps[t]), pts)
        uncovered = (src[:, 0] < -3) | (src[:, 0] > w + 2) | (src[:, 1] < -3) | (src[:, 1] > h + 2)
        if uncovered.any():
            dark.append(outputs[t].reshape(-1, 3)[uncovered].max(axis=1))
    assert dark, "a full-view stabilisation of this shake leaves some area uncovered"
    values = np.concatenate(dark)
    if border == "black":
        assert np.percentile(values, 95) < 30
    else:
        assert np.median(values) > 60  # replicated or mirrored pixels of the texture, not black


# --- errors ------------------------------------------------------------------------------------

@pytest.mark.parametrize("args, fragment", [
    (["--crop", "1.5"], "--crop"),
    (["--crop", "wide"], "--crop"),
    (["--border", "blue"], "--border"),
    (["--model", "projective"], "--model"),
    (["--smoothing", "kalman"], "--smoothing"),
    (["--smoothing", "gaussian", "--radius", "0"], "--radius"),
    (["--crf", "60"], "--crf"),
    (["--preset", "warp"], "--preset"),
])
def test_bad_options(tmp_path, capsys, shaky_clip, args, fragment):
    clip, _, _ = shaky_clip
    out = tmp_path / "out" / "steady.mp4"
    out.parent.mkdir()
    code, err = run_cli(capsys, "stabilize", clip, out, *args)
    assert_one_line_error(code, err, fragment)
    assert list(out.parent.iterdir()) == []


@pytest.mark.slow
def test_bad_paths(tmp_path, capsys, shaky_clip):
    clip, _, _ = shaky_clip
    outdir = tmp_path / "out"
    outdir.mkdir()
    code, err = run_cli(capsys, "stabilize", tmp_path / "missing.mp4", outdir / "a.mp4")
    assert_one_line_error(code, err, "missing.mp4")
    code, err = run_cli(capsys, "stabilize", clip, tmp_path / "nowhere" / "a.mp4")
    assert_one_line_error(code, err, "does not exist")
    code, err = run_cli(capsys, "stabilize", clip, clip)
    assert_one_line_error(code, err, "input")
    code, err = run_cli(capsys, "stabilize", clip, outdir / "a.mp4", "--compare", outdir / "a.mp4")
    assert_one_line_error(code, err, "same file")
    code, err = run_cli(capsys, "stabilize", clip, outdir)
    assert_one_line_error(code, err, "directory")
    code, err = run_cli(capsys, "stabilize", clip, outdir / "a.txt")
    assert_one_line_error(code, err, ".mp4")
    not_video = tmp_path / "notes.mp4"
    not_video.write_text("not a video")
    code, err = run_cli(capsys, "stabilize", not_video, outdir / "a.mp4")
    assert_one_line_error(code, err, "notes.mp4")
    assert list(outdir.iterdir()) == []


def test_unwritable_output(tmp_path, capsys, shaky_clip):
    import os
    from pathlib import Path

    clip, _, _ = shaky_clip
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if os.access(locked, os.W_OK):  # root: permission bits do not apply, a read-only place does
            locked = Path("/sys")
            if not locked.is_dir():
                pytest.skip("no read-only folder to write to")
        code, err = run_cli(capsys, "stabilize", clip, locked / "a.mp4")
        assert_one_line_error(code, err, "not writable")
        assert not (locked / "a.mp4").exists()
    finally:
        (tmp_path / "locked").chmod(0o700)
