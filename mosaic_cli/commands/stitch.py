"""``mosaic stitch VIDEO -o PANO.png``: a streaming panorama with drift control."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from mosaic_cli.cli import app
from mosaic_cli.estimators import DEFAULT_ESTIMATOR, make_estimator
from mosaic_cli.progress import console


@app.command()
def stitch(
    video: str = typer.Argument(..., help="Video file, folder of numbered images, - (standard input) or a stream URL (udp://, tcp://, rtp://, rtsp://, srt://, http(s)://)."),
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
    mask: Path | None = typer.Option(None, "--mask", help="Image (the video's size or aspect): white = use, black = ignore, e.g. burned-in overlays the detector misses."),
    overlay_detect: bool = typer.Option(True, "--overlay-detect/--no-overlay-detect", help="Find burned-in logos, text and letterbox bars (fixed in the frame while the ground moves) and keep them out of estimation and the panorama."),
    start: int = typer.Option(0, "--start", help="Skip this many frames first."),
    max_frames: int | None = typer.Option(None, "--max-frames", help="Stop after this many frames."),
    strict: bool = typer.Option(False, "--strict", help="A video that decodes to fewer frames than its container announces (truncated, damaged) is an error, not a warning."),
    live: bool = typer.Option(False, "--live", help="Stitch as frames arrive (implied by a live input), with a growing --preview."),
    preview: Path | None = typer.Option(None, "--preview", help="--live: rewrite this PNG/JPEG preview of the panorama so far (atomically) every --every seconds."),
    every: float = typer.Option(2.0, "--every", help="--live: seconds between two previews."),
    timeout: float = typer.Option(10.0, "--timeout", help="Live input: end the run when the stream sends nothing for this many seconds."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars."),
    telemetry: str | None = typer.Option(None, "--telemetry", help="GPS log to lay the mosaic on the map: DJI .SRT, .gpx, .csv, MISB .klv (or a video holding one); 'none' ignores a track inside the video. Default: a subtitle (SRT) or KLV track inside the video, if any."),
    hfov: float | None = typer.Option(None, "--hfov", help="Camera's horizontal field of view, degrees (when the telemetry lacks focal_len / HFOV)."),
    telemetry_offset: float = typer.Option(0.0, "--telemetry-offset", help="Seconds added to the telemetry's times to match the video's."),
    footprints: Path | None = typer.Option(None, "--footprints", help="With telemetry: write every keyframe's ground footprint and the flight track (GeoJSON, WGS84)."),
) -> None:
    """Stitch a drone flight into one panorama (PNG/JPEG/TIFF by extension)."""
    # Imported here: scipy.optimize takes seconds to import, and every command pays for cli imports.
    from mosaic_cli.overlay import MaskOptions
    from mosaic_cli.stitch import CanvasOptions, ComposeOptions, KeyframeOptions, RegistrationOptions, StitchOptions
    from mosaic_cli.stitch import stitch as run_stitch
    from mosaic_cli.stitch.output import check_outputs

    options = StitchOptions(
        keyframes=KeyframeOptions(new_ground=_fraction("--overlap", overlap)),
        registration=RegistrationOptions(enabled=drift_control, max_loop_pairs=max_loop_pairs),
        canvas=CanvasOptions(reference=reference, max_size=max_size or None),
        compose=ComposeOptions(blend=blend, seam=seam, exposure=exposure),
        mask=MaskOptions(file=mask, detect=overlay_detect),
        start=start,
        max_frames=max_frames,
        georef=_georef_options(telemetry, hfov, telemetry_offset, footprints),
    )
    options.keyframes.force_overlap = min(options.keyframes.force_overlap, options.keyframes.new_ground)
    # Output and option checks come before the estimator is built (a learned one loads weights).
    check_outputs(out, transforms, options.canvas.max_size)
    from mosaic_cli.live.source import is_live_source
    from mosaic_cli.stitch.live import PreviewOptions, stitch_live

    live = live or is_live_source(video) or preview is not None
    preview_options = PreviewOptions(preview, every)
    if live:
        from mosaic_cli.errors import BadInput

        if timeout <= 0:
            raise BadInput(f"--timeout must be positive, got {timeout}")
        preview_options.validate(out)
    info = None
    if not is_live_source(video):  # the input's one probe, passed down
        from mosaic_cli.video import probe

        info = probe(video)
    if mask is not None and info is not None:  # a bad --mask fails before the estimator loads its weights
        from mosaic_cli.overlay import load_mask

        load_mask(mask, info.source_size)
    est = make_estimator(estimator, work_width=work_width, weights=str(weights) if weights else None, device=device)
    from mosaic_cli.video.reader import reading_policy

    if live:
        result = stitch_live(video, out, est, options, transforms=transforms, preview=preview_options, timeout=timeout,
                             show_progress=not quiet, info=info)
    else:
        with reading_policy(strict):
            result = run_stitch(video, out, est, options, transforms=transforms, show_progress=not quiet, info=info)
    if not quiet:
        r = result.registration
        loops = f", {r.loops - r.loops_dropped} loop closures" if drift_control else ""
        if result.mask is not None and result.mask.use is not None:
            console.print(result.mask.describe())
        used = sum(len(p.transforms) for p in result.panoramas)
        console.print(f"{result.frames} frames -> {used} keyframes{loops}, {result.frames_per_second:.1f} fr/s")
        for p in result.panoramas:
            joined = f" ({p.segments} segments joined)" if p.segments > 1 else ""
            console.print(f"  {p.canvas_size[0]}x{p.canvas_size[1]} panorama of {len(p.transforms)} keyframes{joined} -> {p.path}")
        on_ground = [(p.path, p.georef) for p in result.panoramas if p.georef is not None]
        if on_ground:
            console.print(on_ground[0][1].telemetry.summary())
        for path, georef in on_ground:
            console.print(georef.summary() + (f" ({path})" if len(result.panoramas) > 1 else ""))
    # Said even with -q: nothing leaves the panorama silently.
    for line in _notices(video, result):
        print(f"mosaic: warning: {line}", file=sys.stderr)


def _notices(video: Path, result) -> list[str]:
    """A line for each panorama beyond the first and for frames placed nowhere."""
    lines = []
    extra = result.panoramas[1:]
    if extra:
        firsts = ", ".join(f"frame {p.transforms[0][0]} -> {p.path}" for p in extra)
        lines.append(
            f"{len(extra)} part(s) of the flight registered with no other and went to panoramas of their own: {firsts}"
        )
    if result.georef is not None:
        for p in extra:
            if p.georef is None:
                lines.append(f"{p.path}: the telemetry gives its keyframes no position: a plain panorama, not georeferenced")
    if result.dropped:
        if result.photos:
            from mosaic_cli.video.reader import _folder_images

            names = _folder_images(Path(video))
            for index, why in result.dropped:
                lines.append(f"photo {names[index].name} not used: {why}")
        else:
            lines.append(f"{len(result.dropped)} frame(s) placed nowhere (the flight was lost there): frames {_ranges([i for i, _ in result.dropped])}")
    return lines


def _ranges(indices: list[int]) -> str:
    runs = []
    for i in sorted(indices):
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


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
