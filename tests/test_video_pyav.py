"""The PyAV backend (MOSAIC_VIDEO_BACKEND=pyav) against the ffmpeg binary's as the truth: the
same frames decoded every way the commands decode, the same files written."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import ffmpeg, textured_image, write_clip
from mosaic_cli.errors import BadInput
from mosaic_cli.video import VideoWriter, open_video, probe
from mosaic_cli.video.backend import ENV, video_backend
from mosaic_cli.video.decode import FfmpegDecoder, PyAVDecoder, frame_at, frames_at

N = 20


def moving_frames(width: int, height: int, n: int = N, seed: int = 5) -> list[np.ndarray]:
    """Distinct frames (a texture panning 7 px per frame), so that order mistakes show."""
    tex = textured_image(width + 7 * n, height, seed=seed)
    return [np.ascontiguousarray(tex[:, 7 * k:7 * k + width]) for k in range(n)]


@pytest.fixture(scope="module")
def clips(tmp_path_factory) -> dict[str, object]:
    """An even-sized H.264 mp4 with B-frames (so that reference-only picks skip some), and an
    odd-sized 4:2:0 ffv1 mkv (x264 takes no odd size)."""
    folder = tmp_path_factory.mktemp("pyav")
    even = write_clip(folder / "even.mp4", moving_frames(160, 96), fps=25, extra=["-preset", "medium"])
    odd = write_clip(folder / "odd.mkv", moving_frames(161, 97), fps=25, codec="ffv1")
    return {"even": even, "odd": odd}


def both(monkeypatch, call, *args, **kwargs):
    """``call(*args, **kwargs)`` with the ffmpeg backend, then with PyAV's."""
    monkeypatch.setenv(ENV, "ffmpeg")
    truth = call(*args, **kwargs)
    monkeypatch.setenv(ENV, "pyav")
    return truth, call(*args, **kwargs)


def assert_equal_frames(truth, got, tolerance: int = 0) -> None:
    assert len(got) == len(truth) > 0
    for a, b in zip(truth, got):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and a.dtype == b.dtype == np.uint8
        assert np.abs(a.astype(int) - b).max() <= tolerance


def read(path, **kwargs) -> list[np.ndarray]:
    with open_video(path, **kwargs) as stream:
        return list(stream)


# ---------------------------------------------------------------- choosing


def test_video_backend_env_var(monkeypatch):
    monkeypatch.setenv(ENV, "pyav")
    assert video_backend() == "pyav"
    monkeypatch.setenv(ENV, "ffmpeg")
    assert video_backend() == "ffmpeg"
    monkeypatch.setenv(ENV, "gstreamer")
    with pytest.raises(BadInput, match=ENV):
        video_backend()
    monkeypatch.delenv(ENV)
    assert video_backend() in ("ffmpeg", "pyav")


def test_video_backend_without_ffmpeg_is_pyav(monkeypatch):
    import sys

    from mosaic_cli.video import backend

    monkeypatch.delenv(ENV, raising=False)
    monkeypatch.delenv("IMAGEIO_FFMPEG_EXE", raising=False)
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # (an import of it then fails)
    backend.reset()
    try:
        assert video_backend() == "pyav"
    finally:
        backend.reset()


def test_decoder_follows_the_backend(monkeypatch, clips):
    from mosaic_cli.video.reader import Decoder

    info = probe(clips["even"])
    for name, kind in (("ffmpeg", FfmpegDecoder), ("pyav", PyAVDecoder)):
        monkeypatch.setenv(ENV, name)
        with Decoder(info, "gray", (32, 19)) as decoder:
            assert type(decoder) is kind
            assert len(list(decoder)) == N and decoder.error is None


# ---------------------------------------------------------------- decoding


@pytest.mark.parametrize("clip", ["even", "odd"])
def test_gray_downscaled_is_ffmpeg_s(monkeypatch, clips, clip):
    """swscale's area filter in both: equal (measured: 0 levels apart)."""
    truth, got = both(monkeypatch, lambda: read(clips[clip], width=80, gray=True))
    assert_equal_frames(truth, got)
    assert all(f.flags.writeable for f in got)


