"""Atomic output: write to a temporary file beside the target, then rename over it.

A failed or interrupted run therefore never leaves a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

from mosaic_cli.errors import BadInput


def check_writable(path: str | os.PathLike) -> Path:
    """Fail early, before any work, when ``path`` cannot be written."""
    target = Path(path)
    parent = target.parent if str(target.parent) else Path(".")
    if target.is_dir():
        raise BadInput(f"output {target} is a directory")
    if not parent.is_dir():
        raise BadInput(f"output folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise BadInput(f"output folder {parent} is not writable")
    # A real file, made and removed: permission bits do not stop root, and read-only or
    # pseudo file systems (/proc) pass the access check.
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as exc:
        raise BadInput(f"output folder {parent} is not writable ({exc.strerror.lower()})") from None
    return target


def give_default_permissions(path: str | os.PathLike) -> None:
    """mkstemp makes files readable by their owner only; give the mode a plain ``open`` would
    (0666 less the umask), so outputs are as shareable as any other file the user writes."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path with the target's suffix; rename it onto ``path`` on success.

    The suffix is kept so that tools choosing a format by extension (ffmpeg, cv2.imwrite) work.
    """
    target = check_writable(path)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".part{target.suffix}", dir=target.parent or ".")
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        give_default_permissions(tmp)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_json(path: str | os.PathLike, data: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data) + "\n")


def write_bytes(path: str | os.PathLike, payload: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(payload)
