"""Live processing: streams in (standard input, ffmpeg URLs), outputs as frames arrive."""

from mosaic_cli.live.source import DEFAULT_TIMEOUT, LiveStream, StopRequest, is_live_source

__all__ = ["DEFAULT_TIMEOUT", "LiveStream", "StopRequest", "is_live_source"]
