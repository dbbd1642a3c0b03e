"""``mosaic stitch VIDEO -o PANO.png``: a streaming panorama with drift control."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Annotated

import typer

from mosaic_cli.commands.options import (
    DRIFT_CONTROL,
    INPUT_OUTPUT,
    LIVE,
    MACHINE,
    OUTPUT_QUALITY,
    TELEMETRY,
    Device,
    EstimatorName,
    LensOption,
    Mask,
    MaxFrames,
    Strict,
    Timeout,
    Weights,
    WorkWidth,
    mask_options,
    overlay_detect_option,
    quiet_option,
)
from mosaic_cli.errors import BadInput
from mosaic_cli.live.source import DEFAULT_TIMEOUT
from mosaic_cli.progress import console
from mosaic_cli.video.reader import reading_policy

# --fill-holes fills holes up to this share of the covered panorama: a masked logo's (under 1%),
# never a gap between flight lines.
FILL_HOLES_SHARE = 0.01
OverlayDetect = overlay_detect_option("estimation and the panorama")
Quiet = quiet_option("No progress bars.")


def stitch(
    videos: Annotated[list[str], typer.Argument(help="Video file, folder of numbered images, - (standard input) or a stream URL (udp://, tcp://, rtp://, rtsp://, srt://, http(s)://). Several flights (videos, photo folders, or a folder of them) make one map.", metavar="VIDEO...", show_default=False)],
    out: Annotated[str | None, typer.Option("-o", "--out", help="Panorama: .png, .tif/.tiff (with transparency) or .jpg/.jpeg; with telemetry a map: .tif (Cloud Optimized GeoTIFF), .kmz (Google Earth), DIR/ (web tiles, {z}/{x}/{y}.png), .pmtiles or .mbtiles.", rich_help_panel=INPUT_OUTPUT, show_default="required")] = None,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Read the input's metadata and print it, stitch nothing: each photo's GPS, height, attitude, field of view and camera (EXIF, DJI XMP); a video's size, rate and telemetry.", rich_help_panel=INPUT_OUTPUT)] = False,
    transforms: Annotated[Path | None, typer.Option("--transforms", help="Also write each used frame's homography (frame -> panorama pixels) as JSON.", rich_help_panel=INPUT_OUTPUT)] = None,
    start: Annotated[int, typer.Option("--start", help="Skip this many frames first.", rich_help_panel=INPUT_OUTPUT)] = 0,
    max_frames: MaxFrames = None,
    strict: Strict = False,
    estimator: EstimatorName = None,
    work_width: WorkWidth = None,
    weights: Weights = None,
    device: Device = "auto",
    drift_control: Annotated[bool, typer.Option("--drift-control/--no-drift-control", help="Register revisited ground and refine all placements jointly.", rich_help_panel=DRIFT_CONTROL)] = True,
    max_loop_pairs: Annotated[int | None, typer.Option("--max-loop-pairs", help="At most this many loop registrations (bounds drift-control cost).", rich_help_panel=DRIFT_CONTROL, show_default="300; a photo folder: 3 a photo, at least 300")] = None,
    overlap: Annotated[float, typer.Option("--overlap", help="A new keyframe is due when its overlap with the last one drops below this.", rich_help_panel=DRIFT_CONTROL)] = 0.6,
    reference: Annotated[str, typer.Option("--reference", help="Frame the panorama is drawn in: first, middle or a frame number.", rich_help_panel=OUTPUT_QUALITY)] = "middle",
    max_size: Annotated[int, typer.Option("--max-size", help="Longest side of the panorama in pixels: a larger one is scaled down, said in one line. 0: every pixel (memory does not grow with the panorama).", rich_help_panel=OUTPUT_QUALITY)] = 0,
    gsd: Annotated[str | None, typer.Option("--gsd", help="A map's ground resolution, as 5cm, 0.05m or 50mm (with telemetry): the map is drawn no finer than this.", rich_help_panel=OUTPUT_QUALITY, show_default="the footage's own")] = None,
    blend: Annotated[str, typer.Option("--blend", help="multiband, feather or none.", rich_help_panel=OUTPUT_QUALITY)] = "multiband",
    seam: Annotated[str, typer.Option("--seam", help="Seam finder: dp, graphcut, voronoi or none.", rich_help_panel=OUTPUT_QUALITY)] = "dp",
    exposure: Annotated[str, typer.Option("--exposure", help="Exposure compensation: gain-blocks, gain or none.", rich_help_panel=OUTPUT_QUALITY)] = "gain-blocks",
    rolling_shutter: Annotated[str | None, typer.Option("--rolling-shutter", help="Draw a rolling-shutter camera's frames row band by row band, each where it belongs (not smeared or doubled): auto (readout estimated from the video; global-shutter footage is left alone), off, or the sensor readout as a fraction of the frame interval (0..1).", rich_help_panel=OUTPUT_QUALITY, show_default="auto for a video file; off for photo folders and live input")] = None,
    fill_holes: Annotated[bool, typer.Option("--fill-holes", help="Fill small interior transparent holes (ground under a masked overlay that no frame saw) from their surroundings, for a closed picture; holes at the panorama's border stay transparent.", rich_help_panel=OUTPUT_QUALITY)] = False,
    mask: Mask = None,
    overlay_detect: OverlayDetect = True,
    telemetry: Annotated[str | None, typer.Option("--telemetry", help="GPS log to lay the mosaic on the map: DJI .SRT, .gpx, .csv, MISB .klv (or a video holding one); 'none' ignores a track inside the video or beside it. Default: a subtitle (SRT) or KLV track inside the video, else the DJI log beside it (FLIGHT.SRT), if any.", rich_help_panel=TELEMETRY)] = None,
    hfov: Annotated[float | None, typer.Option("--hfov", help="Camera's horizontal field of view, degrees (when the telemetry lacks focal_len / HFOV).", rich_help_panel=TELEMETRY)] = None,
    telemetry_offset: Annotated[float, typer.Option("--telemetry-offset", help="Seconds added to the telemetry's times to match the video's.", rich_help_panel=TELEMETRY)] = 0.0,
    footprints: Annotated[Path | None, typer.Option("--footprints", help="With telemetry: write every keyframe's ground footprint and the flight track (GeoJSON, WGS84).", rich_help_panel=TELEMETRY)] = None,
    html: Annotated[Path | None, typer.Option("--html", help="With telemetry: write a quick-look page of the map (one offline HTML file: the map, track, footprints, scale bar).", rich_help_panel=TELEMETRY)] = None,
    level_ground: Annotated[bool, typer.Option("--level-ground", help="With telemetry: the ground is level with the take-off point, so each keyframe's height also corrects its scale (drift over long flights). Not over hills or slopes.", rich_help_panel=TELEMETRY)] = False,
    live: Annotated[bool, typer.Option("--live", help="Stitch as frames arrive (implied by a live input), with a growing --preview.", rich_help_panel=LIVE)] = False,
    preview: Annotated[Path | None, typer.Option("--preview", help="--live: rewrite this PNG/JPEG preview of the panorama so far (atomically) every --every seconds.", rich_help_panel=LIVE)] = None,
    every: Annotated[float, typer.Option("--every", help="--live: seconds between two previews.", rich_help_panel=LIVE)] = 2.0,
    timeout: Timeout = DEFAULT_TIMEOUT,
    quiet: Quiet = False,
    lens: LensOption = None,
    workers: Annotated[int | None, typer.Option("--workers", help="Spread the flights' scans (a video of 2,400 frames or more: its segments) and the panorama's tiles over this many local worker processes (Dask; the cluster extra).", rich_help_panel=MACHINE, show_default="none: all in this process")] = None,
    scheduler: Annotated[str | None, typer.Option("--scheduler", help="Use a running Dask cluster (tcp://HOST:PORT) whose workers share this machine's disk.", rich_help_panel=MACHINE)] = None,
) -> None:
    """Stitch a drone flight, or several, into one panorama or map (PNG/JPEG/TIFF by extension)."""
    from mosaic_cli.stitch.flights import expand_flights

    flights = expand_flights(videos) if len(videos) > 1 or Path(videos[0]).is_dir() else list(videos)
    video = flights[0]
    if len(flights) > 1 and (dry_run or live or preview is not None or any(f == "-" or "://" in f for f in flights)):
        raise BadInput("several flights are stitched from files: --dry-run, --live and live inputs take one flight")
    if dry_run:
        _dry_run(video)
        return
    if out is None:
        raise BadInput("-o/--out is required (the panorama or map to write), unless --dry-run")
    # Imported here: scipy.optimize takes seconds to import, and every command pays for cli imports.
    from mosaic_cli.estimators.lens import choose_lens
    from mosaic_cli.live.source import is_live_source
    from mosaic_cli.stabilize.rolling import bridged_bands, parse_rolling_shutter
    from mosaic_cli.stitch import CanvasOptions, ComposeOptions, KeyframeOptions, RegistrationOptions, StitchOptions
    from mosaic_cli.stitch import stitch as run_stitch
    from mosaic_cli.stitch.canvas import parse_distance
    from mosaic_cli.stitch.cluster import ClusterOptions
    from mosaic_cli.stitch.live import PreviewOptions, stitch_live

    options = StitchOptions(
        estimator=estimator,
        work_width=work_width,
        weights=str(weights) if weights else None,
        device=device,
        keyframes=KeyframeOptions(new_ground=overlap),
        registration=RegistrationOptions(enabled=drift_control, max_loop_pairs=max_loop_pairs),
        canvas=CanvasOptions(reference=reference, max_size=max_size or None, gsd=parse_distance(gsd) if gsd is not None else None),
        compose=ComposeOptions(blend=blend, seam=seam, exposure=exposure, fill_holes=FILL_HOLES_SHARE if fill_holes else 0.0),
        mask=mask_options(mask, overlay_detect),
        start=start,
        max_frames=max_frames,
        georef=_georef_options(telemetry, hfov, telemetry_offset, footprints, level_ground, html),
        timeout=timeout,
        rolling_shutter="off" if rolling_shutter is None else rolling_shutter,
        cluster=ClusterOptions(workers, scheduler),
    )
    live = live or is_live_source(video) or preview is not None
    if live and (workers is not None or scheduler is not None):
        raise BadInput("--workers and --scheduler stitch files: not with --live or a live input")
    if live and rolling_shutter is not None and parse_rolling_shutter(rolling_shutter) != "off":
        raise BadInput("--rolling-shutter needs the whole video: not with --live or a live input")
    if rolling_shutter is None and not live and not Path(video).is_dir() and len(flights) == 1:  # the default: a video file's rows are checked
        options = dataclasses.replace(options, rolling_shutter="auto")
    lens_choice = None
    # The library checks the input and the outputs, then builds the estimator (a learned one loads weights).
    if live:
        # --lens: a live input's frames undistorted as they arrive (live/source.py); auto only on a file
        lens_choice = choose_lens(lens, video, live=is_live_source(video))
        result = stitch_live(video, out, options=options, transforms=transforms, preview=PreviewOptions(preview, every),
                             show_progress=not quiet, lens=lens_choice.image_filter)
    elif len(flights) > 1:
        from mosaic_cli.stitch.flights import stitch_flights

        if lens is not None and lens != "none":
            raise BadInput("--lens applies to one flight at a time: stitch flights of one camera, each undistorted, or without --lens")
        with reading_policy(strict):
            result = stitch_flights(flights, out, options=options, transforms=transforms, show_progress=not quiet)
    else:
        with reading_policy(strict):
            lens_choice = choose_lens(lens, video)  # the panorama: a pinhole view of the ground
            result = run_stitch(video, out, options=options, transforms=transforms, show_progress=not quiet,
                                info=lens_choice.info, lens=lens_choice.image_filter)
    if not quiet:
        r = result.registration
        loops = f", {r.loops - r.loops_dropped} loop closures" if drift_control else ""
        if result.mask is not None and result.mask.use is not None:
            console.print(result.mask.describe())
        used = sum(len(p.transforms) for p in result.panoramas)
        stages = ", ".join(f"{name} {seconds:.1f} s" for name, seconds in result.seconds.items())
        console.print(f"{result.frames} frames -> {used} keyframes{loops}, {result.frames_per_second:.1f} fr/s ({stages})")
        if result.photos and result.frames:
            console.print(f"{result.pairs_tried} photo pairs matched, {result.pairs_tried / result.frames:.1f} per photo")
        for p in result.panoramas:
            joined = f" ({p.segments} segments joined)" if p.segments > 1 else ""
            console.print(f"  {p.canvas_size[0]}x{p.canvas_size[1]} panorama of {len(p.transforms)} keyframes{joined} -> {p.path}")
        for line in _flight_lines(result):
            console.print(line)
        on_ground = [(p.path, p.georef) for p in result.panoramas if p.georef is not None]
        if on_ground:
            console.print(on_ground[0][1].telemetry.summary())
        for path, georef in on_ground:
            console.print(georef.summary() + (f" ({path})" if len(result.panoramas) > 1 else ""))
        if result.rolling is not None:
            rs = result.rolling
            said = f"readout {rs.readout:.2f}" + (" (estimated)" if rs.estimated else "")
            console.print(f"rolling shutter: {said}, " + ("each row band drawn where it belongs" if rs.applied else "a global shutter: left alone")
                          + bridged_bands(rs.bridged))
        if lens_choice is not None and lens_choice.source != "none":
            console.print(lens_choice.describe())
        if fill_holes:  # the last line: what the panorama holds that no frame showed
            console.print(f"--fill-holes: {sum(p.filled for p in result.panoramas)} pixels of interior holes filled")
    # Said even with -q: nothing leaves the panorama silently.
    for line in _notices(flights, result):
        print(f"mosaic: warning: {line}", file=sys.stderr)


def _flight_lines(result) -> list[str]:
    """Several flights: one line each, its frames (photos) and the panoramas its keyframes went into."""
    lines = []
    for f in result.flights:
        into = [str(p.path) for p in result.panoramas if any(f.holds(i) for i, _ in p.transforms)]
        unit = "photos" if result.photos else "frames"
        lines.append(f"  flight {Path(f.name).name}: {f.frames} {unit} -> {', '.join(into) if into else 'no panorama'}")
    return lines


def _notices(videos: list[str] | str | Path, result) -> list[str]:
    """A line for a flight in several panoramas (which file holds what), for a panorama that
    ``--max-size``, ``--gsd`` or JPEG's limit scaled down, and for frames or photos placed nowhere."""
    lines = []
    flights = getattr(result, "flights", [])
    video = videos[0] if isinstance(videos, list) else videos
    names: dict[int, str] | list[str] | None = None
    if result.photos and flights:  # each photo by its folder and name, in the one count of the flights
        names = {f.start + i: f"{Path(f.name).name}/{name}" for f in flights for i, name in enumerate(_photo_names(Path(f.name)))}
    elif result.photos:
        names = _photo_names(Path(video))
    several = len(result.panoramas) > 1
    if several:
        lines.append(_split_notice(result.panoramas, names, flights))
    for p in result.panoramas:
        if p.off_map is not None:
            lines.append(f"{p.path}: {p.off_map}: a plain panorama, not georeferenced")
    for p in result.panoramas:
        if p.georef is not None:
            lines += [f"{p.path}: {w}" if several else w for w in p.georef.warnings]
    for p in result.panoramas:
        if p.shrunk_from is not None:
            (w, h), (W, H) = p.canvas_size, p.shrunk_from
            lines.append(f"{p.path}: scaled down from {W}x{H} to {w}x{h} by {p.shrunk_by}")
    lines += result.metadata_notes
    if result.dropped:
        if names is not None:
            for index, why in result.dropped:
                lines.append(f"photo {names[index]} not used: {why}")
        else:
            dropped = _runs_of(sorted(i for i, _ in result.dropped))
            lines.append(f"{len(result.dropped)} frame(s) placed nowhere (the flight was lost there): frames {_frame_runs(dropped, flights)}")
    return lines