@pytest.mark.parametrize("clip", ["even", "odd"])
def test_rgb_full_size_and_lazy_are_ffmpeg_s(monkeypatch, clips, clip):
    from mosaic_cli.video.decode import LumaRGB, YuvFrame

    truth, got = both(monkeypatch, lambda: read(clips[clip]))
    assert_equal_frames(truth, got)
    assert all(isinstance(f, LumaRGB) for f in got)
    truth, got = both(monkeypatch, lambda: read(clips[clip], lazy_rgb=True))
    assert all(isinstance(f, YuvFrame) for f in got)
    assert_equal_frames(truth, got)


def test_rgb_downscaled_is_near_ffmpeg_s(monkeypatch, clips):
    """Downscaled RGB: swscale's area filter and conversion in both; equal on the ffv1 clip, but
    on H.264 (its chroma sited left) the two libswscale builds differ by a level on average."""
    for clip, mean in (("odd", 0.0), ("even", 1.5)):
        truth, got = both(monkeypatch, read, clips[clip], width=80)
        assert len(truth) == len(got) == N
        assert max(np.abs(a.astype(int) - b).mean() for a, b in zip(truth, got)) <= mean


def test_yuv420p_planes_and_start(monkeypatch, clips):
    truth, got = both(monkeypatch, lambda: read(clips["even"], yuv420p=True))
    assert_equal_frames(truth, got)
    for clip in ("even", "odd"):
        truth, got = both(monkeypatch, read, clips[clip], start=7, gray=True)
        assert len(truth) == N - 7
        assert_equal_frames(truth, got)


def test_frames_at_and_frame_at(monkeypatch, clips):
    for clip in ("even", "odd"):
        info = probe(clips[clip])
        picks = [0, 3, 4, 11, N - 1, N + 5]
        for near in (False, True):
            truth, got = both(monkeypatch, lambda *a, **k: list(frames_at(*a, **k)), info, picks, near=near)
            assert_equal_frames(truth, got)
        for seconds in (0.0, 0.33, 0.4, 0.79, 5.0):
            for near in (False, True):
                truth, got = both(monkeypatch, frame_at, info, seconds, near=near)
                if truth is None:
                    assert got is None
                else:
                    assert_equal_frames([truth], [got])


@pytest.mark.parametrize("display_rotation", [-90, 180])
def test_rotated_frames_are_upright_as_ffmpeg_s(monkeypatch, tmp_path, clips, display_rotation):
    """ffmpeg turns frames upright while decoding; PyAV's are turned here, the same way."""
    turned = tmp_path / "turned.mp4"
    ffmpeg("-display_rotation", str(display_rotation), "-i", str(clips["even"]), "-c", "copy", str(turned))
    assert probe(turned).rotation != 0
    for kwargs in ({}, {"gray": True}, {"yuv420p": True}, {"lazy_rgb": True}):
        truth, got = both(monkeypatch, read, turned, **kwargs)
        assert_equal_frames(truth, got)
    truth, got = both(monkeypatch, lambda: read(turned, width=48, gray=True))
    assert_equal_frames(truth, got, tolerance=2)  # (scaled before the turn here, after it in ffmpeg)


# ---------------------------------------------------------------- writing


def write(path, frames, size, **kwargs):
    with VideoWriter(path, size, fps=25, preset="ultrafast", **kwargs) as writer:
        for frame in frames:
            writer.write(frame)
    return path


@pytest.mark.parametrize("size", [(160, 96), (161, 97)])
def test_writer_backends_write_the_same_video(monkeypatch, tmp_path, size):
    frames = moving_frames(*size, n=12)
    meta = {"comment": "pyav test"}
    a, b = both(monkeypatch, lambda: write(tmp_path / f"{video_backend()}.mp4", frames, size, metadata=meta))
    monkeypatch.setenv(ENV, "ffmpeg")  # both read by ffmpeg
    for path in (a, b):
        info = probe(path)
        assert info.source_size == (size[0] + size[0] % 2, size[1] + size[1] % 2) and info.fps == pytest.approx(25)
    fa, fb = read(a), read(b)
    assert len(fa) == len(fb) == 12
    assert max(np.abs(x.astype(int) - y).mean() for x, y in zip(fa, fb)) < 1.0
    import av

    with av.open(str(b)) as container:
        assert container.metadata.get("comment") == "pyav test"
        assert container.streams.video[0].codec_context.name == "h264"


