"""The process-wide reading policy: what happens when a video decodes to fewer frames than its
container announces (a truncated or damaged file)."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from mosaic_cli.errors import BadInput
from mosaic_cli.video.info import VideoInfo

# --- Frames missing at the end: decoded fewer than the container announced -------------------
# The run goes on with what decoded, after one warning line; under ``reading_policy(strict=True)``
# (the commands' --strict) it is an error instead.  What was found is kept per path for the
# outputs' metadata (:func:`shortfalls`).

SHORTFALL_TOLERANCE = 2  # frames: rounding of a duration-based count, an edit list's last frame
EXACT_COUNT_SUFFIXES = {".mp4", ".mov", ".m4v", ".3gp", ".avi"}  # containers that store the count itself
_policy: dict = {"strict": False}
_shortfalls: dict[str, Shortfall] = {}


@dataclass(frozen=True)
class Shortfall:
    """A video that decoded to fewer frames than its container announced."""

    path: str
    decoded: int
    announced: int
    reason: str | None = None  # ffmpeg's complaint, when it made one

    def message(self) -> str:
        why = f" ({self.reason})" if self.reason else ""
        return (f"{self.path}: decoded {self.decoded} of the {self.announced} frames the container announces: "
                f"truncated or damaged{why}")

    def as_meta(self) -> dict:
        """For the outputs' metadata: ``{"frames_decoded", "frames_announced", "truncated", "reason"}``."""
        return {"frames_decoded": self.decoded, "frames_announced": self.announced, "truncated": True,
                "reason": self.reason}


@contextlib.contextmanager
def reading_policy(strict: bool = False) -> Iterator[None]:
    """For one command's run: whether a short video is an error (``strict``) or a warning; also
    forgets what earlier runs in this process found."""
    previous = dict(_policy)
    _policy["strict"] = bool(strict)
    _shortfalls.clear()
    try:
        yield
    finally:
        _policy.update(previous)


def shortfalls() -> dict[str, Shortfall]:
    """Each video of this run found short, by path."""
    return dict(_shortfalls)


def account_for_frames(info: VideoInfo, decoded: int, decode_error: str | None = None) -> Shortfall | None:
    """Compare the frames decoded to the end with those the container announced.

    Short by more than :data:`SHORTFALL_TOLERANCE`: under --strict a BadInput; else one warning
    line on stderr (once per video and run) and the :class:`Shortfall`.  A count worked out from
    the container's duration (mkv, webm) can exceed the video where the audio runs longer, so
    there a complaint from ffmpeg is also needed."""
    if info.is_image_folder or not info.frame_count:
        return None
    exact = Path(info.path).suffix.lower() in EXACT_COUNT_SUFFIXES
    reason = info.damage or decode_error
    if info.frame_count - decoded <= SHORTFALL_TOLERANCE or not (exact or reason or not info.has_audio):
        return None
    found = Shortfall(info.path, decoded, info.frame_count, reason)
    if _policy["strict"]:
        raise BadInput(f"{found.message()}; --strict refuses it")
    if info.path not in _shortfalls:
        _shortfalls[info.path] = found
        sys.stderr.write(f"mosaic: warning: {found.message()}; going on with the {decoded} decoded\n")
        sys.stderr.flush()
    return found


def refuse_damaged(info: VideoInfo) -> None:
    """Under --strict (:func:`reading_policy`), a video whose end the probe found damaged is
    refused before any work; otherwise nothing (the shortfall is said once decoded)."""
    if info.damage and _policy["strict"]:
        said = f"; the container announces {info.frame_count} frames" if info.frame_count else ""
        raise BadInput(f"{info.path}: truncated or damaged video ({info.damage}{said}); --strict refuses it")
