"""Live inputs: standard input (``-``) or a URL ffmpeg reads (udp, tcp, rtp, rtsp, srt, http(s)).

A live source has no known length and may stop sending at any time.  One ffmpeg process
decodes it to raw frames on a pipe; a reader thread moves each frame, stamped with the time it
arrived, into a bounded queue, so the consumer can wait on it with a deadline.  The stream ends

* at its end (the sender closed it; ffmpeg exits),
* when nothing arrives for ``timeout`` seconds (one line on stderr says so),
* at Ctrl-C or SIGTERM (see :class:`StopRequest`): a live run's outputs are the point, so it
  finishes with every frame already received.  A second Ctrl-C abandons the run as usual.

Frames are not dropped: when the consumer falls behind, the queue fills and the reader stops
taking frames from ffmpeg, which stops reading its input (TCP, pipes and SRT then hold the
sender back; UDP has no back pressure and its socket buffer is what is left).
"""

from __future__ import annotations

import contextlib
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from mosaic_cli.errors import BadInput, Interrupted
from mosaic_cli.inputs import DEFAULT_TIMEOUT
from mosaic_cli.progress import note
from mosaic_cli.video.lens_filter import ImageFilter, filter_frame
from mosaic_cli.video.pixels import CONVERTED_HERE, TO_BT601, rgb_from_yuv420p, yuv420p_bytes
from mosaic_cli.video.reader import VideoInfo, ffmpeg_exe, read_into, scaled_size

STDIN = "-"
URL_SCHEMES = ("udp", "tcp", "rtp", "rtsp", "rtsps", "srt", "http", "https", "rtmp", "rist")
# Frames queued between the decoder and the consumer at most (memory bound: the bytes of this
# many frames, or fewer frames when they are large).
QUEUE_BYTES = 256 * 2**20
QUEUE_MIN_FRAMES = 16
PROBE_SECONDS = 0.5
FLUSH_SECONDS = 2.0  # at most this long for ffmpeg to hand over its last frames once stopped
# Our own watchdog waits this much longer than --timeout, so that ffmpeg's (see _start) ends a
# network input first, with its last frames; it ends what ffmpeg cannot time out (a pipe).
WATCHDOG_SLACK = 1.5
_TIMED_OUT = ("Error during demuxing", "Connection timed out", "timed out")
PROBE_BYTES = 4 * 2**20

_URL = re.compile(r"^([a-zA-Z][a-zA-Z0-9+.-]*)://")
_OUTPUT_STREAM = re.compile(r"Stream #0:\d+.*: Video: rawvideo.*?, (\d+)x(\d+)")
_FPS = re.compile(r"([0-9]+(?:\.[0-9]+)?) (?:fps|tbr)")
_INPUT_AUDIO = re.compile(r"Stream #\S+.*?: Audio: (\w+)")


def is_live_source(source: object) -> bool:
    """True for ``-`` and for a URL with a scheme ffmpeg streams from."""
    text = str(source)
    if text == STDIN:
        return True
    match = _URL.match(text)
    return bool(match) and match.group(1).lower() in URL_SCHEMES


def source_name(source: str) -> str:
    return "standard input" if source == STDIN else source


class StopRequest:
    """Ctrl-C and SIGTERM, while a live stream is read, ask it to end rather than unwind the run.

    The first signal sets :attr:`reason` and puts the previous handlers back, so that a second
    one abandons the run as it would any other.  Off the main thread nothing is installed."""

    NAMES = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}

    def __init__(self) -> None:
        self.reason: str | None = None
        self.signum: int | None = None
        self._previous: dict = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for signum in self.NAMES:
            self._previous[signum] = signal.signal(signum, self._on_signal)

    def _on_signal(self, signum, frame) -> None:
        if self.reason is None:
            self.reason = self.NAMES.get(signum, f"signal {signum}")
            self.signum = signum
        self.restore()

    def restore(self) -> None:
        previous, self._previous = self._previous, {}
        for signum, handler in previous.items():
            signal.signal(signum, handler)

    @property
    def requested(self) -> bool:
        return self.reason is not None


@dataclass
class Arrival:
    """A frame as it came off the decoder: its pixels and when (time.monotonic())."""

    frame: np.ndarray
    time: float


_END = object()