def test_writer_takes_yuv420p_planes(monkeypatch, tmp_path, clips):
    planes = read(clips["even"], yuv420p=True)
    a, b = both(monkeypatch, lambda: write(tmp_path / f"{video_backend()}.mp4", planes, (160, 96), pix_fmt_in="yuv420p"))
    monkeypatch.setenv(ENV, "ffmpeg")
    fa, fb = read(a), read(b)
    assert len(fa) == len(fb) == N
    assert max(np.abs(x.astype(int) - y).mean() for x, y in zip(fa, fb)) < 1.0


@pytest.mark.parametrize("audio, suffix", [("aac", "mp4"), ("pcm_s16le", "mkv")])  # copied; re-encoded to AAC
def test_writer_carries_audio_cut(monkeypatch, tmp_path, audio, suffix):
    import av

    source = tmp_path / f"with_audio.{suffix}"
    ffmpeg("-f", "lavfi", "-i", "testsrc2=size=128x72:rate=25", "-f", "lavfi", "-i", "sine=frequency=440",
           "-t", "3", "-c:v", "libx264", "-preset", "ultrafast", "-c:a", audio, str(source))
    frames = moving_frames(128, 72, n=12)
    out = {}
    for name in ("ffmpeg", "pyav"):
        monkeypatch.setenv(ENV, name)
        out[name] = write(tmp_path / f"{name}.mp4", frames, (128, 72), audio_from=probe(source), audio_seconds=0.5)
    seconds = {}
    for name, path in out.items():
        with av.open(str(path)) as container:
            stream = container.streams.audio[0]
            assert stream.codec_context.name == "aac"
            seconds[name] = float(stream.duration * stream.time_base)
            assert container.streams.video[0].frames == 12
    # A copy keeps whole packets (either may overhang by one); an encode ends within a frame.
    assert seconds["pyav"] == pytest.approx(seconds["ffmpeg"], abs=0.05)
    assert 0.45 < seconds["pyav"] < 0.56


def test_writer_abort_leaves_nothing(monkeypatch, tmp_path):
    monkeypatch.setenv(ENV, "pyav")
    target = tmp_path / "out.mp4"
    with pytest.raises(RuntimeError):
        with VideoWriter(target, (64, 48), fps=25, preset="ultrafast") as writer:
            writer.write(np.zeros((48, 64, 3), np.uint8))
            raise RuntimeError("stop")
    assert list(tmp_path.iterdir()) == []
    writer = VideoWriter(target, (64, 48), fps=25)
    writer.abort()
    assert list(tmp_path.iterdir()) == []


def test_the_read_ahead_hands_over_every_item_in_order_and_stays_bounded():
    import threading

    from mosaic_cli.video.decode import ReadAhead

    made = []

    def source():
        for k in range(50):
            made.append(k)
            yield k

    ahead = ReadAhead(source(), 3)
    first = next(iter(ahead))
    deadline = threading.Event()
    deadline.wait(0.2)  # the thread runs ahead as far as it may
    assert first == 0 and len(made) <= 1 + 3 + 1  # the item read, the queue's 3, one waiting to be queued
    assert [first, *ahead] == list(range(50))
    ahead.stop()


def test_the_read_ahead_raises_the_sources_error_to_the_reader_and_stops_early_cleanly():
    from mosaic_cli.video.decode import ReadAhead

    def failing():
        yield 1
        raise ValueError("broken frame")

    with pytest.raises(ValueError, match="broken frame"):
        list(ReadAhead(failing(), 2))
    closed = []

    def endless():
        try:
            k = 0
            while True:
                yield k
                k += 1
        finally:
            closed.append(True)

    ahead = ReadAhead(endless(), 2)
    assert next(iter(ahead)) == 0
    ahead.stop()  # the reader stops early: the thread ends and closes its source
    assert closed == [True]
