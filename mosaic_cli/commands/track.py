"""``mosaic track VIDEO -o OUT.json``: the pairwise homographies themselves."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape  # typer renders help as rich markup: '[plot]' would vanish

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
)
from mosaic_cli.errors import BadInput, install_hint, warn
from mosaic_cli.estimators import DEFAULT_ESTIMATOR
from mosaic_cli.live.source import DEFAULT_TIMEOUT
from mosaic_cli.progress import console
from mosaic_cli.track import TrackOptions

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
    from mosaic_cli.plots import check_plot_request
    from mosaic_cli.track_pipeline import track as run_track

    check_plot_request(plot)  # before any long work
    refuse_moved_settings(estimator, {"patches": patches, "reset-every": reset_every, "refine": refine, "chunk": chunk})
    options = TrackOptions(max_frames=max_frames, threads=threads, timeout=timeout, mask=mask_options(mask, overlay_detect),
                           rolling_shutter=rolling_shutter)
    run = run_track(video, out, options, estimator=estimator, work_width=work_width, weights=str(weights) if weights else None,
                    device=device, lens=lens, strict=strict, show_progress=not quiet)
    result, masked, overlay_seconds, lens_choice = run.result, run.masked, run.overlay_seconds, run.lens
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
                          f"({f'lens {lens_choice.seconds:.1f} s, ' if lens_choice.seconds else ''}"
                          f"overlays {overlay_seconds:.1f} s, track {result.meta['seconds']:.1f} s)")
            if "lens" in result.meta and result.meta["lens"]["source"] != "none":
                console.print(lens_choice.describe())
