"""Decoding and probing speed of mosaic's video reader (docs/developer/video.md).

    python -m benchmarks decode                     # 1280x720 H.264, 300 frames, 3 rounds
    python -m benchmarks decode --rounds 5 --frames 600

One clip, decoded every way side by side in one run, the ways interleaved round after round
(the machine is shared: a slow spell hits every way alike), the median of the rounds reported:
frames per second of wall time; ``after/before``, the median of each round's ratio of the two
(a pair decoded seconds apart shares the machine's load of the moment); and milliseconds of CPU
per frame (this process and its ffmpeg children together: the cost, which a loaded machine
does not change much):

* ``before``: the reader before PyAV probing, i.e. imageio-ffmpeg's ``read_frames`` with the
  options mosaic passed it (rawvideo on a pipe, ffmpeg's scale filter, ``-fps_mode passthrough``);
* ``after``: ``mosaic_cli.video.open_video`` (its own ffmpeg pipe, ``readinto`` fresh arrays);
* ``pyav``: PyAV decoding in this process (frame threads on), converted by ``to_ndarray``
  (``reformat`` with the area filter for a smaller width).

The modes are what the commands decode: ``rgb``, full size (the stitch scan, stabilize's
render of odd sizes); ``gray@640`` (stabilize's track pass); ``gray@320`` (track's and stitch's
estimator input); ``yuv420p`` (stabilize's render pass); ``gray@640+orb`` the same frames with
ORB run on each, the track pass's shape of work (a decoder in another process overlaps it).

Probing: the probe before (imageio-ffmpeg's header read, one ffmpeg decoding a frame half a
second before the end, OpenCV's FFmpeg open for the exact rate and count) against
``mosaic_cli.video.probe`` (PyAV in-process: one open, the first frame, a seek to the end).

The clip flies over the NEON orthophoto in ../shared/data when present (a crop panning 40 x 25
px/s), else over ffmpeg's testsrc2 with film-grain noise.
"""

from __future__ import annotations

import logging
import statistics
import subprocess
import time
from pathlib import Path

import av
import cv2
import imageio_ffmpeg
import numpy as np

from benchmarks.common import ORTHOPHOTO, ROOT, cpu_seconds, make_parser
from mosaic_cli.video import VideoInfo, open_video, probe
from mosaic_cli.video.reader import scaled_size

SUITE = "decode"

FFMPEG = imageio_ffmpeg.get_ffmpeg_exe()
logging.getLogger("imageio_ffmpeg").setLevel(logging.ERROR)  # its note on every downscaled read


def make_clip(path: Path, frames: int) -> str:
    common = ["-frames:v", str(frames), "-r", "30", "-c:v", "libx264", "-preset", "veryfast", "-crf", "20", "-pix_fmt", "yuv420p", str(path)]
    if ORTHOPHOTO.is_file():
        source = ["-loop", "1", "-framerate", "30", "-i", str(ORTHOPHOTO), "-vf", "crop=1280:720:x='40*t':y='25*t'"]
        what = f"a pan over {ORTHOPHOTO.name}"
    else:
        source = ["-f", "lavfi", "-i", "testsrc2=size=1280x720:rate=30", "-vf", "noise=alls=20:allf=t"]
        what = "testsrc2 with noise"
    subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", *source, *common], check=True)
    return what


# --- the ways to decode -------------------------------------------------------------------

