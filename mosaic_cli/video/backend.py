"""Which backend decodes and encodes video files: the ffmpeg binary of imageio-ffmpeg on a pipe
(``"ffmpeg"``, the default) or libav in this process through PyAV (``"pyav"``), for machines
that have PyAV but no ffmpeg binary (docs/developer/video.md, "The PyAV backend")."""

from __future__ import annotations

import os

from mosaic_cli.errors import BadInput

BACKENDS = ("ffmpeg", "pyav")
ENV = "MOSAIC_VIDEO_BACKEND"

_ffmpeg_found: bool | None = None  # the imageio-ffmpeg lookup, made once (it searches the disk)


def video_backend() -> str:
    """``"ffmpeg"`` or ``"pyav"``: :data:`ENV` when set (read on every call, so that a test or
    a user may switch), else ffmpeg where a binary is found, else PyAV."""
    chosen = os.environ.get(ENV, "").strip()
    if chosen:
        if chosen not in BACKENDS:
            raise BadInput(f"{ENV} must be one of {', '.join(BACKENDS)}, got {chosen!r}")
        return chosen
    return "ffmpeg" if ffmpeg_available() else "pyav"


def ffmpeg_available() -> bool:
    """Whether an ffmpeg binary is at hand: ``IMAGEIO_FFMPEG_EXE`` set, or imageio-ffmpeg
    importable and finding its binary (looked up once: :func:`reset` forgets it)."""
    global _ffmpeg_found
    if os.environ.get("IMAGEIO_FFMPEG_EXE"):
        return True
    if _ffmpeg_found is None:
        try:
            import imageio_ffmpeg

            imageio_ffmpeg.get_ffmpeg_exe()
            _ffmpeg_found = True
        except Exception:  # not installed, or installed without its binary (RuntimeError)
            _ffmpeg_found = False
    return _ffmpeg_found


def reset() -> None:
    """Forget the imageio-ffmpeg lookup (tests that hide the binary)."""
    global _ffmpeg_found
    _ffmpeg_found = None
