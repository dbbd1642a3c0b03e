"""A folder of numbered images read as a video: its images in natural order (``frame_2`` before
``frame_10``), each in a frame the size of the first, at a frame rate of its own (``fps``, else 30).

A folder may mix cameras.  An image of the first's shape at another size is resized to it; one
of another shape (4:3 among 16:9, portrait among landscape) is fitted whole into the first's
frame, centred (:class:`~.info.PhotoFit`, listed in the info before any is decoded), and the
consumers keep the empty rest of the frame out of their features and drawings."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.video.info import EXIF_ORIENTATION, PhotoFit, VideoInfo, scaled_size, shown_size
from mosaic_cli.video.stream import VideoStream

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"}
DEFAULT_FOLDER_FPS = 30.0


def _natural_key(path: Path) -> list:
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


def folder_images(folder: Path) -> list[Path]:
    """The images of ``folder`` in natural order (frame_2 before frame_10)."""
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()), key=_natural_key)


def read_image_rgb(path: Path) -> np.ndarray:
    check_intact(path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise BadInput(f"{path}: not an image OpenCV can read")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def check_intact(path: Path, remedy: str = "copy it again, or take it out of the folder") -> None:
    """Refuse a damaged image before OpenCV decodes it: OpenCV decodes a truncated JPEG (a copy cut
    short) with its missing part grey, libjpeg's warning on stderr the only sign, and leaves
    libpng's complaint on stderr for a PNG.  Pillow reads a JPEG's whole coded data at 1/8 scale
    (about half the time of OpenCV's decode) and a PNG's chunks with their checksums; other
    formats are OpenCV's to refuse (``read_image_rgb``).  ``remedy``: what the user is told to do."""
    import warnings

    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Pillow's (a large photo, odd EXIF): only what fails counts here
            with Image.open(path) as image:
                if image.format == "JPEG":
                    image.draft("RGB", (max(1, image.size[0] // 8), max(1, image.size[1] // 8)))
                    image.load()
                elif image.format == "PNG":
                    image.verify()
    except (UnidentifiedImageError, Image.DecompressionBombError):
        return  # a format Pillow does not read, or past its size limit: OpenCV decides
    except (OSError, SyntaxError, ValueError) as exc:
        raise BadInput(f"{path}: damaged image ({exc}): {remedy}") from None


def image_size(path: Path) -> tuple[int, int] | None:
    """(w, h) of an image as it is displayed (its EXIF orientation applied, as OpenCV reads it),
    from its header alone; None where Pillow cannot read the header."""
    import warnings

    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Pillow's about damaged EXIF: read_photo_tags names those
            with Image.open(path) as image:
                return shown_size(image.size, image.getexif().get(EXIF_ORIENTATION, 1))
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError):
        return None


def photo_fits(files: list[Path], frame: tuple[int, int]) -> tuple[PhotoFit, ...]:
    """The images of ``files`` not of ``frame``'s size, each fitted into it (from their headers;
    an image whose header Pillow cannot read is taken to be of the frame's size, and checked as
    it is decoded)."""
    fits = []
    for k, path in enumerate(files):
        size = image_size(path)
        if size is not None and size != frame:
            fits.append(PhotoFit.into(frame, size, k, path.name))
    return tuple(fits)


def other_cameras_note(info: VideoInfo) -> list[str]:
    """One line naming a folder's photos of another size than its first (another camera), and
    how they were read, for the warnings; none where there are none."""
    if not info.photo_fits:
        return []
    w, h = info.source_size
    fits = info.photo_fits
    shown = ", ".join(f"{f.name} ({f.photo_size[0]}x{f.photo_size[1]})" for f in fits[:5]) + (
        f" and {len(fits) - 5} more" if len(fits) > 5 else "")
    how = "resized to it" if all(f.fills((w, h)) for f in fits) else "each fitted whole into its frame (another shape: the rest left empty)"
    return [f"{len(fits)} of {info.frame_count} photos are not {w}x{h} like the first (another camera): {how}, "
            f"placed by their own pixels: {shown}"]


def open_folder(folder: Path, width: int | None, fps: float | None, gray: bool) -> VideoStream:
    """The images of ``folder`` as a stream of frames (``width``: downscaled, aspect kept;
    ``gray``: (h, w) frames); its info says ``fps``, else :data:`DEFAULT_FOLDER_FPS`, and lists
    the images of another shape than the first's, fitted into its frame (``photo_fits``)."""
    files = folder_images(folder)
    if not files:
        raise BadInput(f"{folder}: folder holds no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
    first = read_image_rgb(files[0])
    source_size = (first.shape[1], first.shape[0])
    size = scaled_size(source_size, width)
    rate = fps or DEFAULT_FOLDER_FPS
    fits = {f.index: f for f in photo_fits(files, source_size) if f.index > 0}  # (the first sets the frame)
    info = VideoInfo(str(folder), size, source_size, rate, len(files), len(files) / rate, is_image_folder=True,
                     photo_fits=tuple(fits.values()))

    def frames() -> Iterator[np.ndarray]:
        for k, path in enumerate(files):
            img = first if k == 0 else read_image_rgb(path)
            shape = (img.shape[1], img.shape[0])
            fit = fits.get(k)
            if fit is None and shape != source_size:  # a header Pillow could not read
                fit = PhotoFit.into(source_size, shape, k, path.name)
                if not fit.fills(source_size):
                    raise BadInput(f"{path}: {shape[0]}x{shape[1]} is not the shape of the first image's "
                                   f"{source_size[0]}x{source_size[1]}, and its header cannot be read")
            elif fit is not None and shape != fit.photo_size:
                raise BadInput(f"{path}: decoded at {shape[0]}x{shape[1]} where its header says "
                               f"{fit.photo_size[0]}x{fit.photo_size[1]}")
            if fit is not None and not fit.fills(source_size):
                img = fitted(img, fit, source_size, size)
            elif shape != size:  # (another camera of the first's shape: the registration finds its scale)
                img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
            yield cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if gray else img

    return VideoStream(info, frames())


def fitted(img: np.ndarray, fit: PhotoFit, source_size: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """``img`` placed in a frame of ``size`` (``source_size`` downscaled) where ``fit`` says, the
    rest black."""
    rows, columns = fit.region(size, source_size)
    frame = np.zeros((size[1], size[0], 3), np.uint8)
    frame[rows, columns] = cv2.resize(img, (columns.stop - columns.start, rows.stop - rows.start), interpolation=cv2.INTER_AREA)
    return frame