def _photo_names(video: Path) -> list[str]:
    """The folder's photos by index, as the scan read them (name order)."""
    from mosaic_cli.video.reader import folder_images

    return [p.name for p in folder_images(Path(video))]


def _split_notice(panoramas, photo_names: list[str] | dict[int, str] | None, flights=()) -> str:
    """``the photos make 2 panoramas that no registration joins: pano.png holds 17 photos
    (A.jpg, B.jpg, C.jpg, ..., Q.jpg); pano-2.png holds 1 photo (R.jpg)``: the files in the
    order written (largest first), each with the photos (names) or frames (indices) it holds."""
    parts = []
    for p in panoramas:
        if photo_names is not None:
            held = [photo_names[i] for a, b in p.spans for i in range(a, b + 1)]
            parts.append(f"{p.path} holds {_count(p.size, 'photo')} ({_abridged(held)})")
        else:
            parts.append(f"{p.path} holds {_count(p.size, 'frame')} ({_frame_runs(p.spans, flights)})")
    what = "photos" if photo_names is not None else "flight"
    return f"the {what} make{'' if photo_names is not None else 's'} {len(panoramas)} panoramas that no registration joins: " + "; ".join(parts)


def _frame_runs(runs: list[tuple[int, int]], flights=()) -> str:
    """Inclusive runs of frame numbers as the user reads them: ``0-899, 950``; with several
    flights, each run in its own flight's numbers: ``f1.mp4 0-899, f2.mp4 0-420``."""
    said = []
    for a, b in runs:
        span = next((f for f in flights if f.holds(a)), None)
        name, a, b = ("", a, b) if span is None else (f"{Path(span.name).name} ", a - span.start, b - span.start)
        said.append(f"{name}{a}" if a == b else f"{name}{a}-{b}")
    return ", ".join(said)


