"""``mosaic stitch VIDEO -o PANO.png``: a streaming panorama with drift control."""

from __future__ import annotations

from pathlib import Path

import typer

from mosaic_cli.cli import app
from mosaic_cli.estimators import DEFAULT_ESTIMATOR, make_estimator
from mosaic_cli.progress import console


@app.command()
def stitch(
    video: Path = typer.Argument(..., help="Video file or folder of numbered images."),
    out: Path = typer.Option(..., "-o", "--out", help="Panorama: .png, .tif/.tiff (with transparency) or .jpg/.jpeg."),
    transforms: Path | None = typer.Option(
        None, "--transforms", help="Also write each used frame's homography (frame -> panorama pixels) as JSON."
    ),
    reference: str = typer.Option("middle", "--reference", help="Frame the panorama is drawn in: first, middle or a frame number."),
    max_size: int = typer.Option(8000, "--max-size", help="Longest side of the panorama in pixels (larger canvases are scaled down); 0: no limit."),
    drift_control: bool = typer.Option(True, "--drift-control/--no-drift-control", help="Register revisited ground and refine all placements jointly."),
    max_loop_pairs: int = typer.Option(300, "--max-loop-pairs", help="At most this many loop registrations (bounds drift-control cost)."),
    overlap: float = typer.Option(0.6, "--overlap", help="A new keyframe is due when its overlap with the last one drops below this."),
    blend: str = typer.Option("multiband", "--blend", help="multiband, feather or none."),
    seam: str = typer.Option("dp", "--seam", help="Seam finder: dp, graphcut, voronoi or none."),
    exposure: str = typer.Option("gain-blocks", "--exposure", help="Exposure compensation: gain-blocks, gain or none."),
    estimator: str | None = typer.Option(None, "--estimator", "-e", help=f"orb, orb-ransac, identity, lstm or cnn. Default: {DEFAULT_ESTIMATOR} (with --weights: the network they hold)."),
    work_width: int = typer.Option(320, "--work-width", help="Width the classical estimators (orb, orb-ransac, identity) work at, pixels; the learned ones work at the size their weights were trained for."),
    weights: Path | None = typer.Option(None, "--weights", help="A trained checkpoint (.safetensors) to run."),
    device: str = typer.Option("auto", "--device", help="auto, cpu or cuda (learned estimators)."),
    start: int = typer.Option(0, "--start", help="Skip this many frames first."),
    max_frames: int | None = typer.Option(None, "--max-frames", help="Stop after this many frames."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars."),
    telemetry: str | None = typer.Option(None, "--telemetry", help="GPS log to lay the mosaic on the map: DJI .SRT, .gpx, .csv, MISB .klv (or a video holding one); 'none' ignores a track inside the video. Default: a subtitle (SRT) or KLV track inside the video, if any."),
    hfov: float | None = typer.Option(None, "--hfov", help="Camera's horizontal field of view, degrees (when the telemetry lacks focal_len / HFOV)."),
    telemetry_offset: float = typer.Option(0.0, "--telemetry-offset", help="Seconds added to the telemetry's times to match the video's."),
    footprints: Path | None = typer.Option(None, "--footprints", help="With telemetry: write every keyframe's ground footprint and the flight track (GeoJSON, WGS84)."),
) -> None:
    """Stitch a drone flight into one panorama (PNG/JPEG/TIFF by extension)."""
    # Imported here: scipy.optimize takes seconds to import, and every command pays for cli imports.
    from mosaic_cli.stitch import CanvasOptions, ComposeOptions, KeyframeOptions, RegistrationOptions, StitchOptions
    from mosaic_cli.stitch import stitch as run_stitch
    from mosaic_cli.stitch.output import check_outputs

    options = StitchOptions(
        keyframes=KeyframeOptions(new_ground=_fraction("--overlap", overlap)),
        registration=RegistrationOptions(enabled=drift_control, max_loop_pairs=max_loop_pairs),
        canvas=CanvasOptions(reference=reference, max_size=max_size or None),
        compose=ComposeOptions(blend=blend, seam=seam, exposure=exposure),
        start=start,
        max_frames=max_frames,
        georef=_georef_options(telemetry, hfov, telemetry_offset, footprints),
    )
    options.keyframes.force_overlap = min(options.keyframes.force_overlap, options.keyframes.new_ground)
    # Output and option checks come before the estimator is built (a learned one loads weights).
    check_outputs(out, transforms, options.canvas.max_size)
    est = make_estimator(estimator, work_width=work_width, weights=str(weights) if weights else None, device=device)
    result = run_stitch(video, out, est, options, transforms=transforms, show_progress=not quiet)
    if not quiet:
        r = result.registration
        loops = f", {r.loops - r.loops_dropped} loop closures" if drift_control else ""
        console.print(
            f"{result.frames} frames -> {len(result.transforms)} keyframes{loops}, "
            f"{result.canvas_size[0]}x{result.canvas_size[1]} canvas, {result.frames_per_second:.1f} fr/s -> {out}"
        )
        if result.georef is not None:
            console.print(result.georef.telemetry.summary())
            console.print(result.georef.summary())


def _georef_options(telemetry: str | None, hfov: float | None, offset: float, footprints: Path | None):
    from mosaic_cli.errors import BadInput
    from mosaic_cli.geo.georef import GeorefOptions

    if telemetry is not None and telemetry.strip().lower() == "none":
        if footprints is not None:
            raise BadInput("--footprints needs telemetry (--telemetry none was given)")
        return None
    options = GeorefOptions(telemetry=Path(telemetry) if telemetry else None, hfov=hfov, offset=offset, footprints=footprints)
    options.validate()
    return options


def _fraction(name: str, value: float) -> float:
    from mosaic_cli.errors import BadInput

    if not 0.05 <= value <= 0.95:
        raise BadInput(f"{name} must be between 0.05 and 0.95, got {value}")
    return value
