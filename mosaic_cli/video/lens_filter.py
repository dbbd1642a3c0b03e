"""``--lens`` on the decoded frames: an input seen through an image filter (the lens's
undistortion, ``geometry.lens.Undistortion``), remapped once as each frame is decoded.

A reader takes the filter as an argument, ``lens=`` (:func:`~.decode.open_video`,
:func:`~.decode.frames_at`, ``live.source.LiveStream``), and applies it with :func:`filtered`
(:func:`filter_frame`: an RGB or gray image whole, yuv420p plane by plane).

Transitional: a reader given no ``lens`` still looks up the filter set for its input's path by
:func:`seen_through` (which ``estimators.lens.undistorting`` sets for the length of a command), for
the readers that do not pass one yet: ``stitch/pipeline.py``'s scan, ``stabilize/render.py``,
``stabilize/shared_decode.py``, ``stabilize/metrics.py`` (the input measured against the output),
``estimators/rolling.py``, ``overlay/samples.py`` (``frames_at``), ``overlay/merge.py`` (the
``--mask`` carried into the undistorted frame: :func:`image_filter_for`) and, through
``stitch/live.py`` and ``live/stabilize.py``, the live stream.  Once each is given the lens by its
caller, the registry goes."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from pathlib import Path

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


def lens_of(path: str | Path, lens: ImageFilter | None, raw: bool = False) -> ImageFilter | None:
    """The filter a reader of ``path`` applies: none when ``raw`` (the frames as decoded), else
    ``lens`` when given, else the one :func:`seen_through` set for ``path`` (transitional)."""
    if raw:
        return None
    return lens if lens is not None else image_filter_for(path)


# The transitional registry (see the module doc): each input's filter keyed by its resolved path,
# set for the length of a command.  Every reader of that input that is given no ``lens`` (the
# estimator's pass, the probes, the stitch's scan, the stabiliser's render) then sees the same
# undistorted frames; its outputs (a stabilised video measured afterwards) are left alone.
_SEEN_THROUGH: dict[str, ImageFilter] = {}


@contextlib.contextmanager
def seen_through(path: str | Path, image_filter: ImageFilter | None) -> Iterator[None]:
    """While inside, the frames a reader given no ``lens`` reads from ``path`` are
    ``image_filter(plane)`` of each decoded image (h, w) or (h, w, C), keeping its size; yuv420p
    frames are filtered plane by plane.  None: nothing changes."""
    key = str(Path(path).resolve())
    if image_filter is None:
        yield
        return
    _SEEN_THROUGH[key] = image_filter
    try:
        yield
    finally:
        _SEEN_THROUGH.pop(key, None)


def image_filter_for(path: str | Path) -> ImageFilter | None:
    """The filter :func:`seen_through` set for ``path`` (a file, or a live source's name as
    given), None where there is none."""
    return _SEEN_THROUGH.get(str(Path(path).resolve())) if _SEEN_THROUGH else None
