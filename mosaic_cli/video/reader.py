"""Every video file mosaic reads goes through here: :func:`probe` says what a file holds,
:func:`open_video` streams its frames (or a folder of numbered images' frames), one at a time.

The names live in modules of one job each, re-exported here:

* :mod:`.info`: :class:`VideoInfo`, :class:`StreamMeta`, :func:`scaled_size`;
* :mod:`.stream`: :class:`VideoStream`;
* :mod:`.probe`: probing with PyAV, in-process, once per command;
* :mod:`.decode`: the bundled ffmpeg on a pipe (:mod:`.ffmpeg_decoder`), or PyAV where there is
  none (:mod:`.pyav_decoder`): :func:`Decoder`, :func:`open_video`, picked frames; the pixel
  formats (:mod:`.pixels`), ``--lens`` (:mod:`.lens_filter`);
* :mod:`.folders`: folders of numbered images;
* :mod:`.policy`: the reading policy for a video short of its announced frames (``--strict``).
"""

from mosaic_cli.video.decode import Decoder, frame_at, frames_at, open_video
from mosaic_cli.video.ffmpeg_decoder import FfmpegDecoder, ffmpeg_exe, read_into
from mosaic_cli.video.folders import DEFAULT_FOLDER_FPS, IMAGE_SUFFIXES, folder_images, read_image_rgb
from mosaic_cli.video.info import StreamMeta, VideoInfo, scaled_size
from mosaic_cli.video.pixels import PIXELS, frame_shape
from mosaic_cli.video.policy import (
    EXACT_COUNT_SUFFIXES,
    SHORTFALL_TOLERANCE,
    Shortfall,
    account_for_frames,
    reading_policy,
    refuse_damaged,
    shortfalls,
)
from mosaic_cli.video.probe import DAMAGE_SIGNS, TAIL_SECONDS, audio_codec_of, probe
from mosaic_cli.video.pyav_decoder import PyAVDecoder
from mosaic_cli.video.stream import VideoStream

__all__ = [
    "DAMAGE_SIGNS",
    "DEFAULT_FOLDER_FPS",
    "EXACT_COUNT_SUFFIXES",
    "IMAGE_SUFFIXES",
    "PIXELS",
    "SHORTFALL_TOLERANCE",
    "TAIL_SECONDS",
    "Decoder",
    "FfmpegDecoder",
    "Shortfall",
    "StreamMeta",
    "VideoInfo",
    "VideoStream",
    "account_for_frames",
    "audio_codec_of",
    "ffmpeg_exe",
    "folder_images",
    "frame_at",
    "frame_shape",
    "frames_at",
    "open_video",
    "probe",
    "PyAVDecoder",
    "read_image_rgb",
    "read_into",
    "reading_policy",
    "refuse_damaged",
    "scaled_size",
    "shortfalls",
]
