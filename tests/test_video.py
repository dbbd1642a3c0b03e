"""Streaming reader and writer on clips generated here with the bundled ffmpeg."""

from __future__ import annotations

import os
from fractions import Fraction

import cv2
import numpy as np
import pytest

from conftest import ffmpeg, opencv_count, textured_image, write_clip
from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.geometry import project, resize_matrix
from mosaic_cli.video import VideoWriter, open_video, probe

N_FRAMES = 10


def moving_frames(width: int, height: int, n: int = N_FRAMES, seed: int = 5) -> list[np.ndarray]:
    """Distinct frames (a texture panning 7 px per frame), so order mistakes show."""
    tex = textured_image(width + 7 * n, height, seed=seed)
    return [np.ascontiguousarray(tex[:, 7 * k:7 * k + width]) for k in range(n)]


def read_all(path, **kwargs):
    with open_video(path, **kwargs) as stream:
        return stream.info, list(stream)


def assert_same_sequence(decoded, source, tolerance):
    """Same count, each decoded frame close to its own source frame and closer to it than to
    its neighbours (so a dropped or repeated frame fails)."""
    assert len(decoded) == len(source)
    for k, frame in enumerate(decoded):
        assert frame.shape == source[k].shape
        err = np.abs(frame.astype(np.float32) - source[k]).mean()
        assert err < tolerance, f"frame {k}: mean abs error {err:.2f}"
        for j in (k - 1, k + 1):
            if 0 <= j < len(source):
                assert err < np.abs(frame.astype(np.float32) - source[j]).mean()


@pytest.mark.parametrize(
    "suffix, codec, pix_fmt, tolerance",
    [
        (".mp4", "libx264", "yuv420p", 6.0),
        (".mov", "libx264", "yuv420p", 6.0),
        (".mkv", "ffv1", "bgr0", 0.0),  # lossless
        (".avi", "mpeg4", "yuv420p", 12.0),
        (".mjpeg", "mjpeg", "yuvj444p", 8.0),  # raw MJPEG stream: no container, no duration
    ],
)
def test_reader_decodes_every_container(tmp_path, suffix, codec, pix_fmt, tolerance):
    source = moving_frames(160, 96)
    extra = ["-q:v", "2"] if codec in ("mpeg4", "mjpeg") else []
    clip = write_clip(tmp_path / f"clip{suffix}", source, fps=25, codec=codec, pix_fmt=pix_fmt, extra=extra)
    info, frames = read_all(clip)
    assert info.size == info.source_size == (160, 96)
    assert info.fps == pytest.approx(25.0)
    if suffix == ".mjpeg":
        assert info.frame_count is None
    else:
        assert info.frame_count == N_FRAMES
    if tolerance == 0.0:
        assert all(np.array_equal(a, b) for a, b in zip(frames, source))
        assert len(frames) == len(source)
    else:
        assert_same_sequence(frames, source, tolerance)


def test_reader_odd_size_is_exact(tmp_path):
    source = moving_frames(97, 61, n=4)
    clip = write_clip(tmp_path / "odd.mkv", source, codec="ffv1", pix_fmt="bgr0")
    info, frames = read_all(clip)
    assert info.size == (97, 61)
    assert len(frames) == 4 and all(np.array_equal(a, b) for a, b in zip(frames, source))


def test_reader_gray_and_start(tmp_path):
    source = moving_frames(96, 64, n=6)
    clip = write_clip(tmp_path / "c.mkv", source, codec="ffv1", pix_fmt="bgr0")
    _, gray = read_all(clip, gray=True)
    assert gray[0].shape == (64, 96) and gray[0].dtype == np.uint8
    # ffmpeg's gray is BT.601 luma like OpenCV's: allow rounding and range differences only
    assert np.abs(gray[2].astype(int) - cv2.cvtColor(source[2], cv2.COLOR_RGB2GRAY)).mean() < 2.0
    _, later = read_all(clip, start=3)
    assert len(later) == 3 and np.array_equal(later[0], source[3])


