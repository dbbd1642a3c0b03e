"""Frame counts survive every stage: the reader yields each coded frame once (variable frame
rate included), the writer keeps every frame written whatever the length of the audio it
carries, and ``stabilize`` writes as many frames as it read.

Counts are checked against the frames put into each clip here, decoded back with OpenCV
(its own FFmpeg build, each frame once), not with mosaic's reader or ffprobe."""

from __future__ import annotations

from fractions import Fraction

import cv2
import numpy as np
import pytest
from test_stabilize import shaky_path

from conftest import FFMPEG, ffmpeg, render, textured_image
from mosaic_cli.cli import main
from mosaic_cli.video import VideoWriter, open_video, probe


def decoded_count(path) -> int:
    """Frames OpenCV decodes from ``path`` (every coded frame once, no frame-rate conversion)."""
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    assert capture.isOpened()
    count = 0
    while capture.grab():
        count += 1
    capture.release()
    return count


def audio_seconds(path) -> float:
    """Duration of the first audio stream, decoded by ffmpeg to raw samples (48 kHz mono)."""
    import subprocess

    run = subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-i", str(path), "-map", "0:a:0", "-ac", "1",
                          "-ar", "48000", "-f", "s16le", "-"], capture_output=True, check=True)
    return len(run.stdout) / 2 / 48000


def numbered_frames(n: int, size=(96, 64)) -> list[np.ndarray]:
    """Frames whose mean grey level encodes their index (so a dropped or repeated one shows)."""
    return [np.full((size[1], size[0], 3), 20 + 4 * k, np.uint8) for k in range(n)]


def frame_index(frame: np.ndarray) -> int:
    return int(round((float(frame.mean()) - 20) / 4))


def sound(path, seconds: float) -> None:
    ffmpeg("-f", "lavfi", "-i", f"sine=frequency=440:sample_rate=48000:duration={seconds}", "-c:a", "aac", str(path))


RATES = [Fraction(30000, 1001), Fraction(24000, 1001), Fraction(25), Fraction(30)]


@pytest.mark.parametrize("rate", RATES, ids=lambda r: f"{float(r):.3f}")
@pytest.mark.parametrize("audio_share", [0.9, 1.3])  # audio shorter, longer than the video
def test_writer_keeps_every_frame_whatever_the_audio(tmp_path, rate, audio_share):
    n = 40
    audio = tmp_path / "sound.m4a"
    video_seconds = n / float(rate)
    sound(audio, round(audio_share * video_seconds, 3))
    out = tmp_path / "out.mp4"
    with VideoWriter(out, (96, 64), float(rate), preset="ultrafast", audio_from=audio,
                     audio_seconds=video_seconds) as writer:
        for frame in numbered_frames(n):
            writer.write(frame)
    assert decoded_count(out) == n
    info = probe(out)
    assert info.has_audio
    assert Fraction(info.fps).limit_denominator(2000) == rate
    # The audio is cut where the video ends (to one AAC frame), never the video where the audio ends.
    assert audio_seconds(out) <= video_seconds + 0.05
    if audio_share > 1:
        assert audio_seconds(out) >= video_seconds - 0.05


def variable_rate_clip(path, n: int) -> list[float]:
    """``n`` numbered frames at irregular times (gaps of 1/30 s to 1/10 s); returns the times."""
    rng = np.random.default_rng(3)
    times = np.concatenate([[0.0], np.cumsum(rng.choice([1 / 30, 1 / 20, 1 / 10], n - 1))])
    frames = numbered_frames(n)
    folder = path.parent / "vfr_frames"
    folder.mkdir()
    lines = []
    for k, frame in enumerate(frames):
        name = folder / f"{k:04d}.png"
        cv2.imwrite(str(name), frame)
        duration = times[k + 1] - times[k] if k + 1 < n else 1 / 30
        lines += [f"file '{name}'", f"duration {duration:.6f}"]
    lines.append(f"file '{folder / f'{n - 1:04d}.png'}'")  # the concat demuxer's last-entry rule
    listing = path.parent / "frames.txt"
    listing.write_text("\n".join(lines) + "\n")
    ffmpeg("-f", "concat", "-safe", "0", "-i", str(listing), "-fps_mode", "vfr", "-frames:v", str(n), "-c:v", "libx264", "-preset", "ultrafast", "-qp", "0",
           "-pix_fmt", "yuv420p", str(path))
    return list(times)


def test_reader_yields_each_frame_of_a_variable_rate_video_once(tmp_path):
    clip = tmp_path / "vfr.mp4"
    variable_rate_clip(clip, 45)
    assert decoded_count(clip) == 45
    with open_video(clip) as stream:
        indices = [frame_index(f) for f in stream]
    assert indices == list(range(45))  # a constant-rate resampling would repeat and drop frames
    with open_video(clip, width=48, gray=True) as stream:
        assert sum(1 for _ in stream) == 45


def shaky_frames(n: int) -> list[np.ndarray]:
    shaken, _ = shaky_path(n, seed=11)
    texture = textured_image(700, 500, seed=11)
    return [render(texture, np.linalg.inv(M), (320, 180)) for M in shaken]


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["29.97 fps, audio shorter", "variable rate with audio"])
def test_stabilize_writes_as_many_frames_as_it_reads(tmp_path, capsys, kind):
    n = 48
    clip = tmp_path / "in.mp4"
    if kind.startswith("variable"):
        # shaky frames at irregular times, with a sound track longer than the video
        folder = tmp_path / "shaky"
        folder.mkdir()
        frames = shaky_frames(n)
        rng = np.random.default_rng(5)
        gaps = rng.choice([1 / 30, 1 / 15], n)
        lines = []
        for k, frame in enumerate(frames):
            name = folder / f"{k:04d}.png"
            cv2.imwrite(str(name), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
            lines += [f"file '{name}'", f"duration {gaps[k]:.6f}"]
        lines.append(f"file '{folder / f'{n - 1:04d}.png'}'")
        (tmp_path / "list.txt").write_text("\n".join(lines) + "\n")
        ffmpeg("-f", "concat", "-safe", "0", "-i", str(tmp_path / "list.txt"), "-f", "lavfi", "-i",
               "sine=frequency=440:sample_rate=48000:duration=10", "-map", "0:v", "-map", "1:a", "-fps_mode", "vfr",
               "-frames:v", str(n), "-c:v", "libx264", "-preset", "ultrafast", "-crf", "12", "-pix_fmt", "yuv420p",
               "-c:a", "aac", str(clip))
    else:
        silent = tmp_path / "silent.mp4"
        with VideoWriter(silent, (320, 180), 30000 / 1001, crf=12, preset="ultrafast") as writer:
            for frame in shaky_frames(n):
                writer.write(frame)
        # the sound stops 0.2 s before the picture, as a camera's track may
        ffmpeg("-i", str(silent), "-f", "lavfi", "-i", f"sine=frequency=440:sample_rate=48000:duration={n / 29.97 - 0.2:.3f}",
               "-map", "0:v", "-map", "1:a", "-c:v", "copy", "-c:a", "aac", str(clip))
    assert decoded_count(clip) == n
    out = tmp_path / "steady.mp4"
    with pytest.raises(SystemExit) as exit_info:
        main(["stabilize", str(clip), str(out), "-e", "orb", "-q"])
    assert exit_info.value.code in (0, None), capsys.readouterr().err
    assert decoded_count(out) == n
    source, result = probe(clip), probe(out)
    assert result.has_audio
    # same duration (the output is at the input's average rate), so the sound stays in step
    assert n / result.fps == pytest.approx(n / source.fps, rel=0.01)
