"""What the readers hand out: :class:`VideoStream`, a video's frames one at a time, checked
against the count the container announced once read to the end (:mod:`.policy`)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.video.info import VideoInfo
from mosaic_cli.video.policy import Shortfall, account_for_frames


class VideoStream:
    """An iterable, closeable stream of frames; use as a context manager."""

    def __init__(self, info: VideoInfo, frames: Iterator[np.ndarray], closer=None):
        self.info = info
        self._frames = frames
        self._closer = closer
        self.frames_read = 0
        self.frames_skipped = 0  # by ``start``: decoded, not yielded
        self.decode_error: str | None = None  # set when the decoder stopped with an error
        self.shortfall: Shortfall | None = None  # set when read to the end and short of the count

    def __iter__(self) -> Iterator[np.ndarray]:
        for frame in self._frames:
            self.frames_read += 1
            yield frame
        if self.frames_read == 0:
            why = f" ({self.decode_error})" if self.decode_error else ""
            raise BadInput(f"{self.info.path}: no decodable frames{why}")
        self.shortfall = account_for_frames(self.info, self.frames_skipped + self.frames_read, self.decode_error)

    def close(self) -> None:
        if self._closer is not None:
            self._closer()
            self._closer = None

    def __enter__(self) -> VideoStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
