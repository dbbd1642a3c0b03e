"""What raw-frame pipes cost against decoding and encoding inside this process (PyAV).

    python scripts/bench_pipes.py CLIP transcode|pipes|pyav

transcode: one ffmpeg process (the floor); pipes: ffmpeg decoding to yuv420p on a pipe, this
process reading each frame and writing it to an x264 ffmpeg on another pipe (what stabilize's
render does, without the warp); pyav: the same decode and encode in this process with PyAV's
bundled libav.  Everyone encodes with -preset veryfast -crf 18.  Prints the wall and CPU seconds
(this process and its children).  docs/measurements/speed.md has the figures.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time

import av
import imageio_ffmpeg
import numpy as np


def cpu_seconds() -> float:
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def main(src: str, mode: str) -> None:
    ffmpeg = imageio_ffmpeg.get_ffmpeg_exe()
    out = f"/tmp/bench_pipes_{mode}.mp4"
    with av.open(src) as container:
        stream = container.streams.video[0]
        w, h, rate = stream.codec_context.width, stream.codec_context.height, stream.average_rate
    x264 = ["-c:v", "libx264", "-preset", "veryfast", "-crf", "18", "-pix_fmt", "yuv420p"]
    started, cpu, frames = time.perf_counter(), cpu_seconds(), 0
    if mode == "transcode":
        subprocess.run([ffmpeg, "-v", "error", "-y", "-i", src, "-an", *x264, out], check=True)
    elif mode == "pipes":
        size = w * h * 3 // 2
        decoder = subprocess.Popen([ffmpeg, "-v", "error", "-i", src, "-f", "rawvideo", "-pix_fmt", "yuv420p", "-"],
                                   stdout=subprocess.PIPE, bufsize=0)
        encoder = subprocess.Popen([ffmpeg, "-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "yuv420p", "-s", f"{w}x{h}",
                                    "-r", str(rate), "-i", "-", *x264, out], stdin=subprocess.PIPE)
        while True:
            frame = np.empty(size, np.uint8)
            view, got = memoryview(frame), 0
            while got < size and (n := decoder.stdout.readinto(view[got:])):
                got += n
            if got < size:
                break
            encoder.stdin.write(frame.data)
            frames += 1
        encoder.stdin.close()
        encoder.wait()
        decoder.wait()
    elif mode == "pyav":
        with av.open(src) as source, av.open(out, "w") as sink:
            video = source.streams.video[0]
            video.thread_type = "AUTO"
            encoded = sink.add_stream("libx264", rate=rate)
            encoded.width, encoded.height, encoded.pix_fmt = w, h, "yuv420p"
            encoded.options = {"preset": "veryfast", "crf": "18"}
            for picture in source.decode(video):
                planes = picture.to_ndarray(format="yuv420p")
                for packet in encoded.encode(av.VideoFrame.from_ndarray(planes, format="yuv420p")):
                    sink.mux(packet)
                frames += 1
            for packet in encoded.encode():
                sink.mux(packet)
    else:
        sys.exit(f"mode must be transcode, pipes or pyav, got {mode}")
    print(f"{mode}: {frames} frames, wall {time.perf_counter() - started:.2f} s, CPU {cpu_seconds() - cpu:.2f} s, "
          f"{os.path.getsize(out)} bytes")


if __name__ == "__main__":
    main(*sys.argv[1:3])