def _runs_of(indices: list[int]) -> list[tuple[int, int]]:
    runs: list[list[int]] = []
    for i in indices:
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return [(a, b) for a, b in runs]


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _abridged(names: list[str], most: int = 5) -> str:
    """A few names in full, a long list as its first three, ... and its last."""
    return ", ".join(names) if len(names) <= most else ", ".join([*names[:3], "...", names[-1]])


def _georef_options(telemetry: str | None, hfov: float | None, offset: float, footprints: Path | None, level_ground: bool = False,
                    html: Path | None = None):
    """``--telemetry FILE|none``, ``--hfov``, ``--telemetry-offset``, ``--footprints``,
    ``--level-ground``, ``--html``; None: no georeferencing (``--telemetry none``)."""
    from mosaic_cli.errors import BadInput
    from mosaic_cli.geo.georef import GeorefOptions

    options = GeorefOptions(telemetry=Path(telemetry) if telemetry else None, hfov=hfov, offset=offset, footprints=footprints,
                            level_ground=level_ground, html=html)
    if telemetry is not None and telemetry.strip().lower() == "none":
        if wanted := options.without_telemetry():
            raise BadInput(f"{wanted[0]} needs telemetry (--telemetry none was given)")
        return None
    return options


def _dry_run(video: str) -> None:
    """``--dry-run``: what the input says of itself, one line per photo (or the video's probe and
    telemetry), and what a stitch of it can make."""
    from mosaic_cli.geo.stitching import sidecar_log
    from mosaic_cli.telemetry import find_telemetry, read_telemetry
    from mosaic_cli.telemetry.photos import photo_rate, read_photo_tags
    from mosaic_cli.video import probe
    from mosaic_cli.video.folders import folder_images

    info = probe(video)
    if info.is_image_folder:
        tags = [read_photo_tags(p) for p in folder_images(Path(video))]
        for t in tags:
            print(t.describe())
        fixed = sum(t.has_fix for t in tags)
        attitude = sum(t.yaw == t.yaw for t in tags)
        damaged = sum(bool(t.problems) for t in tags)
        cameras = sorted({t.camera or "unknown camera" for t in tags})
        made = "a georeferenced map (-o map.tif, .kmz, tiles)" if fixed else "a plain panorama (no photo has GPS)"
        print(f"{len(tags)} photos ({', '.join(cameras)}): {fixed} with GPS, {attitude} with a yaw, {damaged} with damaged "
                      f"metadata, one every {1.0 / photo_rate(tags):.1f} s: {made}")
        return
    print(f"{video}: {info.source_size[0]}x{info.source_size[1]}, {info.fps:.2f} fps, "
                  f"{info.frame_count if info.frame_count is not None else 'unknown'} frames")
    track = find_telemetry(video, info)
    if track is None and (beside := sidecar_log(video)) is not None:
        try:
            track = read_telemetry(beside)
        except BadInput as exc:  # captions, or a damaged log: a stitch makes a plain panorama beside it
            print(f"telemetry: none inside the video; beside it, {exc}")
            return
    print(f"telemetry: {track.source}, {len(track)} samples, {int(track.has_fix.sum())} with a GPS fix" if track is not None
                  else "telemetry: none inside the video or beside it (--telemetry FILE gives one)")
