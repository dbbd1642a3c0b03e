"""Atomic output: write to a temporary file beside the target, then rename over it.

A failed or interrupted run therefore never leaves a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

from mosaic_cli.errors import BadInput

T = TypeVar("T")


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
def signals_held() -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM while a temporary file is made and its name handed to the code that
    removes it (a signal in between would leave the file behind); they take effect on leaving.

    The Python handlers are swapped for recorders, rather than the signals blocked, because a
    process with other threads (OpenCV's) takes a signal on any of them and Python still runs
    its handler on the main thread.  Off the main thread nothing is held."""
    held = (signal.SIGINT, signal.SIGTERM)
    pending: list[int] = []
    try:
        previous = {signum: signal.signal(signum, lambda signum, frame: pending.append(signum)) for signum in held}
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        for signum in pending:
            signal.raise_signal(signum)  # now, to the handler that was in place


def temporary_beside(target: Path, suffix: str) -> Path:
    """A new empty file ``.<stem>.XXXX<suffix>`` in the target's folder (call under :func:`signals_held`)."""
    fd, name = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=suffix, dir=target.parent or ".")
    os.close(fd)
    return Path(name)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, alone: bool = False) -> Iterator[Path]:
    """Yield a temporary path with the target's suffix; rename it onto ``path`` on success.

    The suffix is kept so that tools choosing a format by extension (ffmpeg, cv2.imwrite) work.
    ``alone``: the temporary file in a folder of its own (see :func:`private_folder`), for a
    writer that makes files of its own beside its output (GDAL's COG driver its overviews).
    """
    target = check_writable(path)
    if alone:
        with private_folder(target) as folder:
            tmp = folder / target.name
            yield tmp
            give_default_permissions(tmp)
            os.replace(tmp, target)
        return
    tmp = None
    try:
        with signals_held():
            tmp = temporary_beside(target, f".part{target.suffix}")
        yield tmp
        give_default_permissions(tmp)
        os.replace(tmp, target)
    except BaseException:
        if tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        raise


@contextlib.contextmanager
def private_folder(target: Path) -> Iterator[Path]:
    """A new folder ``.<stem>.XXXX.part`` beside ``target``, removed with all it holds on leaving.

    Whatever a writer makes in it by name goes with it, also after an :func:`interruptible`
    call was left running: once the folder is gone, nothing more can be made in it."""
    folder = None
    try:
        with signals_held():
            folder = Path(tempfile.mkdtemp(prefix=f".{target.stem}.", suffix=".part", dir=target.parent or "."))
        yield folder
    finally:
        for _ in range(3):  # a writer still running may add a file while the folder is emptied
            if folder is None or not folder.exists():
                break
            shutil.rmtree(folder, ignore_errors=True)


def interruptible(call: Callable[[], T]) -> T:
    """``call()`` on a thread of its own while this one waits for it, so that Ctrl-C or SIGTERM
    unwind the run at once.

    For long C calls that let go of the interpreter (GDAL's copies of a map take minutes):
    Python runs a signal's handler only between the main thread's bytecodes, so a call made
    there holds the signal until it returns.  On a signal the run unwinds and removes what was
    being written; the thread, left writing into files already unlinked, ends with the process
    (``cli.entry`` leaves by ``os._exit``).  So whatever the call makes by name beside its
    output must be in a :func:`private_folder`.  GDAL's settings are the process's, so the
    thread sees the caller's ``rasterio.Env``."""
    outcome: list[tuple[bool, Any]] = []

    def run() -> None:
        try:
            outcome.append((True, call()))
        except BaseException as exc:  # handed to the waiting thread
            outcome.append((False, exc))

    worker = threading.Thread(target=run, name="mosaic-interruptible", daemon=True)
    worker.start()
    worker.join()  # a signal's handler runs here, at once
    done, value = outcome[0]
    if not done:
        raise value
    return value


def write_json(path: str | os.PathLike, data: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data) + "\n")


def write_bytes(path: str | os.PathLike, payload: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(payload)