def test_reader_downscales_inside_ffmpeg_with_pixel_centres(tmp_path):
    """A blob's centroid after ffmpeg's downscale lands where resize_matrix says."""
    w, h = 640, 360
    centres = [(101.0, 77.0), (400.5, 200.25), (555.0, 300.0)]
    frames = []
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    for cx, cy in centres:
        blob = 255 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 6.0**2))
        frames.append(np.repeat(blob[:, :, None], 3, axis=2).astype(np.uint8))
    clip = write_clip(tmp_path / "blob.mkv", frames, codec="ffv1", pix_fmt="bgr0")
    info, small = read_all(clip, width=160, gray=True)
    assert info.size == (160, 90) and info.source_size == (640, 360)
    S = resize_matrix((w, h), info.size)
    for frame, centre in zip(small, centres):
        m = cv2.moments(frame.astype(np.float32))
        found = np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])
        expected = project(S, np.array([centre]))[0]
        assert np.linalg.norm(found - expected) < 0.05


def test_reader_downscale_matches_opencv_area(tmp_path):
    source = moving_frames(320, 180, n=3)
    clip = write_clip(tmp_path / "c.mkv", source, codec="ffv1", pix_fmt="bgr0")
    _, small = read_all(clip, width=80)
    for frame, full in zip(small, source):
        ref = cv2.resize(full, (80, 45), interpolation=cv2.INTER_AREA)
        assert np.abs(frame.astype(np.float32) - ref).mean() < 1.5


@pytest.mark.parametrize("display_rotation, clockwise, k", [(-90, 90, -1), (90, 270, 1), (180, 180, 2)])
def test_reader_applies_rotation_metadata(tmp_path, display_rotation, clockwise, k):
    source = moving_frames(96, 64, n=3)
    plain = write_clip(tmp_path / "plain.mkv", source, codec="ffv1", pix_fmt="bgr0")
    rotated = tmp_path / "rotated.mkv"
    ffmpeg("-display_rotation", str(display_rotation), "-i", str(plain), "-c", "copy", str(rotated))
    info, frames = read_all(rotated)
    assert info.rotation == clockwise
    expected = [np.rot90(f, k) for f in source]
    assert info.size == (expected[0].shape[1], expected[0].shape[0])
    assert all(np.array_equal(a, b) for a, b in zip(frames, expected))
    small_info, small = read_all(rotated, width=32)
    assert small_info.size[0] == 32 and small[0].shape[1] == 32
    assert small_info.source_size == info.size
    assert probe(plain).rotation == 0