class LiveStream:
    """Frames of a live source, iterated as :class:`Arrival` (see :meth:`arrivals`) or as plain
    frames (``for frame in stream``).  ``pixels``: "gray" (h, w) at ``size``, "rgb" (h, w, 3)
    at ``size``, or "yuv420p" (h * 3 // 2, w) at the source size.  Use as a context manager.

    A live stream can be read only once, so nothing probes it: its size, rate and audio are
    read from the decoder's own log as it starts.  A file read this way (``live=False``) passes
    its probe as ``info`` instead.  ``lens``: each frame through this filter (``--lens``:
    :mod:`mosaic_cli.video.lens_filter`); None: the frames as decoded."""

    def __init__(self, source: str, pixels: str = "gray", width: int | None = None,
                 timeout: float = DEFAULT_TIMEOUT, stop: StopRequest | None = None, quiet: bool = False,
                 live: bool = True, info: VideoInfo | None = None, on_started: Callable[[], None] | None = None,
                 lens: ImageFilter | None = None):
        if pixels not in ("gray", "rgb", "yuv420p"):
            raise ValueError(f"pixels must be gray, rgb or yuv420p, got {pixels}")
        self.source = source
        # live=False: a file read the same way (one pass, frames as they are decoded), which
        # neither times out nor outlives a Ctrl-C: an interrupted file run leaves nothing.
        self.live = live
        self.pixels = pixels
        self.timeout = float(timeout)
        self.quiet = quiet
        self.stop = stop or StopRequest()
        self._own_stop = stop is None and live
        self.frames_read = 0
        self.ended_by: str | None = None  # "end of stream", "timeout", "Ctrl-C", "SIGTERM"
        self._log: list[str] = []
        self._header = threading.Event()
        self._out_size: tuple[int, int] | None = None
        self._fps: float | None = None
        self._audio: str | None = None
        self._queue: queue.Queue | None = None
        self._probed = info
        # RGB comes as yuv420p and is converted here, as a file's is (video/pixels.py): a live
        # stitch then sees the frames an offline one does.  Only a probed file of another layout
        # (4:4:4) keeps ffmpeg's conversion, as offline.
        self._rgb_here = pixels == "rgb" and (info is None or info.pixel_format in CONVERTED_HERE)
        # --lens FILE: each frame undistorted at its full size as it arrives, on the reader thread
        self._filter = lens
        if self._own_stop:
            # Before the decoder starts: a signal from then on asks the stream to end, also one
            # that comes while ``on_started`` runs (stabilize imports its solver there, 0.5 s).
            self.stop.install()
        try:
            self._proc = self._start()
        except BaseException:
            if self._own_stop:
                self.stop.restore()
            if on_started is not None:  # what waited for the decoder's start may go: it will not come
                on_started()
            raise
        try:
            if on_started is not None:  # the decoder is up (listening, for a server URL): what waited for it may go
                on_started()
            self.info = self._wait_for_header(width)
        except BaseException:
            self.close()  # the decoder with it, whatever ended the wait (it runs in a session of its own)
            raise

    # -- the decoder --------------------------------------------------------------------
    def _start(self) -> subprocess.Popen:
        pix_fmt = "yuv420p" if self._rgb_here else {"gray": "gray", "rgb": "rgb24", "yuv420p": "yuv420p"}[self.pixels]
        cmd = [ffmpeg_exe(), "-hide_banner", "-nostats", "-v", "info"]
        if self.source != STDIN and not self.live:
            cmd += ["-nostdin"]
        elif self.source != STDIN:
            # The network protocols' own read timeout (microseconds): ffmpeg then ends the
            # input itself and hands over the frames its demuxer and decoder still hold, which a
            # process killed while it waits for data never does.
            cmd += ["-nostdin", "-timeout", str(int(self.timeout * 1_000_000))]
        # ffmpeg looks at 5 s of a stream by default before the first frame comes out: half a
        # second finds the video of any stream mosaic can use, and a live run waits less.
        cmd += ["-analyzeduration", str(int(PROBE_SECONDS * 1_000_000)), "-probesize", str(PROBE_BYTES)]
        probed = self._probed.stream_index if self._probed is not None else None
        cmd += ["-i", "pipe:0" if self.source == STDIN else self.source,
                "-map", f"0:{probed}" if probed is not None else "0:v:0", "-an", "-sn", "-fps_mode", "passthrough"]
        if self._rgb_here:
            cmd += ["-vf", TO_BT601]
        cmd += ["-f", "rawvideo", "-pix_fmt", pix_fmt, "pipe:1"]
        stdin = sys.stdin.buffer if self.source == STDIN else subprocess.DEVNULL
        if self.source == STDIN:
            # pytest and some shells hand us no usable stdin; say so rather than hang.
            try:
                stdin.fileno()
            except (AttributeError, OSError, ValueError):
                raise BadInput("-: standard input is not readable") from None
        try:
            # Its own session: the terminal's Ctrl-C reaches mosaic alone, which decides.
            proc = subprocess.Popen(cmd, stdin=stdin, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                    start_new_session=True, bufsize=0)
        except OSError as exc:
            raise BadInput(f"{source_name(self.source)}: cannot start ffmpeg ({exc.strerror})") from None
        self._log_reader = threading.Thread(target=self._read_log, args=(proc,), daemon=True)
        self._log_reader.start()
        return proc

    def _timed_out(self) -> bool:
        """Whether ffmpeg ended its input for want of data (its own -timeout)."""
        self._log_reader.join(timeout=1.0)
        return self.live and self.source != STDIN and any(sign in line for line in self._log[-8:] for sign in _TIMED_OUT)

    def _read_log(self, proc: subprocess.Popen) -> None:
        output = False
        for raw in iter(proc.stderr.readline, b""):
            line = raw.decode("utf-8", "replace").rstrip()
            self._log.append(line)
            del self._log[:-50]
            if line.startswith("Input #"):
                output = False
            elif line.startswith("Output #"):
                output = True
            if not output:
                audio = _INPUT_AUDIO.search(line)
                if audio and self._audio is None:
                    self._audio = audio.group(1)
            if output and self._out_size is None:
                match = _OUTPUT_STREAM.search(line)
                if match:
                    self._out_size = (int(match.group(1)), int(match.group(2)))
                    fps = _FPS.search(line)
                    self._fps = float(fps.group(1)) if fps else None
                    self._header.set()
        self._header.set()  # ffmpeg is done: whatever it said is all there is

    def _complaint(self) -> str:
        for line in reversed(self._log):
            text = re.sub(r"^(\[[^]]*\] ?)+", "", line).strip()
            if text and not text.startswith(("Press [q]", "Stream mapping", "  ")):
                return text
        return f"ffmpeg exited with status {self._proc.poll()}"

    def _wait_for_header(self, width: int | None) -> VideoInfo:
        """Wait for ffmpeg to have found the video (at most ``timeout`` s, or a stop request);
        a probed file's header is its probe."""
        if self._probed is not None:
            return self._begin(self._probed.source_size, self._probed.fps, self._probed.audio_codec, width)
        deadline = time.monotonic() + (self.timeout if self.live else 3600.0)
        while not self._header.wait(0.05):
            if self.stop.requested:
                raise Interrupted(f"{source_name(self.source)}: stopped ({self.stop.reason}) before any video arrived",
                                  self.stop.signum)
            if time.monotonic() > deadline:
                raise BadInput(f"{source_name(self.source)}: no video arrived within {self.timeout:g} s (--timeout)")
        if self._out_size is None:
            self._proc.wait(timeout=5)
            if self._timed_out():
                raise BadInput(f"{source_name(self.source)}: no video arrived within {self.timeout:g} s (--timeout)")
            raise BadInput(f"{source_name(self.source)}: cannot read a video stream ({self._complaint()})")
        return self._begin(self._out_size, self._fps or 30.0, self._audio, width)

    def _begin(self, source_size: tuple[int, int], fps: float, audio: str | None, width: int | None) -> VideoInfo:
        """Start moving frames of ``source_size`` into the queue; the stream's :class:`VideoInfo`."""
        size = source_size if self.pixels == "yuv420p" else scaled_size(source_size, width)
        w, h = source_size
        if self.pixels == "yuv420p" and (w % 2 or h % 2):
            raise BadInput(f"{source_name(self.source)}: odd frame size {w}x{h}")
        self._frame_shape = {"gray": (h, w), "rgb": (h, w, 3), "yuv420p": (h * 3 // 2, w)}[self.pixels]
        frame_bytes = int(np.prod(self._frame_shape))  # as queued
        self._queue = queue.Queue(maxsize=max(QUEUE_MIN_FRAMES, QUEUE_BYTES // frame_bytes))
        self._source_size = source_size
        piped = yuv420p_bytes(source_size) if self._rgb_here else frame_bytes
        # yuv420p (RGB converted here included) is filtered plane by plane before any conversion,
        # as a file's frames are (video.lens_filter.filter_frame): the pixels an offline run sees
        self._filter_planes = self.pixels == "yuv420p" or self._rgb_here
        if self._filter is not None:  # the lens against the stream's size, once (its maps made here)
            try:
                filter_frame(np.zeros(piped if self._filter_planes else self._frame_shape, np.uint8), source_size,
                             self._filter_planes, self._filter)
            except ValueError as exc:
                raise BadInput(f"--lens: {exc}") from None
        threading.Thread(target=self._read_frames, args=(piped,), daemon=True).start()
        return VideoInfo(source_name(self.source), size, source_size, fps, None, 0.0, 0, audio)

    def _read_frames(self, frame_bytes: int) -> None:
        pipe = self._proc.stdout
        try:
            while True:
                buffer = bytearray(frame_bytes)
                if read_into(pipe, memoryview(buffer)) < frame_bytes:
                    break  # the end (a partial last frame is not a frame)
                flat = np.frombuffer(buffer, np.uint8)
                if self._filter is not None and self._filter_planes:
                    flat = filter_frame(flat, self._source_size, True, self._filter)
                frame = rgb_from_yuv420p(flat, self._source_size) if self._rgb_here else flat.reshape(self._frame_shape)
                if self._filter is not None and not self._filter_planes:
                    frame = filter_frame(frame, self._source_size, False, self._filter)
                arrival = Arrival(frame, time.monotonic())
                self._queue.put(arrival)
        except (OSError, ValueError):
            pass
        finally:
            self._queue.put(_END)

    # -- the consumer -------------------------------------------------------------------
    def arrivals(self) -> Iterator[Arrival]:
        """Every frame received, in order, until the stream ends (see the module doc)."""
        last = time.monotonic()
        size = self.info.size
        stopping_since: float | None = None
        while True:
            if self.stop.requested and self.ended_by is None:
                self.ended_by = self.stop.reason
            if self.ended_by is not None and stopping_since is None:
                # ffmpeg, asked to stop, hands over the frames its decoder still holds.
                stopping_since = time.monotonic()
                self._stop_decoder()
            try:
                item = self._queue.get(timeout=0.05)
            except queue.Empty:
                now = time.monotonic()
                if self.live and self.ended_by is None and now - last > self.timeout + WATCHDOG_SLACK:
                    self.ended_by = "timeout"
                elif stopping_since is not None and now - stopping_since > FLUSH_SECONDS:
                    with contextlib.suppress(OSError):
                        self._proc.kill()
                    stopping_since = now + 3600.0  # killed: the reader's end marker follows
                continue
            if item is _END:
                self._say_how_it_ended()
                return
            last = time.monotonic()
            frame = item.frame
            if self.pixels != "yuv420p" and (frame.shape[1], frame.shape[0]) != size:
                item.frame = cv2.resize(frame, size, interpolation=cv2.INTER_AREA)
            self.frames_read += 1
            yield item

    def _say_how_it_ended(self) -> None:
        if self.ended_by is None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                self._proc.wait(timeout=1.0)  # its last words, to tell a timeout from an end
            self.ended_by = "timeout" if self._timed_out() else "end of stream"
        if self.ended_by == "end of stream":
            if self.frames_read == 0:
                self._proc.wait(timeout=5)
                raise BadInput(f"{source_name(self.source)}: no video frames received ({self._complaint()})")
            return
        if self.frames_read == 0:
            raise BadInput(f"{source_name(self.source)}: no video frames received before the {self.ended_by}")
        if self.quiet:
            return
        if self.ended_by == "timeout":
            note(f"{source_name(self.source)} sent nothing for {self.timeout:g} s (--timeout): "
                 f"ending with the {self.frames_read} frames received")
        else:
            note(f"{self.ended_by}: ending with the {self.frames_read} frames received")

    def __iter__(self) -> Iterator[np.ndarray]:
        for arrival in self.arrivals():
            yield arrival.frame

    def _stop_decoder(self) -> None:
        if self._proc.poll() is None:
            with contextlib.suppress(OSError):
                self._proc.terminate()

    def close(self) -> None:
        if self._own_stop:
            self.stop.restore()
        if self._proc.poll() is None:
            with contextlib.suppress(OSError):
                self._proc.kill()
        self._proc.wait()
        # Unblock the reader thread if it waits on a full queue.
        if self._queue is not None:
            with contextlib.suppress(queue.Empty):
                while True:
                    self._queue.get_nowait()

    def __enter__(self) -> LiveStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# yuv420p luma is limited range (16..235); ffmpeg's "gray", which every other command decodes
# and the learned estimators were trained on, is full range: the same table ffmpeg applies.
_FULL_RANGE = np.clip(np.round((np.arange(256) - 16) * 255 / 219), 0, 255).astype(np.uint8)


def gray_of_yuv(frame: np.ndarray, source_size: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """The Y plane of a yuv420p frame as ffmpeg's full-range gray, resized to ``size`` (what
    the estimators take): the frames a file's ``track`` sees."""
    w, h = source_size
    y = cv2.LUT(frame[:h], _FULL_RANGE)
    return y if (w, h) == tuple(size) else cv2.resize(y, size, interpolation=cv2.INTER_AREA)
