#!/usr/bin/env python3
"""Does ``mosaic stabilize`` write exactly the frames it was given?  On every kind of input a
camera or an editor makes: with and without audio, audio shorter or longer than the picture,
odd frame rates (29.97, 23.976, 25, 60), variable frame rate, mkv and mov containers, a clip
cut without re-encoding (edit list), an odd frame size, an image folder.

Each input is made here from one shaky simulated flight; input and output frames are counted
by decoding them with OpenCV (every coded frame once; no ffprobe, no container figures).
Prints a markdown table and exits 1 if any count differs.

    python scripts/check_stabilize_frames.py                     # 150 frames at 320x180, -e orb
    python scripts/check_stabilize_frames.py --frames 300 --size 852x480 --estimator lstm --workdir /tmp/frames
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import imageio_ffmpeg

FFMPEG = imageio_ffmpeg.get_ffmpeg_exe()


def ffmpeg(*args: str) -> None:
    subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", *args], check=True)


def decoded_count(path: Path) -> int:
    """Frames OpenCV decodes (a folder: its images)."""
    if path.is_dir():
        return len(list(path.glob("*.png")))
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    count = 0
    while capture.grab():
        count += 1
    capture.release()
    return count


def audio_seconds(path: Path) -> float | None:
    run = subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-i", str(path), "-map", "0:a:0?", "-ac", "1",
                          "-ar", "48000", "-f", "s16le", "-"], capture_output=True)
    return len(run.stdout) / 2 / 48000 if run.stdout else None


def make_inputs(flight: Path, seconds: float, work: Path) -> dict[str, Path]:
    """name -> input file (or folder), all made from ``flight`` (30 fps, no audio)."""
    x264 = ["-c:v", "libx264", "-preset", "veryfast", "-crf", "16", "-pix_fmt", "yuv420p"]

    def sine(duration: float) -> list[str]:
        return ["-f", "lavfi", "-i", f"sine=frequency=440:sample_rate=48000:duration={duration:.3f}"]

    def with_audio(name: str, video: Path, duration: float, codec: str = "aac") -> Path:
        out = work / name
        ffmpeg("-i", str(video), *sine(duration), "-map", "0:v", "-map", "1:a", "-c:v", "copy", "-c:a", codec, str(out))
        return out

    def retimed(name: str, rate: str) -> Path:
        out = work / name
        ffmpeg("-i", str(flight), "-vf", f"setpts=N/({rate})/TB", "-r", rate, *x264, str(out))
        return out

    inputs: dict[str, Path] = {"30 fps, no audio": flight}
    inputs["30 fps, AAC as long"] = with_audio("equal.mp4", flight, seconds)
    inputs["30 fps, AAC 0.02 s shorter"] = with_audio("short002.mp4", flight, seconds - 0.02)
    inputs["30 fps, AAC 0.3 s shorter"] = with_audio("short03.mp4", flight, seconds - 0.3)
    inputs["30 fps, AAC 2 s longer"] = with_audio("long2.mp4", flight, seconds + 2)
    for rate, label, delta in (("30000/1001", "29.97", -0.1), ("24000/1001", "23.976", +1.0), ("25", "25", -0.05),
                               ("60", "60", 0.0)):
        video = retimed(f"r{label}.mp4", rate)
        n = decoded_count(video)
        num, _, den = rate.partition("/")
        length = n * (float(den) if den else 1.0) / float(num)
        inputs[f"{label} fps, AAC {delta:+.2f} s"] = with_audio(f"r{label}_audio.mp4", video, length + delta)
    vfr = work / "vfr.mp4"
    ffmpeg("-i", str(flight), *sine(seconds * 1.2), "-map", "0:v", "-map", "1:a",
           "-vf", "setpts='(N+floor(N/10)*0.6+0.3*sin(N))/30/TB'", "-fps_mode", "vfr", *x264, "-c:a", "aac", str(vfr))
    inputs["variable rate, AAC"] = vfr
    mkv = work / "audio.mkv"
    ffmpeg("-i", str(inputs["30 fps, AAC 0.3 s shorter"]), "-c", "copy", str(mkv))
    inputs["mkv, AAC 0.3 s shorter"] = mkv
    mov = work / "pcm.mov"
    ffmpeg("-i", str(flight), *sine(seconds - 0.1), "-map", "0:v", "-map", "1:a", "-c:v", "copy", "-c:a", "pcm_s16le", str(mov))
    inputs["mov, PCM audio (re-encoded to AAC)"] = mov
    trimmed = work / "trimmed.mp4"
    ffmpeg("-ss", f"{seconds / 3:.2f}", "-i", str(inputs["30 fps, AAC as long"]), "-c", "copy", str(trimmed))
    inputs["cut without re-encoding (edit list), AAC"] = trimmed
    odd = work / "odd.mp4"
    ffmpeg("-i", str(inputs["30 fps, AAC 0.3 s shorter"]), "-vf", "crop=iw-1:ih-1:0:0", "-c:v", "libx264", "-preset",
           "veryfast", "-crf", "16", "-pix_fmt", "yuv444p", "-c:a", "copy", str(odd))
    inputs["odd size (yuv444p), AAC"] = odd
    folder = work / "frames"
    folder.mkdir(exist_ok=True)
    ffmpeg("-i", str(flight), str(folder / "f_%04d.png"))
    inputs["image folder"] = folder
    return inputs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--size", default="320x180")
    parser.add_argument("--estimator", default="orb")
    parser.add_argument("--workdir", default=None, help="keep the inputs here (default: a temporary folder)")
    args = parser.parse_args()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="mosaic-frames-"))
    work.mkdir(parents=True, exist_ok=True)
    flight = work / "flight.mp4"
    subprocess.run([sys.executable, "-m", "mosaic_cli", "simulate", "-o", str(flight), "-n", str(args.frames),
                    "--profile", "shaky", "--size", args.size, "--preset", "veryfast", "-q"], check=True)
    inputs = make_inputs(flight, args.frames / 30.0, work)
    print("| input | frames in | frames out | audio in (s) | audio out (s) | video out (s) |\n|---|---:|---:|---:|---:|---:|")
    failed = 0
    for name, path in inputs.items():
        out = work / f"out_{path.stem}.mp4"
        run = subprocess.run([sys.executable, "-m", "mosaic_cli", "stabilize", str(path), str(out), "-e", args.estimator, "-q"],
                             capture_output=True, text=True)
        if run.returncode != 0:
            print(f"| {name} | {decoded_count(path)} | failed: {run.stderr.strip()} | | | |")
            failed += 1
            continue
        n_in, n_out = decoded_count(path), decoded_count(out)
        capture = cv2.VideoCapture(str(out), cv2.CAP_FFMPEG)
        video_s = n_out / capture.get(cv2.CAP_PROP_FPS)
        capture.release()
        a_in, a_out = audio_seconds(path) if path.is_file() else None, audio_seconds(out)
        fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
        mark = "" if n_in == n_out else " **differs**"
        failed += n_in != n_out
        print(f"| {name} | {n_in} | {n_out}{mark} | {fmt(a_in)} | {fmt(a_out)} | {video_s:.3f} |", flush=True)
    print(f"\n{len(inputs) - failed} of {len(inputs)} inputs kept every frame")
    raise SystemExit(1 if failed else 0)


if __name__ == "__main__":
    main()
