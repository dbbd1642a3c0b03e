"""Streaming video input and output: one frame at a time, memory independent of length."""

from mosaic_cli.video.decode import gray_at  # noqa: F401
from mosaic_cli.video.reader import VideoInfo, open_video, probe  # noqa: F401
from mosaic_cli.video.writer import VideoWriter  # noqa: F401
