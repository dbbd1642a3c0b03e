"""``mosaic stabilize IN OUT``: a steady copy of a shaky video, same frames, rate and audio."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape  # typer renders help as rich markup: '[plot]' would vanish

from mosaic_cli.commands.options import (
    ESTIMATOR,
    INPUT_OUTPUT,
    LIVE,
    OUTPUT_QUALITY,
    SMOOTHING,
    Device,
    EstimatorName,
    LensOption,
    Mask,
    Strict,
    Timeout,
    Weights,
    mask_options,
    overlay_detect_option,
    quiet_option,
)
from mosaic_cli.errors import BadInput, install_hint
from mosaic_cli.live.source import DEFAULT_TIMEOUT
from mosaic_cli.progress import console
from mosaic_cli.video.reader import reading_policy

OverlayDetect = overlay_detect_option("the motion estimate (the output keeps every pixel)")
Quiet = quiet_option("No progress bars or summary.")


def stabilize(
    video: Annotated[str, typer.Argument(help="Input video file, folder of numbered images, - (standard input) or a stream URL (udp://, tcp://, rtp://, rtsp://, srt://, http(s)://).")],
    out: Annotated[str, typer.Argument(help="Output video (.mp4, .mov, .m4v or .mkv), H.264 with the input's audio; with --latency or a live input also - (MPEG-TS on standard output) or a URL (udp://, srt://, tcp://).")],
    smoothing: Annotated[str, typer.Option("--smoothing", help="l1 (L1-optimal camera path) or gaussian.", rich_help_panel=SMOOTHING)] = "l1",
    radius: Annotated[int, typer.Option("--radius", help="Gaussian smoothing radius in frames (sigma = radius / 3).", rich_help_panel=SMOOTHING)] = 30,
    model: Annotated[str, typer.Option("--model", help="Motion model of the correction: tilt (a similarity, plus the pitch and roll shake where the estimates show it), similarity, affine or homography.", rich_help_panel=SMOOTHING)] = "tilt",
    crop: Annotated[str, typer.Option("--crop", help="auto (zoom just enough that no border shows) or the share of "
                                      "width and height to keep, 0.5..1 (borders may then show, filled as --border says).", rich_help_panel=SMOOTHING)] = "auto",
    border: Annotated[str | None, typer.Option("--border", help="Fill of uncovered areas with a fixed --crop: black "
                                               "(default), replicate or reflect.", rich_help_panel=SMOOTHING)] = None,
    crf: Annotated[int, typer.Option("--crf", help="x264 quality, 0 (lossless) .. 51.", rich_help_panel=OUTPUT_QUALITY)] = 18,
    preset: Annotated[str | None, typer.Option("--preset", help="x264 preset (ultrafast .. veryslow).", rich_help_panel=OUTPUT_QUALITY,
                                               show_default="veryfast; live, above 854x480 at 30 fps: ultrafast")] = None,
    warps: Annotated[Path | None, typer.Option("--warps", help="Write the per-frame warps (input -> output pixels) as JSON.", rich_help_panel=INPUT_OUTPUT)] = None,
    compare: Annotated[Path | None, typer.Option("--compare", help="Also write input and output side by side to this video.", rich_help_panel=INPUT_OUTPUT)] = None,
    estimator: EstimatorName = None,
    work_width: Annotated[int | None, typer.Option("--work-width", help="Width the classical estimators (orb, orb-ransac) "
                                                  "work at, pixels (default 640, never wider than the video: more than track and stitch's 320 "
                                                  "because every tracking error shows as shake in a stabilised video). The learned ones (lstm, "
                                                  "cnn) work at the width their weights were trained at: another value is refused.", rich_help_panel=ESTIMATOR)] = None,
    weights: Weights = None,
    device: Device = "auto",
    mask: Mask = None,
    overlay_detect: OverlayDetect = True,
    strict: Strict = False,
    latency: Annotated[float | None, typer.Option("--latency", help="One pass, each frame out at most this many seconds after it came in (a lookahead-bounded L1 path). Default for a live input or output: 1.", rich_help_panel=LIVE)] = None,
    timeout: Timeout = DEFAULT_TIMEOUT,
    rolling_shutter: Annotated[str | None, typer.Option("--rolling-shutter", help="Take out a rolling shutter's wobble (jello): auto (readout estimated from the video; global-shutter footage is left alone), off, or the sensor readout as a fraction of the frame interval (0..1). Each output row is warped by its own correction.", rich_help_panel=SMOOTHING, show_default="auto; off when live or with a latency")] = None,
    quiet: Quiet = False,
    lens: LensOption = None,
    keep_lens: Annotated[bool, typer.Option("--keep-lens", help="With a lens applied (--lens FILE, or auto that finds one): "
                                            "write the lens's look (the warps composed with the lens, one resampling a frame), "
                                            "not the undistorted view; the tracking still works on undistorted frames. "
                                            "Warped by OpenCV on the CPU.", rich_help_panel=INPUT_OUTPUT)] = False,
    plot: Annotated[Path | None, typer.Option("--plot", help="Also draw the camera path before and after (x, y, rotation, scale) "
                                              "and the crop window over time to this PNG (needs matplotlib: "
                                              f"{escape(install_hint('plot'))}).", rich_help_panel=INPUT_OUTPUT)] = None,
) -> None:
    """Stabilise a video: L1-optimal smooth camera path, no black borders by default, audio kept.

    The output has the input's size, frame count and frame rate."""
    from mosaic_cli.estimators.lens import choose_lens
    from mosaic_cli.live.source import is_live_source
    from mosaic_cli.live.stabilize import is_live_request, stabilize_live
    from mosaic_cli.plots import check_plot_request
    from mosaic_cli.stabilize import StabilizeOptions
    from mosaic_cli.stabilize import stabilize as run
    from mosaic_cli.stabilize.rolling import bridged_bands, parse_rolling_shutter

    check_plot_request(plot)  # before any long work
    options = StabilizeOptions(
        estimator=estimator, work_width=work_width, weights=str(weights) if weights else None, device=device,
        smoothing=smoothing, radius=radius, model=model, crop=crop, border=border, crf=crf, preset=preset,
        mask=mask_options(mask, overlay_detect), latency=latency, timeout=timeout,
        rolling_shutter="auto" if rolling_shutter is None else rolling_shutter,
    )
    if is_live_request(video, out, options):
        if keep_lens:
            raise BadInput("--keep-lens renders through the whole video's path: not with --latency or a live input or output")
        if rolling_shutter is not None and parse_rolling_shutter(rolling_shutter) != "off":
            raise BadInput("--rolling-shutter needs the whole video: not with --latency or a live input or output")
        options = dataclasses.replace(options, rolling_shutter="off")
        if plot is not None:
            raise BadInput("--plot needs the whole camera path: not with --latency or a live input or output")
        # --lens: a live input's frames undistorted as they arrive (live/source.py); auto only on a file
        lens_choice = choose_lens(lens, video, live=is_live_source(video))
        live = stabilize_live(video, out, options, warps_out=str(warps) if warps else None,
                              compare=str(compare) if compare else None, show_progress=not quiet, lens=lens_choice.image_filter)
        if not quiet:
            console.print(
                f"{live.frames_in} frames in, {live.frames_out} out -> {'standard output' if out == '-' else out}: "
                f"latency p50 {live.latency(50):.2f} s, p95 {live.latency(95):.2f} s, max {live.latency(100):.2f} s "
                f"(horizon {live.horizon.frames} frames); {live.frames_out / max(live.seconds, 1e-9):.1f} fr/s; "
                f"pairs by {', '.join(f'{name} {n}' for name, n in live.pairs_by.items()) or 'none'}",
                soft_wrap=True,
            )
            if lens_choice.source != "none":
                console.print(lens_choice.describe())
        return
    # The output is the undistorted (pinhole) view: the path and warps are planned on it
    # (--keep-lens: the render composes them with the lens).
    with reading_policy(strict):
        lens_choice = choose_lens(lens, video)
        if keep_lens and lens_choice.lens is not None:
            options = dataclasses.replace(options, keep_lens=lens_choice.lens)
        result = run(video, out, options, warps_out=warps, compare=compare, show_progress=not quiet, lens=lens_choice.image_filter)
    if plot is not None:
        _plot(plot, result)
    if not quiet:
        s = result.seconds
        tightest, at = result.tightest_crop
        console.print(
            f"{result.frames} frames -> {out}: {result.frames / max(s['total'], 1e-9):.1f} fr/s "
            f"(overlays {s['overlays']:.1f} s; track {s['track']:.1f} s, path {s['plan']:.1f} s of it, "
            f"beside the render {s['render']:.1f} s" + (f", rolling shutter {s['rolling']:.1f} s of those" if result.rolling is not None else "")
            + "); "
            f"cropping {result.cropping:.3f} mean, {tightest:.3f} at its tightest (frame {at}, {at / max(result.fps, 1e-9):.1f} s), "
            f"distortion {result.distortion:.3f}, border {100 * result.border:.2f}%"
        )
        if result.rolling is not None:
            rs = result.rolling
            said = f"readout {rs.readout:.2f} ({'estimated' if rs.estimated else 'given'})"
            console.print(f"rolling shutter: {said}, " + ("each row corrected" if rs.applied else "a global shutter: left alone")
                          + bridged_bands(rs.bridged))
        if lens_choice.source != "none":
            said = lens_choice.describe()
            if keep_lens:
                said += ("; --keep-lens: the output keeps the lens's look" if lens_choice.lens is not None
                         else "; --keep-lens: no lens applied, the output as without it")
            console.print(said)
        elif keep_lens:
            console.print("--keep-lens: no lens applied (--lens none), the output as without it")


def _plot(path: Path, result) -> None:
    """``--plot``: the path stabilize planned, before and after, and the crop window."""
    from mosaic_cli.plots import camera_path_series, crop_series, write_stabilize_plot

    before, after = camera_path_series(result.motion, result.views)
    write_stabilize_plot(path, before, after, crop_series(result.warps, result.size), result.fps)
