"""A folder of numbered images read as a video: its images in natural order (``frame_2`` before
``frame_10``), each the size of the first, at a frame rate of its own (``fps``, else 30)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.video.info import VideoInfo, scaled_size
from mosaic_cli.video.stream import VideoStream

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"}
DEFAULT_FOLDER_FPS = 30.0
SAME_SHAPE = 0.01  # images whose aspect ratios differ by less than this share a folder's size


def _natural_key(path: Path) -> list:
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


def folder_images(folder: Path) -> list[Path]:
    """The images of ``folder`` in natural order (frame_2 before frame_10)."""
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()), key=_natural_key)


def read_image_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise BadInput(f"{path}: not an image OpenCV can read")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def open_folder(folder: Path, width: int | None, fps: float | None, gray: bool) -> VideoStream:
    """The images of ``folder`` as a stream of frames (``width``: downscaled, aspect kept;
    ``gray``: (h, w) frames); its info says ``fps``, else :data:`DEFAULT_FOLDER_FPS`."""
    files = folder_images(folder)
    if not files:
        raise BadInput(f"{folder}: folder holds no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
    first = read_image_rgb(files[0])
    source_size = (first.shape[1], first.shape[0])
    size = scaled_size(source_size, width)
    rate = fps or DEFAULT_FOLDER_FPS
    info = VideoInfo(str(folder), size, source_size, rate, len(files), len(files) / rate, is_image_folder=True)

    def frames() -> Iterator[np.ndarray]:
        for k, path in enumerate(files):
            img = first if k == 0 else read_image_rgb(path)
            if (img.shape[1], img.shape[0]) != source_size:
                # Another camera of the same shape (a folder mixing drones): read at the first's size;
                # the registration finds each photo's own scale.
                if abs(img.shape[1] * source_size[1] / (img.shape[0] * source_size[0]) - 1.0) > SAME_SHAPE:
                    raise BadInput(f"{path}: size {img.shape[1]}x{img.shape[0]} is not the shape of the first image's "
                                   f"{source_size[0]}x{source_size[1]}: stitch photos of each shape apart")
                img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
            elif size != source_size:
                img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
            yield cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if gray else img

    return VideoStream(info, frames())