def test_folder_of_numbered_images_in_natural_order(tmp_path):
    source = moving_frames(64, 48, n=12)
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, frame in enumerate(source):
        cv2.imwrite(str(folder / f"frame_{k + 1}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    (folder / "notes.txt").write_text("not an image")
    info, frames = read_all(folder)
    assert info.is_image_folder and info.frame_count == 12 and info.fps == 30.0
    assert all(np.array_equal(a, b) for a, b in zip(frames, source)) and len(frames) == 12
    info, small = read_all(folder, width=32, fps=12.5, gray=True)
    assert info.fps == 12.5 and small[0].shape == (24, 32)


def test_folder_with_an_image_of_another_shape_fits_it_whole_into_the_first_frame(tmp_path):
    """A portrait image among landscape ones: scaled to the frame's height, centred, the rest black;
    the info lists it before any image is decoded, with where it lies."""
    rng = np.random.default_rng(1)
    first, portrait = rng.integers(1, 255, (60, 80, 3), dtype=np.uint8), rng.integers(1, 255, (120, 90, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "a_1.png"), first)
    cv2.imwrite(str(tmp_path / "a_2.png"), portrait)
    info, frames = read_all(tmp_path)
    (fit,) = info.photo_fits
    assert (fit.index, fit.name, fit.photo_size, fit.scale, fit.box) == (1, "a_2.png", (90, 120), 0.5, (17, 0, 45, 60))
    expected = cv2.cvtColor(cv2.resize(portrait, (45, 60), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
    assert np.array_equal(frames[1][:, 17:62], expected)
    assert not frames[1][:, :17].any() and not frames[1][:, 62:].any()
    info, small = read_all(tmp_path, width=40)  # downscaled: the same place, halved
    assert small[1].shape == (30, 40, 3) and not small[1][:, :8].any() and small[1][:, 9:30].all(axis=-1).mean() > 0.95


def test_folder_with_a_larger_image_of_the_same_shape_reads_it_at_the_first_size(tmp_path):
    """Another camera of the same shape: read at the first image's size (its content resized)."""
    rng = np.random.default_rng(0)
    first = rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "a_1.png"), first)
    cv2.imwrite(str(tmp_path / "a_2.png"), cv2.resize(first, (160, 120), interpolation=cv2.INTER_NEAREST))
    info, frames = read_all(tmp_path)
    assert info.source_size == (80, 60) and [f.shape for f in frames] == [(60, 80, 3), (60, 80, 3)]
    assert np.abs(frames[1].astype(int) - frames[0].astype(int)).mean() < 1.0  # 2x2 blocks averaged back


def test_probe_frame_count_and_fps_of_avi_with_copied_h264(tmp_path):
    """h264 copied into avi reports an average rate of 600 fps; the base rate is the real one."""
    mp4 = tmp_path / "c.mp4"
    ffmpeg("-f", "lavfi", "-i", "testsrc2=size=64x48:rate=30", "-t", "2", "-c:v", "libx264", "-pix_fmt", "yuv420p", str(mp4))
    avi = tmp_path / "c.avi"
    ffmpeg("-i", str(mp4), "-c", "copy", str(avi))
    info = probe(avi)
    assert info.fps == pytest.approx(30.0) and info.frame_count == 60


# ---------------------------------------------------------------- writer


def test_writer_odd_size_round_trip(tmp_path):
    source = moving_frames(97, 61, n=5)
    out = tmp_path / "odd.mp4"
    with VideoWriter(out, (97, 61), fps=24, crf=10, preset="ultrafast") as writer:
        for frame in source:
            writer.write(frame)
    info, frames = read_all(out)
    assert info.size == (98, 62) and info.fps == pytest.approx(24.0)
    # the padding repeats the last row and column
    assert np.abs(frames[2][:, 97].astype(int) - frames[2][:, 96]).mean() < 4
    assert_same_sequence([f[:61, :97] for f in frames], source, 6.0)
    assert [p.name for p in tmp_path.iterdir()] == ["odd.mp4"]
    mask = os.umask(0)
    os.umask(mask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~mask  # not mkstemp's 0600


def test_writer_crf_changes_quality(tmp_path):
    source = moving_frames(128, 96, n=4)
    sizes = {}
    for crf in (5, 40):
        out = tmp_path / f"crf{crf}.mp4"
        with VideoWriter(out, (128, 96), fps=30, crf=crf, preset="ultrafast") as writer:
            for frame in source:
                writer.write(frame)
        sizes[crf] = out.stat().st_size
    assert sizes[5] > 2 * sizes[40]


@pytest.mark.parametrize("kwargs, message", [
    (dict(crf=52), "crf"), (dict(crf=-1), "crf"), (dict(preset="warp"), "preset"), (dict(fps=0), "frame rate"),
])
def test_writer_rejects_bad_options_before_creating_anything(tmp_path, kwargs, message):
    args = dict(path=tmp_path / "x.mp4", size=(64, 48), fps=30)
    args.update(kwargs)
    with pytest.raises(BadInput, match=message):
        VideoWriter(**args)
    assert list(tmp_path.iterdir()) == []


def test_writer_unwritable_destination(tmp_path):
    with pytest.raises(BadInput, match="does not exist"):
        VideoWriter(tmp_path / "missing" / "x.mp4", (64, 48), fps=30)
    (tmp_path / "file").write_text("")
    with pytest.raises(BadInput):
        VideoWriter(tmp_path / "file" / "x.mp4", (64, 48), fps=30)


def test_writer_is_atomic(tmp_path):
    out = tmp_path / "x.mp4"
    with pytest.raises(ZeroDivisionError):
        with VideoWriter(out, (64, 48), fps=30, preset="ultrafast") as writer:
            writer.write(np.zeros((48, 64, 3), np.uint8))
            assert not out.exists()
            1 / 0
    assert list(tmp_path.iterdir()) == []
    writer = VideoWriter(out, (64, 48), fps=30)
    with pytest.raises(ProcessingError, match="no frames"):
        writer.close()
    assert list(tmp_path.iterdir()) == []
    with VideoWriter(out, (64, 48), fps=30) as writer:
        with pytest.raises(ProcessingError, match="size"):
            writer.write(np.zeros((10, 10, 3), np.uint8))
        writer.write(np.zeros((48, 64), np.uint8))  # gray is accepted
    assert out.exists()


def test_writer_carries_audio_over(tmp_path):
    source = tmp_path / "with_audio.mp4"
    ffmpeg("-f", "lavfi", "-i", "testsrc2=size=128x72:rate=25", "-f", "lavfi", "-i", "sine=frequency=440",
           "-t", "2", "-c:v", "libx264", "-pix_fmt", "yuv420p", "-c:a", "aac", str(source))
    src_info = probe(source)
    assert src_info.has_audio and src_info.audio_codec == "aac"
    for suffix in (".mp4", ".mkv"):
        out = tmp_path / f"out{suffix}"
        with open_video(source) as stream, VideoWriter(out, stream.info.size, stream.info.fps, preset="ultrafast",
                                                       audio_from=source, audio_seconds=2.0) as writer:
            for frame in stream:
                writer.write(frame)
        info = probe(out)
        assert info.audio_codec == "aac" and len(read_all(out)[1]) == 50
        assert info.duration == pytest.approx(2.0, abs=0.1)
    # a source without audio gives a silent video rather than an error
    silent = write_clip(tmp_path / "silent.mp4", moving_frames(64, 48, n=3))
    out = tmp_path / "silent_out.mp4"
    with VideoWriter(out, (64, 48), fps=30, audio_from=silent) as writer:
        writer.write(np.zeros((48, 64, 3), np.uint8))
    assert not probe(out).has_audio


def test_writer_shorter_than_audio_ends_with_the_video(tmp_path):
    source = tmp_path / "with_audio.mp4"
    ffmpeg("-f", "lavfi", "-i", "testsrc2=size=128x72:rate=25", "-f", "lavfi", "-i", "sine",
           "-t", "3", "-c:v", "libx264", "-pix_fmt", "yuv420p", str(source))
    out = tmp_path / "short.mp4"
    with VideoWriter(out, (128, 72), fps=25, preset="ultrafast", audio_from=source, audio_seconds=1.0) as writer:
        for _ in range(25):
            writer.write(np.zeros((72, 128, 3), np.uint8))
    assert probe(out).duration < 1.5


# ---------------------------------------------------------------- probe


def lavfi_clip(path, rate: str, frames: int, audio: str | None = None, audio_seconds: float | None = None,
               codec: str = "libx264", extra: tuple[str, ...] = ()) -> None:
    """``frames`` frames of testsrc2 (160x90) at ``rate``, with a sine track in ``audio``'s codec."""
    args = ["-f", "lavfi", "-i", f"testsrc2=size=160x90:rate={rate}"]
    if audio is not None:
        seconds = audio_seconds if audio_seconds is not None else frames / float(Fraction(rate))
        args += ["-f", "lavfi", "-i", f"sine=frequency=440:sample_rate=48000:duration={seconds:.4f}", "-map", "0:v", "-map", "1:a",
                 "-c:a", audio]
    video = ["-c:v", codec, "-pix_fmt", "yuv420p"] + (["-preset", "ultrafast"] if codec == "libx264" else ["-deadline", "realtime"])
    ffmpeg(*args, "-frames:v", str(frames), *video, *extra, str(path))


# (file, rate as ffmpeg takes it, frames, audio codec or None, rotation written, clockwise rotation read)
PROBE_CASES = [
    ("ntsc.mp4", "30000/1001", 45, "aac", None, 0),
    ("film.mkv", "24000/1001", 36, None, None, 0),
    ("pal.mov", "25", 30, "pcm_s16le", None, 0),
    ("vp9.webm", "30", 30, "libopus", None, 0),  # (the stderr-scraping probe read the codec as "opus,")
    ("turned.mp4", "30", 30, None, 90, 270),  # display matrix: counter-clockwise 90 = clockwise 270
    ("turned.mov", "30", 30, "aac", -90, 90),
    ("turned.mkv", "25", 25, None, 180, 180),
]


@pytest.mark.parametrize("name, codec", [("long_audio.webm", "libvpx-vp9"), ("long_audio.mkv", "libx264")])
def test_probe_counts_the_pictures_not_a_longer_audio_track(tmp_path, name, codec):
    """mkv and webm carry no frame count: the container's duration is the longest stream's, so
    a sound track running 0.5 s past 30 pictures must not add 15 frames (it did: 45)."""
    video = tmp_path / ("video" + name[name.rindex("."):])
    lavfi_clip(video, "30", 30, codec=codec)
    clip = tmp_path / name
    ffmpeg("-i", str(video), "-f", "lavfi", "-i", "sine=frequency=440:sample_rate=48000:duration=1.5",
           "-map", "0:v", "-map", "1:a", "-c:v", "copy", "-c:a", "libopus", str(clip))
    info = probe(clip)
    assert info.duration == pytest.approx(1.5, abs=0.05)  # the container's: the audio's
    assert info.frame_count == 30 == opencv_count(clip)
    with open_video(clip, width=48, info=info) as stream:
        assert sum(1 for _ in stream) == 30
    assert stream.shortfall is None


@pytest.mark.parametrize("name, rate, frames, audio, turn, clockwise", PROBE_CASES, ids=[c[0] for c in PROBE_CASES])
def test_probe_reads_what_the_file_was_made_with(tmp_path, name, rate, frames, audio, turn, clockwise):
    clip = tmp_path / name
    if turn is None:
        lavfi_clip(clip, rate, frames, audio, codec="libvpx-vp9" if name.endswith(".webm") else "libx264")
    else:
        plain = tmp_path / f"plain{clip.suffix}"
        lavfi_clip(plain, rate, frames, audio)
        ffmpeg("-display_rotation", str(turn), "-i", str(plain), "-c", "copy", str(clip))
    info = probe(clip)
    assert info.fps == pytest.approx(float(Fraction(rate)), rel=1e-9)  # exact, not ffmpeg's rounded 29.97
    assert info.frame_count == frames == opencv_count(clip)
    assert info.duration == pytest.approx(frames / float(Fraction(rate)), abs=0.05)
    assert info.rotation == clockwise
    assert info.source_size == ((90, 160) if clockwise in (90, 270) else (160, 90))
    assert info.audio_codec == {"libopus": "opus"}.get(audio, audio)
    assert [s.kind for s in info.streams] == (["audio"] if audio else [])
    assert info.damage is None
    with open_video(clip, width=48, info=info) as stream:
        decoded = list(stream)
    assert len(decoded) == frames and decoded[0].shape == (stream.info.size[1], stream.info.size[0], 3)
    assert stream.shortfall is None


def test_probe_of_a_variable_rate_video_counts_its_frames(tmp_path):
    """Frames 30 fps apart, then a half-second gap: the average rate, every frame counted."""
    clip = tmp_path / "vfr.mp4"
    ffmpeg("-f", "lavfi", "-i", "testsrc2=size=160x90:rate=30", "-frames:v", "60",
           "-vf", "setpts='N/30/TB+if(gte(N,30),0.5/TB,0)'", "-fps_mode", "passthrough", "-c:v", "libx264",
           "-preset", "ultrafast", "-pix_fmt", "yuv420p", str(clip))
    info = probe(clip)
    assert info.frame_count == 60 == opencv_count(clip)
    assert info.duration == pytest.approx(2.5, abs=0.01) and info.fps == pytest.approx(60 / 2.5, rel=0.01)


def test_probe_of_audio_longer_than_the_video_is_not_damage(tmp_path):
    """The container lasts as long as its audio: no frame in its last half second is no damage."""
    for suffix in (".mkv", ".mp4"):
        clip = tmp_path / f"long_audio{suffix}"
        ffmpeg("-f", "lavfi", "-t", "1", "-i", "testsrc2=size=160x90:rate=30", "-f", "lavfi", "-i",
               "sine=frequency=440:sample_rate=48000:duration=4", "-map", "0:v", "-map", "1:a", "-c:v", "libx264",
               "-preset", "ultrafast", "-pix_fmt", "yuv420p", "-c:a", "aac", str(clip))
        info = probe(clip)
        assert info.damage is None and info.has_audio and info.duration > 3.5
        with open_video(clip, info=info) as stream:
            assert sum(1 for _ in stream) == 30 == opencv_count(clip)


def test_reader_yuv420p_planes_are_the_rgb_frames_upright(tmp_path):
    """stabilize's render pass reads yuv420p planes: the same frames as RGB, turned upright too."""
    plain = tmp_path / "plain.mp4"
    lavfi_clip(plain, "30", 6)
    clip = tmp_path / "turned.mp4"
    ffmpeg("-display_rotation", "90", "-i", str(plain), "-c", "copy", str(clip))
    info = probe(clip)
    w, h = info.source_size
    with open_video(clip, yuv420p=True, info=info) as planes, open_video(clip, info=info) as rgb:
        pairs = list(zip(planes, rgb))
    assert len(pairs) == 6
    for yuv, frame in pairs:
        assert yuv.shape == (h * 3 // 2, w)
        as_rgb = cv2.cvtColor(yuv, cv2.COLOR_YUV2RGB_I420)
        assert np.abs(as_rgb.astype(np.float32) - frame).mean() < 3.0
    with pytest.raises(ValueError):
        open_video(clip, width=32, yuv420p=True, info=info)


# ---------------------------------------------------------------- one probe per command


@pytest.fixture
def media_starts(monkeypatch):
    """Every file libav opens in this process (the probe) and every ffmpeg process started, by argv."""
    import subprocess

    import av

    opened: list[str] = []
    started: list[list[str]] = []
    real_open, real_popen = av.open, subprocess.Popen

    def counting_open(file, *args, **kwargs):
        opened.append(str(file))
        return real_open(file, *args, **kwargs)

    class CountingPopen(real_popen):  # type: ignore[misc, valid-type]
        def __init__(self, args, *rest, **kwargs):
            if isinstance(args, (list, tuple)) and args and "ffmpeg" in os.path.basename(str(args[0])):
                started.append([str(a) for a in args])
            super().__init__(args, *rest, **kwargs)

    monkeypatch.setattr(av, "open", counting_open)
    monkeypatch.setattr(subprocess, "Popen", CountingPopen)
    return opened, started


def decoders(started: list[list[str]]) -> list[list[str]]:
    """The ffmpeg processes that decode a file to raw frames on a pipe."""
    return [cmd for cmd in started if cmd[-5:-2] == ["-f", "rawvideo", "-pix_fmt"] and cmd[-1] == "pipe:1"]


def encoders(started: list[list[str]]) -> list[list[str]]:
    """The ffmpeg processes that encode raw frames from a pipe."""
    return [cmd for cmd in started if "rawvideo" in cmd and cmd[cmd.index("-i") + 1] == "-"]


@pytest.mark.parametrize("command, decodes, encodes", [
    ("track", 2, 0),  # overlays sampled, then every frame
    ("stitch", 2, 0),  # overlays sampled, then the scan
    ("stabilize", 2, 1),  # overlays sampled, then every frame for the tracking and the render; one encoder
])
def test_each_command_probes_its_input_once(tmp_path, capsys, flight_clip, media_starts, command, decodes, encodes):
    """No second probe, no ffmpeg run only to read metadata: two libav opens of the input (the
    probe, and the overlay sampler reading where the keyframes are), and ffmpeg started only
    to decode (once per pass) or to encode."""
    from conftest import cli_exit

    mask = tmp_path / "mask.png"
    cv2.imwrite(str(mask), np.full((180, 320), 255, np.uint8))  # --mask: the commands' other early use of the size
    out = {"track": ["-o", tmp_path / "t.json"], "stitch": ["-o", tmp_path / "p.png"], "stabilize": [tmp_path / "s.mp4"]}[command]
    code = cli_exit([command, flight_clip, *out, "-e", "orb", "-q", "--mask", mask])
    assert code == 0, capsys.readouterr().err
    opened, started = media_starts
    assert opened == [str(flight_clip)] * 2
    assert len(decoders(started)) == decodes and len(encoders(started)) == encodes
    assert len(started) == decodes + encodes, started


def _ffmpeg_frames(path, pix_fmt: str = "rgb24", even: bool = False) -> list[np.ndarray]:
    """Every frame as ffmpeg itself converts it (the independent truth).  ``even``: padded to an
    even size first and cut back, so that an odd-sized frame takes ffmpeg's even-size conversion
    (nearest chroma, as OpenCV's) rather than its odd-size one (interpolated chroma)."""
    import subprocess

    from conftest import FFMPEG

    w, h = probe(path).source_size
    W, H = (w + w % 2, h + h % 2) if even else (w, h)
    pad = ["-vf", f"pad={W}:{H}"] if even else []
    raw = subprocess.run([FFMPEG, "-v", "error", "-i", str(path), *pad, "-f", "rawvideo", "-pix_fmt", pix_fmt, "-"],
                         capture_output=True, check=True).stdout
    frames = np.frombuffer(raw, np.uint8).reshape((-1, H, W, 3) if pix_fmt == "rgb24" else (-1, H, W))
    return list(frames[:, :h, :w])


def test_full_size_rgb_of_bt601_yuv420p_is_converted_here_as_ffmpeg_converts_it(tmp_path):
    """An untagged or BT.601 limited-range yuv420p stream read as RGB at full size is piped as
    yuv420p and converted here: the pixels are ffmpeg's within 3 levels (rounding: ffmpeg's
    are about a level darker), and each frame keeps its luma plane, whose gray copy is ffmpeg's
    own gray (what ``track`` decodes) exactly at full size, and within a level once resized
    (each size made once, read-only)."""
    from mosaic_cli.video.decode import LumaRGB, gray_at

    frames = [textured_image(320, 180, seed=k) for k in range(4)]
    for name, extra in (("untagged", []), ("bt601", ["-colorspace", "smpte170m", "-color_range", "tv"])):
        path = write_clip(tmp_path / f"{name}.mp4", frames, extra=extra)
        rgb, gray = _ffmpeg_frames(path), _ffmpeg_frames(path, "gray")
        with open_video(path) as stream:
            got = list(stream)
        assert len(got) == len(rgb) == len(gray) == 4
        for mine, theirs, their_gray in zip(got, rgb, gray):
            assert isinstance(mine, LumaRGB) and mine.luma is not None, name
            assert np.abs(mine.astype(int) - theirs).max() <= 3, name
            assert np.abs(mine.astype(float) - theirs).mean() < 1.5, name
            assert np.array_equal(gray_at(mine, (320, 180)), their_gray), name
            for size in ((160, 90), (64, 36)):
                expected = cv2.resize(their_gray, size, interpolation=cv2.INTER_AREA)
                assert np.abs(gray_at(mine, size).astype(int) - expected).max() <= 1, (name, size)
                # Made once per size: every stage that asks shares it, and none may change it.
                again = gray_at(mine, size)
                assert again is gray_at(mine, size) and not again.flags.writeable
                with pytest.raises(ValueError):
                    again[0, 0] = 0


def test_lazy_rgb_frames_are_the_converted_ones_converted_only_when_asked(tmp_path):
    """``open_video(..., lazy_rgb=True)`` (stitch's scan): each frame is RGB only once its pixels
    are asked for, then exactly the eagerly converted frame; its gray copies are those of the
    eager frame without any conversion; a stream that is not converted here comes as arrays."""
    from mosaic_cli.video.decode import YuvFrame, gray_at

    path = write_clip(tmp_path / "clip.mp4", [textured_image(320, 180, seed=k) for k in range(3)])
    with open_video(path) as stream:
        eager = list(stream)
    with open_video(path, lazy_rgb=True) as stream:
        lazy = list(stream)
    assert len(lazy) == len(eager) == 3
    for mine, theirs in zip(lazy, eager):
        assert isinstance(mine, YuvFrame) and mine.shape == theirs.shape and mine._rgb is None
        for size in ((320, 180), (160, 90)):
            assert np.array_equal(gray_at(mine, size), gray_at(theirs, size))
        assert mine._rgb is None  # the gray copies converted nothing
        pixels = np.asarray(mine)
        assert type(pixels) is np.ndarray and np.array_equal(pixels, theirs)
        assert np.asarray(mine) is pixels  # converted once
        copied = np.array(mine)  # a copy asked for is one
        assert copied is not pixels and np.array_equal(copied, pixels) and not np.shares_memory(copied, pixels)
    path = write_clip(tmp_path / "444.mp4", [textured_image(320, 180, seed=0)], pix_fmt="yuv444p")
    with open_video(path, lazy_rgb=True) as stream:
        assert all(type(f) is np.ndarray for f in stream)


@pytest.mark.parametrize("name, extra, pix_fmt, codec, suffix, size, levels", [
    ("bt709", ["-colorspace", "bt709", "-color_primaries", "bt709", "-color_trc", "bt709"], "yuv420p", "libx264", "mp4", (320, 180), 8),
    ("full range", [], "yuvj420p", "libx264", "mp4", (320, 180), 3),
    ("odd size", [], "yuv420p", "ffv1", "mkv", (321, 181), 3),
])
def test_rgb_of_other_4_2_0_streams_is_converted_here_near_ffmpeg_s(tmp_path, name, extra, pix_fmt, codec, suffix, size, levels):
    """Another colour matrix or range is brought to BT.601 limited range by ffmpeg before the
    conversion here; an odd size is converted with its luma padded: each near ffmpeg's own RGB.
    (For the odd size the truth is ffmpeg's conversion of the frame padded to an even size,
    whose last row and column carry the pad filter's own edge, so those are left out.)"""
    from mosaic_cli.video.decode import LumaRGB

    frames = [textured_image(*size, seed=k) for k in range(3)]
    path = write_clip(tmp_path / f"clip.{suffix}", frames, codec=codec, pix_fmt=pix_fmt, extra=extra)
    odd = size[0] % 2 or size[1] % 2
    truth = _ffmpeg_frames(path, even=bool(odd))
    with open_video(path) as stream:
        got = list(stream)
    assert len(got) == len(truth) == 3
    inner = np.s_[:-1, :-1] if odd else np.s_[:, :]
    for mine, theirs in zip(got, truth):
        assert isinstance(mine, LumaRGB) and mine.shape == theirs.shape, name
        difference = np.abs(mine.astype(int) - theirs)[inner]
        assert difference.max() <= levels, name
        assert difference.mean() < 1.5, name
    if odd:  # the whole frame, last row and column too, against BT.601's formula on ffmpeg's planes
        for mine, formula in zip(got, _bt601_of_yuv420p(path)):
            assert np.abs(mine.astype(float) - formula).max() <= 2, name


def _bt601_of_yuv420p(path) -> list[np.ndarray]:
    """RGB by BT.601's limited-range formula (float, then rounded) from the yuv420p planes ffmpeg
    decodes, each chroma sample covering its 2x2 pixels (the last ones cut at an odd edge)."""
    import subprocess

    from conftest import FFMPEG

    w, h = probe(path).source_size
    cw, ch = (w + 1) // 2, (h + 1) // 2
    raw = np.frombuffer(subprocess.run([FFMPEG, "-v", "error", "-i", str(path), "-f", "rawvideo", "-pix_fmt", "yuv420p", "-"],
                                       capture_output=True, check=True).stdout, np.uint8)
    out = []
    for frame in raw.reshape(-1, w * h + 2 * cw * ch):
        y = frame[:w * h].reshape(h, w).astype(float) - 16
        u, v = (frame[w * h + k * cw * ch:w * h + (k + 1) * cw * ch].reshape(ch, cw).repeat(2, 0).repeat(2, 1)[:h, :w].astype(float) - 128
                for k in (0, 1))
        rgb = np.stack([1.164 * y + 1.596 * v, 1.164 * y - 0.392 * u - 0.813 * v, 1.164 * y + 2.017 * u], axis=-1)
        out.append(np.clip(np.round(rgb), 0, 255))
    return out


def test_rgb_of_4_4_4_or_downscaled_is_ffmpeg_s_own_conversion(tmp_path):
    """A 4:4:4 stream keeps ffmpeg's conversion (bit for bit: no chroma lost to a 4:2:0 pipe), as
    does a downscaled read; slices of a converted frame drop the luma plane."""
    from mosaic_cli.video.decode import LumaRGB, gray_at

    path = write_clip(tmp_path / "444.mp4", [textured_image(320, 180, seed=k) for k in range(3)], pix_fmt="yuv444p")
    with open_video(path) as stream:
        got = list(stream)
    assert not any(isinstance(f, LumaRGB) for f in got)
    assert all(np.array_equal(a, b) for a, b in zip(got, _ffmpeg_frames(path)))
    path = write_clip(tmp_path / "clip.mp4", [textured_image(320, 180, seed=k) for k in range(2)])
    with open_video(path, width=160) as stream:
        assert not any(isinstance(f, LumaRGB) for f in stream)
    with open_video(path) as stream:
        frame = next(iter(stream))
    part = frame[10:90, 20:180]
    assert getattr(part, "luma", None) is None
    assert np.array_equal(gray_at(part, (80, 40)), cv2.resize(cv2.cvtColor(np.ascontiguousarray(part), cv2.COLOR_RGB2GRAY), (80, 40),
                                                                 interpolation=cv2.INTER_AREA))
