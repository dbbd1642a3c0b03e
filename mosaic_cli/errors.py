"""User-facing errors: one clear line on stderr and a distinct exit code, never a traceback."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

EXIT_BAD_INPUT = 2
EXIT_FAILED = 1
EXIT_INTERRUPTED = 130


def warn(message: str) -> None:
    """One ``mosaic: warning:`` line on stderr: said even with -q, the run goes on."""
    import sys

    sys.stderr.write(f"mosaic: warning: {message}\n")
    sys.stderr.flush()


class MosaicError(Exception):
    """An error the user can act on; the CLI prints its message as one line."""

    exit_code = EXIT_FAILED


class BadInput(MosaicError):
    """The user's input (path, video, option value) is unusable."""

    exit_code = EXIT_BAD_INPUT


class ProcessingError(MosaicError):
    """Valid input that the pipeline cannot turn into a result (e.g. a degenerate chain)."""

    exit_code = EXIT_FAILED


class Interrupted(MosaicError):
    """The user stopped the run (Ctrl-C, SIGTERM) at a point where it could say what was kept;
    its exit status the shell's for that signal (130, 143)."""

    exit_code = EXIT_INTERRUPTED

    def __init__(self, message: str, signum: int | None = None):
        super().__init__(message)
        if signum is not None:
            self.exit_code = 128 + signum


def install_hint(extra: str) -> str:
    """The one command that adds an extra (``plot``, ``geo``) to an installed mosaic, named the
    same in every message and doc: it works in the environment mosaic is installed in, from any
    folder, whether mosaic came from a checkout (``pip install -e .``) or a wheel."""
    return f"pip install 'mosaic-cli[{extra}]'"


# Maps (georeferencing, COG, footprints, GPX) need packages only the ``geo`` extra installs.
GEO_EXTRA = f"maps need the geo extra: {install_hint('geo')}"
GEO_PACKAGES = ("pyproj", "rasterio", "gpxpy")


def require_geo(*packages: str) -> None:
    """BadInput, one line, when a package of the ``geo`` extra (``packages``, or all of them) is
    not installed; called before it is imported, and before any long work that ends in a map.
    Looks the packages up without importing them."""
    import importlib.util

    for name in packages or GEO_PACKAGES:
        if importlib.util.find_spec(name) is None:
            raise BadInput(GEO_EXTRA)


# Below this much free space a failed write is put down to a full disk.
FULL_DISK_BYTES = 64 << 20


def disk_reason(folder, detail: str) -> str:
    """Why a write into ``folder`` failed, for the user: "the disk holding FOLDER is full" where
    it has (nearly) no space left, else ``detail`` (the library's words)."""
    import os
    import shutil

    try:
        free = shutil.disk_usage(os.fspath(folder) or ".").free
    except OSError:
        return detail
    return f"the disk holding {folder} is full" if free < FULL_DISK_BYTES else detail


def write_failed(out, what: str, detail: str) -> ProcessingError:
    """One line for a failed write of ``what`` for ``out`` (``detail``: the library's words), the
    disk named where it is full."""
    import os

    folder = os.path.dirname(os.fspath(out)) or "."
    return ProcessingError(f"{out}: could not write {what} ({disk_reason(folder, detail)})")


@contextlib.contextmanager
def gdal_writing(out, what: str) -> Iterator[None]:
    """GDAL failing inside the block as one :func:`write_failed` line for ``out``: rasterio
    raises its own errors and GDAL's ``CPLE_*``, which are not among them."""
    import rasterio.errors
    from rasterio._err import CPLE_BaseError  # (not exported by rasterio.errors)

    try:
        yield
    except (rasterio.errors.RasterioError, CPLE_BaseError) as exc:
        raise write_failed(out, what, str(exc)) from None
