"""The render: warp every frame of the input at full resolution, encode.

The frames come from ``stabilize``'s one decode, shared with the tracking
(:mod:`.shared_decode`), or from a decode of the render's own (:meth:`Renderer.render` without
``decoded``).  Decoding (the reader's ffmpeg pipe), warping (OpenCV) and encoding (an x264 pipe)
all release the GIL, so each runs in its own thread with small bounded queues between them: on
two cores the three overlap instead of taking turns.

Video files of even size stay in yuv420p from decoder to encoder (the planes are warped
separately, chroma at half resolution): no RGB conversion either way and half the pixels to
warp, 27 instead of 37 ms of CPU a 1280x720 frame.  Image folders and odd sizes go through RGB.
"""

from __future__ import annotations

import contextlib
import functools
import queue
import sys
import threading
from collections.abc import Callable, Generator, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mosaic_cli.device import resolve_device
from mosaic_cli.errors import BadInput
from mosaic_cli.geometry import resize_matrix
from mosaic_cli.geometry.lens import Lens, distort_by_table, distortion_table, undistort_points, undistorted_camera
from mosaic_cli.geometry.rolling_shutter import undo_row_correction
from mosaic_cli.progress import progress_task
from mosaic_cli.video import VideoInfo, VideoWriter, open_video
from mosaic_cli.video.decode import ImageFilter, ReadAhead

BORDERS = {"black": cv2.BORDER_CONSTANT, "replicate": cv2.BORDER_REPLICATE, "reflect": cv2.BORDER_REFLECT}
COMPARE_PANEL_WIDTH = 960  # wider inputs are shown at half size in --compare videos
COMPARE_LABELS = ("input", "stabilised")  # written on the --compare video's left and right panels


def parse_border(name: str) -> str:
    if name.lower() not in BORDERS:
        raise BadInput(f"--border must be one of {', '.join(BORDERS)}, got {name!r}")
    return name.lower()


def warp_frame(frame: np.ndarray, warp: np.ndarray, size: tuple[int, int], border: str = "black") -> np.ndarray:
    """The output frame: ``frame`` resampled so that input pixel x lands on ``warp @ x``."""
    # (An affine warp takes the faster path, with no per-pixel division.)
    return _warp_plane(frame, np.asarray(warp, dtype=np.float64), size, border, 0)


# yuv420p frames: the three planes one after the other in one uint8 array of (h * 3 // 2, w).
YUV_BLACK = (16, 128, 128)  # limited-range black, as ffmpeg converts RGB (0, 0, 0)


