"""Stage 4, outputs: the panorama (PNG, JPEG or TIFF by extension; alpha where the format
has it; with telemetry also a KMZ, MBTiles or a folder of web tiles, see geo/) and the
transforms JSON, all written atomically."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mosaic_cli.atomic import check_writable, write_json
from mosaic_cli.errors import BadInput
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
    if fmt == "jpeg" and max_size is not None and max_size > JPEG_MAX_SIDE:
        raise BadInput(f"JPEG images are at most {JPEG_MAX_SIDE} pixels wide: give --max-size {JPEG_MAX_SIDE} or less, or write a .png or .tif")
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
