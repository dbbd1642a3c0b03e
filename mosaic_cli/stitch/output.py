"""Stage 4, outputs: the panorama (PNG, JPEG or TIFF by extension; alpha where the format
has it; with telemetry also a KMZ, MBTiles or a folder of web tiles, see geo/) and the
transforms JSON, all written atomically."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.atomic import atomic_path, check_writable, write_json
from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.inputs import FORMATS, MAP_FORMATS, output_format  # noqa: F401  (what a panorama's extension makes it; geo/ asks too)

JPEG_MAX_SIDE = 65500


def check_outputs(out: str | Path, transforms: str | Path | None, max_size: int | None) -> str:
    """Fail before any work on an output that cannot be written; returns the image format."""
    fmt = output_format(out)
    out = Path(out)
    if fmt is None:
        raise BadInput(f"output {out} must end in .png, .jpg, .jpeg, .tif, .tiff, .kmz, .pmtiles or .mbtiles, or be a folder (DIR/) for web tiles")
    if fmt == "tiles":
        from mosaic_cli.geo.tiles import check_tiles_folder

        check_tiles_folder(out)
    else:
        check_writable(out)
    if fmt == "jpeg" and (max_size is None or max_size > JPEG_MAX_SIDE):
        raise BadInput(f"JPEG images are at most {JPEG_MAX_SIDE} pixels wide: give --max-size {JPEG_MAX_SIDE} or less")
    if transforms is not None:
        transforms = Path(transforms)
        if transforms.suffix.lower() != ".json":
            raise BadInput(f"--transforms {transforms} must end in .json")
        check_writable(transforms)
        if transforms.resolve() == out.resolve():
            raise BadInput("--transforms must differ from the panorama output")
    return fmt


def numbered(path: str | Path, number: int) -> str | Path:
    """The ``number``-th output (from 0) of a flight stitched into several panoramas:
    pano.png, pano-2.png, pano-3.png, ..."""
    if number == 0:
        return path if isinstance(path, str) else Path(path)  # a str keeps a folder's trailing slash
    folder = str(path).endswith(("/", os.sep))
    path = Path(path)
    if folder:
        return f"{path}-{number + 1}{os.sep}"
    return path.with_name(f"{path.stem}-{number + 1}{path.suffix}")


def write_panorama(out: str | Path, rgba: np.ndarray, jpeg_quality: int = 92) -> None:
    """PNG and TIFF keep the alpha channel (transparent where nothing was seen); JPEG has
    none, so uncovered areas are black.  ``rgba`` is turned into BGRA in place: a panorama
    may be gigabytes, so no second copy is made."""
    fmt = output_format(out)
    if fmt in MAP_FORMATS:
        raise ProcessingError(f"{out}: a {MAP_FORMATS[fmt]} output needs the panorama's place on the ground, which the telemetry does not give it")
    image = cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA, dst=rgba)
    if fmt == "jpeg":  # OpenCV drops the alpha channel row by row
        params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality]
    else:
        params = [cv2.IMWRITE_PNG_COMPRESSION, 3] if fmt == "png" else []
    with atomic_path(out) as tmp:
        if not cv2.imwrite(str(tmp), image, params):
            raise ProcessingError(f"{out}: OpenCV could not write the {(fmt or 'image').upper()} image")


def write_transforms(
    path: str | Path, canvas_size: tuple[int, int], frames: list[tuple[int, np.ndarray]], extra: tuple[dict, list[dict]] | None = None
) -> None:
    """``{"canvas_size": [W, H], "frames": [{"index": i, "H": 3x3}, ...]}``: each used frame's
    homography, frame pixels (full resolution) -> panorama pixels; with ``"input": {...}`` when
    the video decoded to fewer frames than its container announced (video.reader.Shortfall).
    ``extra`` (georeferenced stitches) adds top-level keys and per-frame keys: ``crs`` and
    ``map_H`` (see geo/output.py)."""
    from mosaic_cli.video.reader import shortfalls

    top, per_frame = extra if extra is not None else ({}, [{} for _ in frames])
    doc = {
        "canvas_size": [int(canvas_size[0]), int(canvas_size[1])],
        **top,
        "frames": [{"index": int(i), "H": [[float(v) for v in row] for row in H], **more} for (i, H), more in zip(frames, per_frame)],
    }
    for short in shortfalls().values():  # one video a run
        doc["input"] = short.as_meta()
    write_json(path, doc)
