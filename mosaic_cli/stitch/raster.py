"""The panorama on disk, tile by tile, so that memory does not follow the canvas.

compose writes each finished tile into a tiled RGBA GeoTIFF staged beside the output (GDAL
through rasterio; the alpha band declared as alpha), and every format is made from that file:
a plain TIFF is the staged file itself, renamed; PNG and JPEG are GDAL's drivers reading it
block by block (on a thread of their own, so that a signal need not wait for a copy of minutes);
the maps (COG, KMZ, tiles, PMTiles, MBTiles) are geo/'s writers reading it.
GDAL's block cache is bounded (``CACHE_MB``), so a write holds a few tiles, not the canvas.
Where GDAL cannot be imported (the lent GPU machine has no rasterio) the panorama is held in
memory and written by OpenCV, as before tiles: the same pixels, memory that follows the canvas.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from mosaic_cli.atomic import atomic_path, give_default_permissions, interruptible, signals_held, temporary_beside
from mosaic_cli.errors import BadInput, ProcessingError, gdal_writing
from mosaic_cli.inputs import MAP_FORMATS
from mosaic_cli.stitch.compose import MemoryCanvas
from mosaic_cli.stitch.output import JPEG_MAX_SIDE

BLOCK = 512  # the staged file's internal tiles, pixels
CACHE_MB = 256  # GDAL's block cache while the panorama is written and copied (rasterio takes it in bytes)


class StagedPanorama:
    """A tiled RGBA GeoTIFF being written: ``write(x, y, rgba)`` puts a tile (compose's sink);
    ``crs`` and ``transform`` (rasterio's Affine, pixel corners -> CRS) make it a map.  ``keep``:
    it becomes the user's ``.tif`` (compressed as a deliverable; otherwise fast to write)."""

    def __init__(self, path: Path, size: tuple[int, int], crs: str | None = None, transform=None, keep: bool = False,
                 out: str | Path | None = None):
        import rasterio
        from rasterio.enums import ColorInterp

        self.path, self.size = path, size
        self.out = path if out is None else out  # the user's output, which errors name
        compression = {"compress": "deflate", "predictor": 2} if keep else {"compress": "deflate", "zlevel": 1}
        profile = dict(driver="GTiff", width=size[0], height=size[1], count=4, dtype="uint8", tiled=True, blockxsize=BLOCK,
                       blockysize=BLOCK, photometric="RGB", ALPHA="YES", BIGTIFF="IF_SAFER", **compression)
        if crs is not None:
            profile.update(crs=crs, transform=transform)
        with gdal_writing(self.out, "the panorama"):
            self.dataset = rasterio.open(path, "w+", **profile)  # readable too: --fill-holes reads it back
            self.dataset.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]

    def write(self, x: int, y: int, rgba: np.ndarray) -> None:
        from rasterio.windows import Window

        with gdal_writing(self.out, "the panorama"):
            self.dataset.write(np.ascontiguousarray(rgba.transpose(2, 0, 1)), window=Window(x, y, rgba.shape[1], rgba.shape[0]))

    def read(self) -> np.ndarray:
        """The whole panorama, RGBA (H, W, 4) (``--fill-holes`` only: it needs the canvas at once)."""
        return np.ascontiguousarray(self.dataset.read().transpose(1, 2, 0))

    def close(self) -> None:
        if not self.dataset.closed:
            with gdal_writing(self.out, "the panorama"):
                self.dataset.close()  # (the last blocks written here)


class MemoryPanorama(MemoryCanvas):
    """The panorama in memory, RGBA (H, W, 4), where GDAL is missing: a plain image only."""

    path = None

    def __init__(self, size: tuple[int, int]):
        super().__init__(size)
        self.size = size

    def read(self) -> np.ndarray:
        return self.rgba

    def close(self) -> None:
        pass


@contextlib.contextmanager
def staged_panorama(out: str | Path, size: tuple[int, int], crs: str | None = None, transform=None,
                    keep: bool = False) -> Iterator[StagedPanorama | MemoryPanorama]:
    """A :class:`StagedPanorama` in a temporary file beside ``out`` (the same disk, so that a
    plain ``.tif`` is renamed into place), removed on leaving unless :func:`write_image` moved
    it; GDAL's cache bounded while it is open.  Without GDAL (and no map asked), a
    :class:`MemoryPanorama`."""
    try:
        import rasterio
    except ImportError:
        if crs is not None:
            raise
        yield MemoryPanorama(size)
        return
    path = None
    try:
        with signals_held():
            path = temporary_beside(Path(out), ".staging.tif")
        with rasterio.Env(GDAL_CACHEMAX=CACHE_MB << 20, GDAL_PAM_ENABLED="NO"), _plain_is_fine():
            staged = StagedPanorama(path, size, crs, transform, keep, out=out)
            try:
                yield staged
            finally:
                staged.close()
    finally:
        if path is not None:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()


def write_image(out: str | Path, staged: StagedPanorama | MemoryPanorama, fmt: str, jpeg_quality: int = 92) -> None:
    """The plain image ``out`` from the staged panorama, atomically: TIFF the staged file
    itself (tiled, deflate, alpha), PNG with alpha, JPEG without (uncovered ground black)."""
    staged.close()
    if fmt in MAP_FORMATS:
        raise ProcessingError(f"{out}: a {MAP_FORMATS[fmt]} output needs the panorama's place on the ground, which the telemetry does not give it")
    width, height = staged.size
    if fmt == "jpeg" and max(width, height) > JPEG_MAX_SIDE:
        raise BadInput(f"{out}: JPEG holds at most {JPEG_MAX_SIDE} pixels a side, the panorama is {width}x{height}: "
                       f"write a .png or .tif, or give --max-size {JPEG_MAX_SIDE}")
    if isinstance(staged, MemoryPanorama):
        _write_with_opencv(out, staged.rgba, fmt, jpeg_quality)
        return
    import rasterio
    import rasterio.shutil

    if fmt == "tiff":
        target = Path(out)
        with signals_held():
            give_default_permissions(staged.path)
            os.replace(staged.path, target)
        return
    options = {"QUALITY": str(jpeg_quality)} if fmt == "jpeg" else {"ZLEVEL": "3"}
    with gdal_writing(out, f"the {fmt.upper()} image"), atomic_path(out) as tmp, \
            rasterio.Env(GDAL_CACHEMAX=CACHE_MB << 20, GDAL_PAM_ENABLED="NO"), _plain_is_fine():
        source = _rgb_only(staged.path) if fmt == "jpeg" else str(staged.path)
        interruptible(lambda: rasterio.shutil.copy(source, tmp, driver="JPEG" if fmt == "jpeg" else "PNG", **options))


def _write_with_opencv(out: str | Path, rgba: np.ndarray, fmt: str, jpeg_quality: int) -> None:
    """``rgba`` turned into BGRA in place (no second copy of a large panorama) and written."""
    import cv2

    image = cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA, dst=rgba)
    if fmt == "jpeg":  # OpenCV drops the alpha channel row by row
        params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality]
    else:
        params = [cv2.IMWRITE_PNG_COMPRESSION, 3] if fmt == "png" else []
    with atomic_path(out) as tmp:
        if not cv2.imwrite(str(tmp), image, params):
            raise ProcessingError(f"{out}: OpenCV could not write the {fmt.upper()} image")


@contextlib.contextmanager
def _plain_is_fine() -> Iterator[None]:
    """A panorama without telemetry has no place on the ground: rasterio's warning that it has
    none is not news to the user."""
    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        yield


def _rgb_only(path: Path) -> str:
    """A VRT (XML, passed as the dataset name) of the staged file's three colour bands."""
    import rasterio

    with rasterio.open(path) as src:
        width, height = src.width, src.height
    bands = "".join(
        f'<VRTRasterBand dataType="Byte" band="{b}"><ColorInterp>{c}</ColorInterp><SimpleSource>'
        f'<SourceFilename relativeToVRT="0">{path}</SourceFilename><SourceBand>{b}</SourceBand></SimpleSource></VRTRasterBand>'
        for b, c in ((1, "Red"), (2, "Green"), (3, "Blue")))
    return f'<VRTDataset rasterXSize="{width}" rasterYSize="{height}">{bands}</VRTDataset>'
