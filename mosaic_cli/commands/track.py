"""``mosaic track VIDEO -o OUT.json``: the pairwise homographies themselves."""

from __future__ import annotations

import concurrent.futures
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape  # typer renders help as rich markup: '[plot]' would vanish

from mosaic_cli.atomic import check_writable
from mosaic_cli.commands.options import (
    INPUT_OUTPUT,
    Device,
    EstimatorName,
    LensOption,
    Mask,
    MaxFrames,
    Strict,
    Threads,
    Timeout,
    Weights,
    WorkWidth,
    mask_options,
    overlay_detect_option,
    quiet_option,
    use_threads,
)
from mosaic_cli.errors import BadInput, install_hint, warn
from mosaic_cli.estimators import DEFAULT_ESTIMATOR, Estimator, plan_estimator
from mosaic_cli.live.loading import built_beside, trained_width
from mosaic_cli.live.source import DEFAULT_TIMEOUT, is_live_source
from mosaic_cli.live.track import is_jsonl, track_stream
from mosaic_cli.overlay import check_mask_file, frame_mask_pending, frame_mask_while
from mosaic_cli.progress import console, progress_group
from mosaic_cli.track import TrackOptions, save_track, track_video
from mosaic_cli.video import probe
from mosaic_cli.video.reader import reading_policy

OverlayDetect = overlay_detect_option("estimation")
# Once track's own flags, now the estimator's settings (-e lstm:patches=5) on every command alike.
MovedPatches = Annotated[int | None, typer.Option("--patches", hidden=True)]
MovedResetEvery = Annotated[int | None, typer.Option("--reset-every", hidden=True)]
MovedRefine = Annotated[str | None, typer.Option("--refine", hidden=True)]
MovedChunk = Annotated[int | None, typer.Option("--chunk", hidden=True)]


def refuse_moved_settings(estimator: str | None, given: dict) -> None:
    """One line for a flag that became an estimator setting, naming how it is written now."""
    for key, value in given.items():
        if value is not None:
            name = (estimator or DEFAULT_ESTIMATOR).split(":")[0]
            raise BadInput(f"--{key} is an estimator setting now: -e {name}:{key}={value}")
Quiet = quiet_option("No progress bar.")