def yuv_planes(frame: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Views of the Y (h, w), U and V (h/2, w/2) planes of a yuv420p frame."""
    w, h = size
    flat = frame.reshape(-1)
    q = (w // 2) * (h // 2)
    return flat[:w * h].reshape(h, w), flat[w * h:w * h + q].reshape(h // 2, w // 2), flat[w * h + q:].reshape(h // 2, w // 2)


def warp_yuv(frame: np.ndarray, warp: np.ndarray, size: tuple[int, int], border: str = "black") -> np.ndarray:
    """:func:`warp_frame` for a yuv420p frame: chroma warped by the same map at half resolution."""
    w, h = size
    out = np.empty((h * 3 // 2, w), np.uint8)
    to_chroma = resize_matrix((w, h), (w // 2, h // 2))
    chroma_warp = to_chroma @ warp @ np.linalg.inv(to_chroma)
    for src, dst, M, black in zip(yuv_planes(frame, size), yuv_planes(out, size), (warp, chroma_warp, chroma_warp), YUV_BLACK):
        dst[...] = _warp_plane(src, M, (dst.shape[1], dst.shape[0]), border, black)
    return out


def side_by_side_yuv(left: np.ndarray, right: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """:func:`side_by_side` for yuv420p frames of ``size``."""
    out_size = compare_size(size)
    out = np.empty((out_size[1] * 3 // 2, out_size[0]), np.uint8)
    text, outline = compare_labels(out_size)
    small = (out_size[0] // 2, out_size[1] // 2)
    chroma_text = cv2.resize((text | outline).view(np.uint8), small, interpolation=cv2.INTER_AREA) > 0
    for i, (a, b, dst) in enumerate(zip(yuv_planes(left, size), yuv_planes(right, size), yuv_planes(out, out_size))):
        panel = (dst.shape[1] // 2, dst.shape[0])
        if (a.shape[1], a.shape[0]) != panel:
            a = cv2.resize(a, panel, interpolation=cv2.INTER_AREA)
            b = cv2.resize(b, panel, interpolation=cv2.INTER_AREA)
        dst[:, :panel[0]], dst[:, panel[0]:] = a, b
        if i == 0:  # white letters outlined in black (limited range), grey under them in chroma
            dst[outline], dst[text] = 16, 235
        else:
            dst[chroma_text] = 128
    return out


@functools.lru_cache(maxsize=4)
def compare_labels(out_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Where the --compare video's labels go, at its size ``out_size``: (letters, outline), two
    boolean (h, w) masks, :data:`COMPARE_LABELS` in the top-left corner of each panel.  The text
    is about a sixteenth of the panel's height (at least 10 px), narrowed to fit a small panel."""
    w, h = out_size
    panel_w = w // 2
    font = cv2.FONT_HERSHEY_SIMPLEX
    scale = max(10.0, h / 16) / cv2.getTextSize("Ag", font, 1.0, 1)[0][1]
    widest = max(cv2.getTextSize(label, font, 1.0, 1)[0][0] for label in COMPARE_LABELS)
    scale = min(scale, 0.8 * panel_w / widest)
    thickness = max(1, round(scale * 1.5))
    margin = max(3, round(h / 40))
    text = np.zeros((h, w), np.uint8)
    for i, label in enumerate(COMPARE_LABELS):
        (_, height), _ = cv2.getTextSize(label, font, scale, thickness)
        cv2.putText(text, label, (i * panel_w + margin, margin + height), font, scale, 255, thickness, cv2.LINE_AA)
    letters = text > 127
    outline = cv2.dilate(letters.view(np.uint8), np.ones((3, 3), np.uint8), iterations=max(1, thickness // 2)) > 0
    return letters, outline & ~letters


def label_panels(frame: np.ndarray) -> np.ndarray:
    """An RGB side-by-side frame with :data:`COMPARE_LABELS` written on its panels (in place)."""
    text, outline = compare_labels((frame.shape[1], frame.shape[0]))
    frame[outline], frame[text] = 0, 255
    return frame


def _warp_plane(plane: np.ndarray, warp: np.ndarray, size: tuple[int, int], border: str, black) -> np.ndarray:
    mode = BORDERS[border]
    if abs(warp[2, 0]) < 1e-12 and abs(warp[2, 1]) < 1e-12:
        return cv2.warpAffine(plane, warp[:2] / warp[2, 2], size, flags=cv2.INTER_LINEAR, borderMode=mode,
                              borderValue=black)
    return cv2.warpPerspective(plane, warp, size, flags=cv2.INTER_LINEAR, borderMode=mode, borderValue=black)


def render_yuv(info: VideoInfo, compare: bool) -> bool:
    """Whether the render reads, warps and encodes yuv420p planes (video files of even size, the
    --compare video's too), rather than RGB frames: how its frames are decoded."""
    w, h = info.source_size
    sizes = [info.source_size] + ([compare_size(info.source_size)] if compare else [])
    halves = [(w // 2, h // 2)] if compare and w > COMPARE_PANEL_WIDTH else []
    return not info.is_image_folder and all(a % 2 == 0 and b % 2 == 0 for a, b in sizes + halves)


def side_by_side(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Input and output next to each other (halved when the frames are wide), labelled "input"
    and "stabilised" (:func:`compare_labels`)."""
    h, w = left.shape[:2]
    if w > COMPARE_PANEL_WIDTH:
        size = (w // 2, h // 2)
        left = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
        right = cv2.resize(right, size, interpolation=cv2.INTER_AREA)
    return label_panels(np.hstack([left, right]))


def compare_size(size: tuple[int, int]) -> tuple[int, int]:
    w, h = size
    return (2 * (w // 2), h // 2) if w > COMPARE_PANEL_WIDTH else (2 * w, h)


@dataclass
class Renderer:
    """Options of the output encoding."""

    border: str = "black"
    crf: int = 18
    preset: str = "veryfast"  # x264 'medium' halves throughput on two cores for a few % of bitrate
    # --device: the GPU that warps the frames (stabilize/device_render.py) where it names or finds
    # one ("auto", "cuda", "cuda:N"; "cpu" here is torch's CPU, for tests); None: OpenCV's warps on
    # the CPU, an order of magnitude faster there than torch's.
    device: str | None = None

    def warp_device(self) -> str | None:
        """The torch device the frames are warped on, or None for OpenCV's (see ``device``).
        ``auto`` asks torch only where an NVIDIA driver is loaded or torch already is (an ORB
        render on a machine without a GPU never imports it)."""
        if self.device is None:
            return None
        if self.device != "auto":
            return str(resolve_device(self.device))
        if "torch" not in sys.modules and not Path("/proc/driver/nvidia/version").exists():
            return None
        found = resolve_device("auto")
        return str(found) if found.type == "cuda" else None

    def render(self, video: str | Path, out: str | Path, warps: np.ndarray | Callable[[int], np.ndarray], info: VideoInfo,
               compare: str | Path | None = None, show_progress: bool = True,
               metadata: dict[str, str] | None = None, frames: int | None = None,
               per_row: Callable[[np.ndarray, int, np.ndarray], np.ndarray | None] | None = None,
               decoded: Iterable[np.ndarray] | None = None, lens: ImageFilter | None = None) -> int:
        """Write the stabilised video (and the side-by-side one); returns the frames written.

        ``warps``: (N, 3, 3), or a function giving frame t's warp (which may wait until it is
        known: :meth:`~.stream.PathFeed.warp`); then ``frames`` is the count expected, which
        cuts the audio (None: the audio is not cut).  Frames beyond ``len(warps)`` (a decoder
        that finds one more frame the second time) reuse the last warp.  ``per_row(frame, t,
        warp)``: a warp of its own instead, row by row (``stabilize/rolling.py``), or None for the usual one.
        ``decoded``: the frames, decoded by the caller (None: a decode of ``video`` of its own, each
        frame through ``lens``, ``--lens``'s filter)."""
        if isinstance(warps, np.ndarray):
            frames, known = len(warps), warps
            warps = lambda t: known[min(t, len(known) - 1)]  # noqa: E731
        warp_of = warps
        size = info.source_size
        yuv = render_yuv(info, compare is not None)
        pix_fmt = "yuv420p" if yuv else "rgb24"
        warp = warp_yuv if yuv else warp_frame
        join = (lambda a, b: side_by_side_yuv(a, b, size)) if yuv else side_by_side
        # The audio ends with the video (the frames the first pass counted, at the input's rate).
        common: dict[str, Any] = dict(crf=self.crf, preset=self.preset, audio_from=info if info.has_audio else None,
                                      audio_seconds=frames / info.fps if frames else None, pix_fmt_in=pix_fmt, metadata=metadata)
        writers = [VideoWriter(out, size, info.fps, **common)]
        if compare is not None:
            writers.append(VideoWriter(compare, compare_size(size), info.fps, **common))
        try:
            with contextlib.ExitStack() as inputs:
                if decoded is None:  # the frames upright, each once; yuv420p planes when they can stay so
                    stream = inputs.enter_context(open_video(video, yuv420p=yuv, info=info, lens=lens))
                    ahead = ReadAhead(iter(stream), 4)  # decoded on a thread of its own, 4 frames ahead of the warps
                    inputs.callback(ahead.stop)
                    decoded = ahead
                elif hasattr(decoded, "close"):  # a generator: its decoders closed with the render
                    inputs.callback(decoded.close)
                advance = inputs.enter_context(progress_task("stabilize: render", frames, disable=not show_progress))

                def outputs(source: Iterable[np.ndarray]) -> Generator[tuple[np.ndarray, ...]]:
                    for t, frame in enumerate(source):
                        W = warp_of(t)
                        result = per_row(frame, t, W) if per_row is not None else None
                        if result is None:
                            result = warp(frame, W, size, self.border)
                        yield (result, join(frame, result)) if compare is not None else (result,)

                def on_device(source: Iterable[np.ndarray]) -> Generator[tuple[np.ndarray, ...]]:
                    """The same frames warped on ``self.device``, two in flight (DeviceWarper.stream)."""
                    from mosaic_cli.stabilize.device_render import DeviceWarper

                    assert device is not None
                    warper = DeviceWarper(device, size, self.border)

                    def asked() -> Iterator[tuple]:
                        for t, frame in enumerate(source):
                            W = warp_of(t)
                            rows = per_row.correction() if per_row is not None else None  # type: ignore[attr-defined]
                            yield (frame, W) if rows is None else (frame, W, rows, t)

                    for frame, result in warper.stream(asked()):
                        yield (result, join(frame, result)) if compare is not None else (result,)

                # (a per_row that cannot say its correction, only warp, warps on the CPU)
                device = self.warp_device() if per_row is None or hasattr(per_row, "correction") else None
                results = on_device(decoded) if device is not None else outputs(decoded)
                inputs.callback(results.close)
                written = _drain(results, [w.write for w in writers], advance)
            for writer in writers:
                writer.close()
        except BaseException:
            for writer in writers:
                writer.abort()
            raise
        return written


class KeptLens:
    """``stabilize --keep-lens``: the render's ``per_row`` that writes each frame with the lens's
    look, from the frames as the lens saw them, in one resampling: each output pixel (the lens's
    pixels) -> the undistorted frame's pixel it shows (``lens``'s undistortion, the frames' own,
    fixed, computed once) -> back through the frame's stabilising warp (and, with ``rows``, the
    rolling shutter's row correction of the input row it lands on) -> the undistorted input's
    pixel -> the lens's pixel of it (:func:`~mosaic_cli.geometry.lens.distortion_table`) -> one
    ``cv2.remap`` of the frame.  Maps as the rolling shutter's row warper builds them: computed on
    the chroma grid and resized to the luma grid (the composed map is smooth), chroma at half
    size.  RGB (h, w, 3) or yuv420p (h * 3 // 2, w) frames of ``size``; ``border``: an OpenCV
    border mode, ``black`` the planes' fill.  ``rows``: a ``RowWarpLater`` (its ``correction()``,
    None for a global shutter).  OpenCV's warps only: a device render warps without the lens."""

    def __init__(self, lens: Lens, size: tuple[int, int], border: int, black: tuple[int, int, int], rows=None):
        w, h = self.size = (int(size[0]), int(size[1]))
        self.border, self.black, self.rows = border, black, rows
        at = lens.at(self.size)
        cw, ch = w // 2, h // 2
        # the chroma grid's pixel centres in luma pixels (as RollingCorrection.warper)
        gx, gy = np.meshgrid(np.arange(cw, dtype=np.float64) * 2 + 0.5, np.arange(ch, dtype=np.float64) * 2 + 0.5)
        u = undistort_points(at, np.stack([gx.ravel(), gy.ravel()], 1), undistorted_camera(at))
        self.ux, self.uy = u[:, 0].reshape(ch, cw), u[:, 1].reshape(ch, cw)
        self.table = distortion_table(lens, self.size)
        self._rows = np.arange(h, dtype=np.float64)

    def maps(self, t: int, warp: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Frame t's (map_x, map_y) on the luma grid and on the chroma grid (its own pixels),
        float32: where each output pixel samples the frame as the lens saw it."""
        w, h = self.size
        Wi = np.linalg.inv(np.asarray(warp, dtype=np.float64))
        z = Wi[2, 0] * self.ux + Wi[2, 1] * self.uy + Wi[2, 2]
        x = (Wi[0, 0] * self.ux + Wi[0, 1] * self.uy + Wi[0, 2]) / z
        y = (Wi[1, 0] * self.ux + Wi[1, 1] * self.uy + Wi[1, 2]) / z
        rolling = self.rows.correction() if self.rows is not None else None
        if rolling is not None:
            x, y = undo_row_correction(rolling.row_channels(t, self._rows).astype(np.float32), self.size, x, y)
        cu, cv_ = distort_by_table(*self.table, x, y)
        full_u = cv2.resize(cu, (w, h), interpolation=cv2.INTER_LINEAR)
        full_v = cv2.resize(cv_, (w, h), interpolation=cv2.INTER_LINEAR)
        return full_u, full_v, (cu + 0.5) / 2 - 0.5, (cv_ + 0.5) / 2 - 0.5

    def __call__(self, frame: np.ndarray, t: int, warp: np.ndarray) -> np.ndarray:
        w, h = self.size
        u, v, cu, cv_ = self.maps(t, warp)
        if frame.ndim == 3:
            return cv2.remap(frame, u, v, cv2.INTER_LINEAR, borderMode=self.border, borderValue=(0, 0, 0))
        out = np.empty_like(frame)
        flat_in, flat_out = frame.reshape(-1), out.reshape(-1)
        flat_out[:w * h] = cv2.remap(flat_in[:w * h].reshape(h, w), u, v, cv2.INTER_LINEAR, borderMode=self.border,
                                     borderValue=self.black[0]).reshape(-1)
        cw, ch = w // 2, h // 2
        q = cw * ch
        for i, start in enumerate((w * h, w * h + q)):
            plane = flat_in[start:start + q].reshape(ch, cw)
            flat_out[start:start + q] = cv2.remap(plane, cu, cv_, cv2.INTER_LINEAR, borderMode=self.border,
                                                  borderValue=self.black[1 + i]).reshape(-1)
        return out


_DONE = object()


def _drain(results: Iterable[tuple[np.ndarray, ...]], sinks: list[Callable[[np.ndarray], None]],
           advance: Callable[[int], None], depth: int = 4) -> int:
    """Feed each element of every result tuple to its sink, one encoder thread per sink."""
    queues: list[queue.Queue] = [queue.Queue(maxsize=depth) for _ in sinks]
    errors: list[BaseException] = []

    def consume(q: queue.Queue, sink: Callable[[np.ndarray], None]) -> None:
        while True:
            item = q.get()
            if item is _DONE:
                return
            if errors:
                continue  # keep draining so the producer never blocks
            try:
                sink(item)
            except BaseException as exc:
                errors.append(exc)

    workers = [threading.Thread(target=consume, args=(q, s), daemon=True) for q, s in zip(queues, sinks)]
    for worker in workers:
        worker.start()
    count = 0
    try:
        for result in results:
            if errors:
                break
            for q, frame in zip(queues, result):
                q.put(frame)
            count += 1
            advance(1)
    finally:
        for q in queues:
            q.put(_DONE)
        for worker in workers:
            worker.join()
    if errors:
        raise errors[0]
    return count
