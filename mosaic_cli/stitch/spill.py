"""Keyframe pixels kept on disk between the scan and the compositing.

A survey keeps a keyframe's pixels for every bit of new ground, and neighbouring survey lines
overlap, so the held pixels add up to several times the canvas: about 900 MB for a 1080p
flight whose canvas reaches 8000 px (``python -m benchmarks stitch memory``
--speed 32).  Holding them in temporary ``.npy`` files instead (lossless, a few ms to write
or read one) keeps the process's memory to what compositing one strip needs; the files live
in a temporary folder (``$TMPDIR``) that the stitch removes however it ends.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from mosaic_cli.errors import ProcessingError, disk_reason


class SpilledImage:
    """An image held in a file until needed: ``shape``, ``size`` and ``dtype`` as the array's,
    ``load()`` for the pixels, ``drop()`` to delete the file."""

    def __init__(self, image: np.ndarray, folder: str | Path):
        handle, name = tempfile.mkstemp(suffix=".npy", dir=folder)
        self.path = Path(name)
        try:
            with os.fdopen(handle, "wb") as file:
                np.save(file, np.ascontiguousarray(image), allow_pickle=False)
        except OSError as exc:  # numpy's short write says only how many bytes it wrote
            self.path.unlink(missing_ok=True)
            raise ProcessingError(f"{folder}: could not keep a keyframe's pixels there ({disk_reason(folder, str(exc))}); "
                                  "TMPDIR names another folder") from None
        self.shape: tuple[int, ...] = image.shape
        self.size: int = image.size
        self.dtype = image.dtype

    def load(self) -> np.ndarray:
        return np.load(self.path, allow_pickle=False)

    def drop(self) -> None:
        self.path.unlink(missing_ok=True)


Pixels = np.ndarray | SpilledImage


def load_pixels(image: Pixels) -> np.ndarray:
    """The pixels of an array or of a spilled image."""
    return image.load() if isinstance(image, SpilledImage) else image


def drop_pixels(image: Pixels | None) -> None:
    """Free a spilled image's file now rather than when the stitch ends."""
    if isinstance(image, SpilledImage):
        image.drop()
