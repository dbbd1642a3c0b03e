"""``mosaic track``'s pipeline: :func:`track` checks the request, builds the estimator and picks
the path, one of three:

* a live input (``-``, a stream URL): :func:`~mosaic_cli.live.track.track_stream`, the network
  loading beside the stream's opening, the mask made from ``--mask`` once the first frame gives
  the size;
* a file to JSON Lines: :func:`~mosaic_cli.live.track.track_stream` too, each pair written as it
  is estimated, once the overlays have been looked for;
* a file to a track file (``.json``, ``.npy``): :func:`~mosaic_cli.track.track_video`, the
  tracking started while the overlays are still looked for beside it.

``--lens`` undistorts the frames as they are decoded on each path; the track file is written
(:func:`~mosaic_cli.track.save_track`) unless the pairs went out as JSON Lines."""

from __future__ import annotations

import concurrent.futures
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mosaic_cli.atomic import check_writable
from mosaic_cli.device import ask_cpu_threads
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import Estimator, plan_estimator
from mosaic_cli.estimators.lens import LensChoice, choose_lens, parse_lens_option
from mosaic_cli.estimators.rolling import parse_rolling_shutter
from mosaic_cli.live.loading import built_beside, trained_width
from mosaic_cli.live.source import is_live_source
from mosaic_cli.live.track import is_jsonl, track_stream
from mosaic_cli.overlay import FrameMask, check_mask_file, frame_mask_pending, frame_mask_while
from mosaic_cli.progress import progress_group
from mosaic_cli.track import TrackOptions, TrackResult, save_track, track_video
from mosaic_cli.video import VideoInfo, probe
from mosaic_cli.video.reader import reading_policy


@dataclass
class TrackRun:
    """What :func:`track` did: the track, the use mask (None: a live input's, in ``result.meta``),
    the seconds the overlays cost before and during the tracking, and what ``--lens`` resolved to."""

    result: TrackResult
    masked: FrameMask | None
    overlay_seconds: float
    lens: LensChoice


def check_request(video: str, out: str, options: TrackOptions, lens: str | None) -> VideoInfo | None:
    """What the options cannot check alone, before any work: the output's kind against the
    input's and ``--rolling-shutter``'s, ``--lens auto`` on a live input, the input itself (its
    probe, returned; None for a live input) and the ``--mask`` image against it."""
    out_is_jsonl = is_jsonl(out)
    if parse_rolling_shutter(options.rolling_shutter) != "off" and (is_live_source(video) or out_is_jsonl
                                                                    or not out.lower().endswith(".json")):
        raise BadInput("--rolling-shutter writes its block to a .json track file: not with .npy, JSON Lines or a live input")
    if not out_is_jsonl:
        check_writable(out)
        if Path(out).suffix.lower() not in (".json", ".npy"):
            raise BadInput(f"output {out} must end in .json or .npy (or .jsonl, or be -, for JSON Lines)")
    elif out != "-":
        check_writable(out)
    live = is_live_source(video)
    if live and parse_lens_option(lens) == "auto":
        raise BadInput("--lens auto reads frames spread over a whole video file: with a live input, pass a lens FILE (or none)")
    info = None if live else probe(video)  # the input's one probe, passed down
    check_mask_file(options.mask, info)
    return info


def track(video: str, out: str, options: TrackOptions, *, estimator: str | None = None, work_width: int | None = None,
          weights: str | None = None, device: str = "auto", lens: str | None = None, strict: bool = False,
          show_progress: bool = True) -> TrackRun:
    """Track ``video`` (a file, an image folder or a live source) into ``out`` (a track file, or
    JSON Lines: ``.jsonl`` or ``-``) with the estimator named as on the command line
    (:func:`~mosaic_cli.estimators.plan_estimator`); ``lens``: ``--lens``'s value; ``strict``:
    a video short of its announced frames is an error (``--strict``)."""
    info = check_request(video, out, options, lens)
    build = plan_estimator(estimator, work_width=work_width, weights=weights, device=device)
    ask_cpu_threads(options.threads)
    clock = time.perf_counter()
    if is_live_source(video) or is_jsonl(out):
        return _track_stream(video, out, options, build, estimator, weights, lens, info, clock, show_progress)
    return _track_file(video, out, options, build, lens, strict, info, clock, show_progress)


def _track_stream(video: str, out: str, options: TrackOptions, build: Callable[[], Estimator], estimator: str | None, weights: str | None,
                  lens: str | None, info: VideoInfo | None, clock: float, show_progress: bool) -> TrackRun:
    """A live input, or a file to JSON Lines: the pairs out as they are estimated."""
    live = is_live_source(video)
    masked = None
    tracker: Estimator | concurrent.futures.Future
    width = None
    # --lens: a live input's frames undistorted as they arrive (live/source.py), a file's as decoded
    lens_choice = choose_lens(lens, video, info, live=live)
    if live:  # a live input's mask is made when its first frame gives the size (live_mask)
        # A network loads beside the stream's opening (its width read from its weights' header):
        # the socket listens at once.
        width = trained_width(estimator, weights)
        tracker = built_beside(build, after_start=True) if width is not None else build()
    else:  # JSON Lines go out as the pairs are estimated: the mask is waited for first
        masked, est = frame_mask_while(build, video, options.mask, info, show_progress=show_progress, lens=lens_choice.image_filter)
        est.set_mask(masked.use)
        tracker = est
    overlay_seconds = time.perf_counter() - clock - lens_choice.seconds  # (--lens auto's fit said apart)
    result = track_stream(video, tracker, out, timeout=options.timeout, max_frames=options.max_frames, show_progress=show_progress,
                          mask=options.mask if live else None, info=info, width=width, lens=lens_choice.image_filter)
    if masked is not None:
        result.meta["mask"] = masked.to_json()
    result.meta["lens"] = lens_choice.to_meta()
    if not is_jsonl(out):
        save_track(result, out)
    return TrackRun(result, masked, overlay_seconds, lens_choice)


def _track_file(video: str, out: str, options: TrackOptions, build: Callable[[], Estimator], lens: str | None, strict: bool, info: VideoInfo | None,
                clock: float, show_progress: bool) -> TrackRun:
    """A file to a track file: the tracking starts once the estimator is built, the overlays still
    being looked for beside it, and starts again if one is found (track_video's ``mask``)."""
    with reading_policy(strict), progress_group(disable=not show_progress):
        lens_choice = choose_lens(lens, video, info)
        pending, est = frame_mask_pending(build, video, options.mask, info, show_progress=show_progress, lens=lens_choice.image_filter)
        with pending:
            built = time.perf_counter() - clock
            result = track_video(video, est, max_frames=options.max_frames, show_progress=show_progress, info=info,
                                 rolling_shutter=options.rolling_shutter, mask=pending, lens=lens_choice.image_filter)
    masked = pending.result()
    # The "overlays" figure: the time before the tracking could start (the build, the
    # detection beside it; not --lens auto's fit, said apart), and the time the tracking then
    # lost to the detection (its end waiting for it, a pass discarded for an overlay found);
    # "track" is the kept pass.
    overlay_seconds = built - lens_choice.seconds + result.meta["overlay_wait_seconds"] + result.meta["overlay_lost_seconds"]
    result.meta["mask"] = masked.to_json()
    result.meta["lens"] = lens_choice.to_meta()  # the pairs are the undistorted frames' (its camera: docs/guide/track.md)
    save_track(result, out)
    return TrackRun(result, masked, overlay_seconds, lens_choice)
