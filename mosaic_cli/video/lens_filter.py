"""``--lens`` on the decoded frames: an input seen through an image filter (the lens's
undistortion, ``geometry.lens.Undistortion``), remapped once as each frame is decoded.

A reader takes the filter as an argument, ``lens=`` (:func:`~.decode.open_video`,
:func:`~.decode.frames_at`, ``live.source.LiveStream``, and the readers above them), and applies
it with :func:`filtered` (:func:`filter_frame`: an RGB or gray image whole, yuv420p plane by
plane).  A reader given none reads the frames as they are decoded.  Where ``--lens`` is resolved
(``estimators.lens.choose_lens``: the ``stitch``, ``stabilize`` and ``track`` commands), its
filter (``LensChoice.image_filter``) is handed down to every reader of that input."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from mosaic_cli.video.pixels import YuvFrame

ImageFilter = Callable[[np.ndarray], np.ndarray]  # an image (h, w) or (h, w, C) -> one of the same size


def filter_frame(frame, size: tuple[int, int], yuv420p: bool, image_filter: ImageFilter):
    """One decoded frame of ``size`` through ``image_filter``: an RGB or gray image whole, a
    yuv420p frame (or a :class:`~.pixels.YuvFrame`) plane by plane."""
    def planes(flat: np.ndarray) -> np.ndarray:
        w, h = size
        cw, ch = (w + 1) // 2, (h + 1) // 2
        flat = np.asarray(flat).reshape(-1)
        out = np.empty_like(flat)
        out[:w * h] = image_filter(flat[:w * h].reshape(h, w)).reshape(-1)
        for k in range(2):
            at = w * h + k * cw * ch
            out[at:at + cw * ch] = image_filter(flat[at:at + cw * ch].reshape(ch, cw)).reshape(-1)
        return out

    if isinstance(frame, YuvFrame):
        return YuvFrame(planes(frame._flat), frame.size)
    if yuv420p:
        return planes(frame).reshape(frame.shape)
    return image_filter(np.asarray(frame))


def filtered(frames: Iterator, size: tuple[int, int], yuv420p: bool, image_filter: ImageFilter | None) -> Iterator:
    """``frames`` through ``image_filter`` (:func:`filter_frame`); None: ``frames`` themselves."""
    if image_filter is None:
        return frames
    return (filter_frame(frame, size, yuv420p, image_filter) for frame in frames)
