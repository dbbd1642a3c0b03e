"""Live video output: H.264 in MPEG-TS on standard output (``-``) or to a URL (udp://, srt://,
tcp://, rtp://), encoded as frames are handed over (x264 ``zerolatency``: no lookahead, no
B-frames, each frame leaves the encoder as soon as it is encoded)."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import tempfile
from fractions import Fraction

import numpy as np

from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.live.source import _URL, STDIN
from mosaic_cli.video.reader import ffmpeg_exe
from mosaic_cli.video.writer import PRESETS

OUTPUT_SCHEMES = ("udp", "srt", "tcp", "rtp", "rist")
# MPEG-TS packets are 188 bytes: 7 of them fill a UDP datagram without IP fragmentation.
UDP_PACKET = 1316


def is_stream_output(out: str) -> bool:
    match = _URL.match(str(out))
    return str(out) == STDIN or bool(match)


def check_stream_output(out: str) -> None:
    match = _URL.match(str(out))
    if match and match.group(1).lower() not in OUTPUT_SCHEMES:
        raise BadInput(f"output {out}: a stream goes to - (standard output) or to one of "
                       f"{', '.join(s + '://' for s in OUTPUT_SCHEMES)}")


class StreamWriter:
    """Write yuv420p frames (h * 3 // 2, w) of an even ``size`` to ``out`` as a live stream."""

    def __init__(self, out: str, size: tuple[int, int], fps: float, crf: int = 18, preset: str = "veryfast"):
        check_stream_output(out)
        if preset not in PRESETS:
            raise BadInput(f"--preset must be one of {', '.join(PRESETS)}, got {preset!r}")
        self.out = out
        self.size = size
        self.frames_written = 0
        target = "pipe:1" if out == STDIN else out
        if target.lower().startswith("udp://") and "pkt_size" not in target:
            target += ("&" if "?" in target else "?") + f"pkt_size={UDP_PACKET}"
        w, h = size
        cmd = [ffmpeg_exe(), "-y", "-hide_banner", "-v", "error", "-nostdin",
               "-f", "rawvideo", "-pix_fmt", "yuv420p", "-s", f"{w}x{h}", "-r", str(Fraction(fps).limit_denominator()),
               "-i", "pipe:0", "-an", "-vcodec", "libx264", "-pix_fmt", "yuv420p", "-crf", str(crf), "-preset", preset,
               "-tune", "zerolatency", "-flush_packets", "1", "-f", "mpegts", target]
        self._log = tempfile.TemporaryFile()
        stdout = sys.stdout.buffer if out == STDIN else subprocess.DEVNULL
        try:
            self._encoder = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=stdout, stderr=self._log,
                                             start_new_session=True)
        except OSError as exc:
            raise ProcessingError(f"cannot start ffmpeg ({exc.strerror})") from None

    def write(self, frame: np.ndarray) -> None:
        try:
            self._encoder.stdin.write(np.ascontiguousarray(frame, dtype=np.uint8).data)
            self._encoder.stdin.flush()
        except OSError:
            self.abort()
            raise ProcessingError(f"{self._name()}: sending failed ({self._complaint()})") from None
        self.frames_written += 1

    def close(self) -> str:
        with contextlib.suppress(OSError):
            self._encoder.stdin.close()
        if self._encoder.wait() != 0:
            raise ProcessingError(f"{self._name()}: sending failed ({self._complaint()})")
        self._log.close()
        return self.out

    def abort(self) -> None:
        with contextlib.suppress(OSError):
            self._encoder.kill()
        self._encoder.wait()
        with contextlib.suppress(OSError):
            self._encoder.stdin.close()

    def _name(self) -> str:
        return "standard output" if self.out == STDIN else self.out

    def _complaint(self) -> str:
        if not self._log.closed:
            self._log.seek(0)
            lines = self._log.read().decode("utf-8", "replace").strip().splitlines()
            if lines:
                return lines[-1]
        return f"ffmpeg exited with status {self._encoder.poll()}"