def track(
    video: Annotated[str, typer.Argument(help="Video file (mp4, mov, mkv, avi, ...), folder of numbered images, - (standard input) or a stream URL (udp://, tcp://, rtp://, rtsp://, srt://, http(s)://).")],
    out: Annotated[str, typer.Option("-o", "--out", help="Output .json (documented format), .npy (pairwise array), or .jsonl / - (standard output): JSON Lines, one pair a line as it is estimated.", rich_help_panel=INPUT_OUTPUT)],
    estimator: EstimatorName = None,
    work_width: WorkWidth = None,
    weights: Weights = None,
    device: Device = "auto",
    patches: MovedPatches = None,
    reset_every: MovedResetEvery = None,
    refine: MovedRefine = None,
    chunk: MovedChunk = None,
    threads: Threads = None,
    mask: Mask = None,
    overlay_detect: OverlayDetect = True,
    max_frames: MaxFrames = None,
    strict: Strict = False,
    timeout: Timeout = DEFAULT_TIMEOUT,
    quiet: Quiet = False,
    lens: LensOption = None,
    rolling_shutter: Annotated[str, typer.Option("--rolling-shutter", help="Also each row band's motion and correction (a rolling shutter's wobble) in the track file's \"rolling_shutter\" block: auto (readout estimated; a global shutter reads 0, no motion written), off, or the readout as a fraction of the frame interval (0..1). .json output only.", rich_help_panel=INPUT_OUTPUT)] = "off",
    plot: Annotated[Path | None, typer.Option("--plot", help="Also draw each pair's confidence over time, failed pairs marked, to "
                                              f"this PNG (needs matplotlib: {escape(install_hint('plot'))}).",
                                              rich_help_panel=INPUT_OUTPUT)] = None,
) -> None:
    """Estimate the homography between every pair of consecutive frames.

    pairwise[t] maps pixel (x, y) of frame t (OpenCV pixel centres, full resolution) to frame t+1.
    """
    from mosaic_cli.estimators.lens import parse_lens_option, undistorting
    from mosaic_cli.estimators.rolling import parse_rolling_shutter
    from mosaic_cli.plots import check_plot_request

    check_plot_request(plot)  # before any long work
    refuse_moved_settings(estimator, {"patches": patches, "reset-every": reset_every, "refine": refine, "chunk": chunk})
    options = TrackOptions(max_frames=max_frames, threads=threads, timeout=timeout, mask=mask_options(mask, overlay_detect),
                           rolling_shutter=rolling_shutter)
    if parse_rolling_shutter(rolling_shutter) != "off" and (is_live_source(video) or is_jsonl(out) or not out.lower().endswith(".json")):
        raise BadInput("--rolling-shutter writes its block to a .json track file: not with .npy, JSON Lines or a live input")
    if not is_jsonl(out):
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
    build = plan_estimator(estimator, work_width=work_width, weights=str(weights) if weights else None, device=device)
    use_threads(options.threads)
    masked = None
    clock = time.perf_counter()
    if live or is_jsonl(out):
        tracker: Estimator | concurrent.futures.Future
        width = None
        # --lens: a live input's frames undistorted as they arrive (live/source.py), a file's as decoded
        with undistorting(lens, video, info, live=live) as lens_choice:
            if live:  # a live input's mask is made when its first frame gives the size (live_mask)
                # A network loads beside the stream's opening (its width read from its weights' header):
                # the socket listens at once.
                width = trained_width(estimator, str(weights) if weights else None)
                tracker = built_beside(build, after_start=True) if width is not None else build()
            else:  # JSON Lines go out as the pairs are estimated: the mask is waited for first
                masked, est = frame_mask_while(build, video, options.mask, info, show_progress=not quiet)
                est.set_mask(masked.use)
                tracker = est
            overlay_seconds = time.perf_counter() - clock
            result = track_stream(video, tracker, out, timeout=options.timeout, max_frames=options.max_frames, show_progress=not quiet,
                                  mask=options.mask if live else None, info=info, width=width)
            if masked is not None:
                result.meta["mask"] = masked.to_json()
            result.meta["lens"] = lens_choice.to_meta()
        if not is_jsonl(out):
            save_track(result, out)
    else:
        # The tracking starts once the estimator is built, the overlays still being looked for
        # beside it, and starts again if one is found (track_video's ``mask``).
        with reading_policy(strict), undistorting(lens, video, info) as lens_choice, progress_group(disable=quiet):
            pending, est = frame_mask_pending(build, video, options.mask, info, show_progress=not quiet)
            with pending:
                built = time.perf_counter() - clock
                result = track_video(video, est, max_frames=options.max_frames, show_progress=not quiet, info=info,
                                     rolling_shutter=options.rolling_shutter, mask=pending)
        masked = pending.result()
        # The "overlays" figure: the time before the tracking could start (the build, the
        # detection beside it), and the time the tracking then lost to the detection (its end
        # waiting for it, a pass discarded for an overlay found); "track" is the kept pass.
        overlay_seconds = built + result.meta["overlay_wait_seconds"] + result.meta["overlay_lost_seconds"]
        result.meta["mask"] = masked.to_json()
        result.meta["lens"] = lens_choice.to_meta()  # the pairs are the undistorted frames' (its camera: docs/guide/track.md)
        save_track(result, out)
    if plot is not None:
        from mosaic_cli.plots import write_track_plot

        write_track_plot(plot, result.confidence, result.info.fps, paths=result.paths)
    where = "standard output" if out == "-" else out
    if not len(result.pairwise):
        # One frame: nothing to track, which is not an error (the output is a valid empty
        # track), but no confidence either: said even with -q.
        warn(f"{video} has only {result.frames} frame: no frame pair to track; {where} holds an empty track")
    if not quiet:
        if masked is not None and masked.use is not None:
            console.print(masked.describe())
        elif masked is None and result.meta["mask"]["excluded"] > 0:
            console.print(f"{100 * result.meta['mask']['excluded']:.1f}% of the frame masked (--mask)")
        if len(result.pairwise):
            import numpy as np

            console.print(f"{result.frames} frames, {result.meta['ms_per_frame']:.1f} ms/frame, "
                          f"median confidence {float(np.median(result.confidence)):.2f} -> {where} "
                          f"(overlays {overlay_seconds:.1f} s, track {result.meta['seconds']:.1f} s)")
            if "lens" in result.meta and result.meta["lens"]["source"] != "none":
                console.print(lens_choice.describe())
