"""``mosaic simulate [MAP_IMAGE] -o flight.mp4``: a virtual drone flight with exact ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mosaic_cli.commands.options import (
    FLIGHT,
    INPUT_OUTPUT,
    OUTPUT_QUALITY,
    TELEMETRY,
    quiet_option,
)
from mosaic_cli.inputs import parse_size
from mosaic_cli.progress import console

Quiet = quiet_option("No progress bar.")


def simulate(
    out: Annotated[Path, typer.Option("-o", "--out", help="Output video (.mp4); the ground truth goes to <stem>.gt.json beside it.", rich_help_panel=INPUT_OUTPUT)],
    map_image: Annotated[Path | None, typer.Argument(help="Aerial image to fly over (RGBA: cropped to its opaque part). Default: a procedural map.")] = None,
    profile: Annotated[str, typer.Option("--profile", "-p", help="paper, survey, fast, shaky, shaky-tilt, hard, extreme or bursts.", rich_help_panel=FLIGHT)] = "paper",
    frames: Annotated[int, typer.Option("--frames", "-n", help="Number of frames.", rich_help_panel=FLIGHT)] = 300,
    size: Annotated[str, typer.Option("--size", help="Frame size WxH.", rich_help_panel=FLIGHT)] = "1280x720",
    fps: Annotated[float, typer.Option("--fps", help="Frame rate.", rich_help_panel=FLIGHT)] = 30.0,
    seed: Annotated[int, typer.Option("--seed", help="Random seed (path, map, effects).", rich_help_panel=FLIGHT)] = 0,
    crf: Annotated[int | None, typer.Option("--crf", help="H.264 quality (0-51, lower is better). Default: 18, 30 for extreme.", rich_help_panel=OUTPUT_QUALITY)] = None,
    preset: Annotated[str, typer.Option("--preset", help="x264 preset (ultrafast ... veryslow).", rich_help_panel=OUTPUT_QUALITY)] = "medium",
    overlays: Annotated[str | None, typer.Option("--overlays", help="Burn in overlays: logo, timestamp, letterbox, watermark (a translucent white diamond with soft edges), osd (a semi-transparent text box), comma-separated, or all (logo, timestamp, letterbox); watermark:0.6 and osd:0.5 set an opacity. The exact footprint goes to <stem>.mask.png.", rich_help_panel=FLIGHT)] = None,
    bursts: Annotated[str | None, typer.Option("--bursts", help="Every 12-30 frames, 1-3 frames with no motion cue: glare, blur, dark, flat, drop, duplicate (comma-separated), all, or none. Default: the profile's (all for -p bursts, none otherwise). Listed in the ground truth.", rich_help_panel=FLIGHT)] = None,
    rolling_shutter: Annotated[float, typer.Option("--rolling-shutter", help="Sensor readout as a fraction of the frame interval (0..1): row y of frame t sees the camera at t + R*y/h. 0: global shutter. The bands' homographies go to the ground truth.", rich_help_panel=FLIGHT)] = 0.0,
    vibration: Annotated[str | None, typer.Option("--vibration", help="Propeller vibration of the camera, sampled at each row's time: HZ,PX a sinusoid of HZ (5-30 typical) and PX 1280-wide px of translation (and a small rotation); several tones joined by + (12,2+31,1); noise:LO-HI,PX[,DEG] band-limited noise on both shifts (PX RMS) and the rotation (DEG RMS).", rich_help_panel=FLIGHT)] = None,
    lens: Annotated[str | None, typer.Option("--lens", help="See the ground through a lens: K1[,K2][,f=PX] (OpenCV's radial model; focal PX default: about 71 degrees across), fisheye[:K1,...][,f=PX] (equidistant; default about 120 degrees across) or a lens FILE (mosaic, Gyroflow or OpenSfM JSON). The truth stays the pinhole frames' and records the lens.", rich_help_panel=FLIGHT)] = None,
    quiet: Quiet = False,
    telemetry: Annotated[str | None, typer.Option("--telemetry", help="Also write the drone's GPS log beside the video: srt (DJI), gpx, csv or klv (MISB ST 0601); truth in <stem>.geo.json.", rich_help_panel=TELEMETRY)] = None,
    origin: Annotated[str, typer.Option("--origin", help="LAT,LON of the map's centre, when the map carries no geotransform (with --telemetry).", rich_help_panel=TELEMETRY)] = "47.3977,8.5456",
    gsd: Annotated[float, typer.Option("--gsd", help="Metres per map pixel, when the map carries no geotransform (with --telemetry).", rich_help_panel=TELEMETRY)] = 0.05,
    gps_noise: Annotated[float, typer.Option("--gps-noise", help="Horizontal GPS error, RMS metres (correlated over 2 s), with --telemetry.", rich_help_panel=TELEMETRY)] = 3.0,
    gps_dropouts: Annotated[float, typer.Option("--gps-dropouts", help="Fraction of log samples without a fix, with --telemetry.", rich_help_panel=TELEMETRY)] = 0.02,
    baro_bias: Annotated[float, typer.Option("--baro-bias", help="RMS of the barometric height's offset over the flight, metres, with --telemetry.", rich_help_panel=TELEMETRY)] = 0.5,
    telemetry_rate: Annotated[float, typer.Option("--telemetry-rate", help="Log samples per second; 0: one per frame.", rich_help_panel=TELEMETRY)] = 0.0,
) -> None:
    """Render a drone flight over a large aerial image with a virtual nadir camera.

    Profiles: paper (1-2 px/frame, slow heading changes, altitude drift), survey (lawnmower
    lines that revisit the ground), fast (10-20 px/frame), shaky (paper + 3-8 Hz shake),
    shaky-tilt (shaky + 3-8 Hz pitch and roll shake of up to 0.3 degrees: the view shifts and keystones),
    hard (paper + exposure drift, noise, motion blur), extreme (25-60 px/frame, fast yaw turns
    and altitude changes, exposure drift and jumps, noise, motion blur, vignetting, haze,
    low-bitrate H.264), bursts (8-30 px/frame, exposure drift, noise and blur, and every 12-30
    frames 1-3 frames without a motion cue: see --bursts).  Motion is in 1280x720-equivalent px.
    The exact homographies go to <stem>.gt.json: map_to_frame per frame and pairwise t -> t+1.
    """
    from mosaic_cli.simulate import (
        BurstSpec,
        OverlaySpec,
        RollingShutter,
        SimulateOptions,
        check_outputs,
        ground_truth_path,
        parse_lens,
        parse_vibration,
        simulate_flight,
    )
    from mosaic_cli.simulate.telemetry import GpsErrors, TelemetryOptions, prepare_telemetry, write_telemetry

    frame_size = parse_size(size, "--size")
    options = SimulateOptions(profile=profile, frames=frames, size=frame_size, fps=fps, seed=seed, crf=crf,
                              preset=preset, overlays=OverlaySpec.parse(overlays),
                              bursts=BurstSpec.parse(bursts) if bursts is not None else None,
                              rolling=RollingShutter(rolling_shutter, *parse_vibration(vibration)), lens=parse_lens(lens, frame_size))
    log = None
    if telemetry is not None:
        log = TelemetryOptions(format=telemetry, origin=origin, gsd=gsd, rate=telemetry_rate,
                               errors=GpsErrors(rms=gps_noise, dropouts=gps_dropouts, height_bias=baro_bias, seed=seed))
    check_outputs(out, map_image, options)
    if log is not None:  # checked before rendering: a bad option costs nothing
        map_geo = prepare_telemetry(out, map_image, log)
    gt = simulate_flight(out, map_image, options, show_progress=not quiet)
    if log is not None:
        geo = map_geo(gt.map_size)
        written = write_telemetry(out, gt, geo, log.format, log.errors, log.rate or None)
        if not quiet:
            console.print(f"telemetry ({log.format}, {geo.crs}, {geo.gsd:g} m per map pixel) -> {written}")
    if not quiet:
        console.print(
            f"{gt.frames} frames {gt.size[0]}x{gt.size[1]} over {gt.map_name} ({gt.map_size[0]}x{gt.map_size[1]}), "
            f"profile {gt.profile} -> {out}, ground truth -> {ground_truth_path(out)}"
        )