def before(path: Path, mode: str, work, info: VideoInfo) -> int:
    pixels, width = mode_of(mode)
    source_size = info.source_size
    size = scaled_size(source_size, width)
    out = ["-fps_mode", "passthrough"]
    if size != source_size:
        out = ["-vf", f"scale={size[0]}:{size[1]}:flags=area"] + out
    pix_fmt, bits = {"rgb": ("rgb24", 24), "gray": ("gray", 8), "yuv420p": ("yuv420p", 12)}[pixels]
    shape = {"rgb": (size[1], size[0], 3), "gray": (size[1], size[0]), "yuv420p": (size[1] * 3 // 2, size[0])}[pixels]
    gen = imageio_ffmpeg.read_frames(str(path), pix_fmt=pix_fmt, bits_per_pixel=bits, output_params=out)
    next(gen)
    n = 0
    for raw in gen:
        work(np.frombuffer(raw, np.uint8).reshape(shape))
        n += 1
    return n


def after(path: Path, mode: str, work, info: VideoInfo) -> int:
    pixels, width = mode_of(mode)
    n = 0
    with open_video(path, width=width, gray=pixels == "gray", yuv420p=pixels == "yuv420p", info=info) as stream:
        for frame in stream:
            work(frame)
            n += 1
    return n


def pyav(path: Path, mode: str, work, info: VideoInfo) -> int:
    pixels, width = mode_of(mode)
    fmt = {"rgb": "rgb24", "gray": "gray", "yuv420p": "yuv420p"}[pixels]
    n = 0
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        size = scaled_size((stream.codec_context.width, stream.codec_context.height), width)
        for frame in container.decode(stream):
            if size != (frame.width, frame.height):
                frame = frame.reformat(width=size[0], height=size[1], format=fmt, interpolation="AREA")
            work(frame.to_ndarray(format=fmt))
            n += 1
    return n


def mode_of(mode: str) -> tuple[str, int | None]:
    name = mode.split("+")[0]
    pixels, _, width = name.partition("@")
    return pixels, int(width) if width else None


def work_for(mode: str):
    if mode.endswith("+orb"):
        orb = cv2.ORB_create(1000)
        return lambda frame: orb.detectAndCompute(frame, None)
    return lambda frame: None


# --- probing ------------------------------------------------------------------------------

def probe_before(path: Path) -> None:
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    gen.close()
    seek = ["-sseof", "-0.5"] if float(meta.get("duration") or 0) > 0.5 else []
    subprocess.run([FFMPEG, "-hide_banner", "-nostdin", *seek, "-i", str(path), "-map", "0:v:0", "-frames:v", "1",
                    "-f", "rawvideo", "-pix_fmt", "gray", "-"], capture_output=True, timeout=60)
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    capture.get(cv2.CAP_PROP_FRAME_COUNT)
    capture.release()


def main(argv: list[str] | None = None) -> int | None:
    parser = make_parser(SUITE, None, __doc__)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=ROOT / ".dev" / "bench_decode")
    args = parser.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    clip = args.workdir / "clip720.mp4"
    what = make_clip(clip, args.frames)
    info = probe(clip)
    print(f"{clip.name}: {info.source_size[0]}x{info.source_size[1]} H.264, {info.frame_count} frames, {what}; "
          f"ffmpeg {imageio_ffmpeg.get_ffmpeg_version()}, PyAV {av.__version__}, {args.rounds} rounds (median)")

    modes = ["rgb", "gray@640", "gray@320", "yuv420p", "gray@640+orb"]
    ways = {"before": before, "after": after, "pyav": pyav}
    rates: dict[tuple[str, str], list[float]] = {}
    cpu: dict[tuple[str, str], list[float]] = {}
    probes: dict[str, list[float]] = {"before": [], "after": []}
    for _ in range(args.rounds):
        for mode in modes:
            for name, decode in ways.items():
                clock, used = time.perf_counter(), cpu_seconds()
                n = decode(clip, mode, work_for(mode), info)  # (probed once: decoding alone is timed)
                rates.setdefault((mode, name), []).append(n / (time.perf_counter() - clock))
                cpu.setdefault((mode, name), []).append(1000 * (cpu_seconds() - used) / n)
                if n != info.frame_count:
                    raise SystemExit(f"{name} {mode}: {n} frames of {info.frame_count}")
        for name, fn in (("before", probe_before), ("after", probe)):
            clock = time.perf_counter()
            fn(clip)
            probes[name].append(1000 * (time.perf_counter() - clock))

    print(f"\n| decode | {' | '.join(f'{w} fr/s' for w in ways)} | after/before | {' | '.join(f'{w} CPU ms/frame' for w in ways)} |")
    print("|---|" + "---:|" * (2 * len(ways) + 1))
    for mode in modes:
        paired = statistics.median(a / b for a, b in zip(rates[(mode, "after")], rates[(mode, "before")]))
        print(f"| {mode} | " + " | ".join(f"{statistics.median(rates[(mode, name)]):.1f}" for name in ways) + f" | {paired:.2f} | "
              + " | ".join(f"{statistics.median(cpu[(mode, name)]):.2f}" for name in ways) + " |")
    print(f"\nprobe: before {statistics.median(probes['before']):.0f} ms, after {statistics.median(probes['after']):.0f} ms")
