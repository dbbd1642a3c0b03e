"""``stabilize``: track the camera, plan a smooth view of it, render that view.

One decode of the input, shared by the tracking and the render (shared_decode.py: each frame
reduced to gray for the tracking, whole for the render, through a ring that covers the camera
path's window), and nothing in memory that grows with its length but the per-frame matrices
(72 bytes a frame):

1. track: the estimator's pairwise homographies, each frame reduced to gray at the estimator's
   width (a thread);
2. plan: the camera motion in the chosen model, smoothed (L1-optimal path or Gaussian) with
   the crop window kept inside every frame; the per-frame warps input -> output.  The L1 path
   is solved a window at a time as the pairs come in (stream.py);
3. render: warp each frame at full resolution, encode with the input's audio, each frame as
   soon as its window is solved: on two cores the tracking runs beside the encoder instead of
   before it.  Where the ring is too small for what the path needs (--smoothing gaussian, long
   runs of failed pairs) the render reads the rest from a second decode of its own.

Burned-in overlays are looked for beside the tracking, which starts once the estimator is
built: its pairs reach the plan (and so the render) only once the mask is settled, and it
starts again from the first frame if an overlay was found (mosaic_cli/overlay/speculate.py),
reading the ring again: no frame leaves it before the mask is settled.
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosaic_cli.atomic import check_writable, write_json
from mosaic_cli.device import check_device
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import Estimator, check_work_width, plan_estimator
from mosaic_cli.geometry.lens import Lens, remap_frame
from mosaic_cli.inputs import DEFAULT_TIMEOUT, check_timeout
from mosaic_cli.overlay import MaskOptions, PendingMask, check_mask_file, frame_mask_pending
from mosaic_cli.overlay.speculate import Gate
from mosaic_cli.progress import progress_group
from mosaic_cli.stabilize.crop import border_fraction, parse_crop
from mosaic_cli.stabilize.metrics import cropping_ratio, distortion, frame_cropping
from mosaic_cli.stabilize.path import MotionModel, motion_model
from mosaic_cli.stabilize.render import BORDERS, YUV_BLACK, KeptLens, Renderer, parse_border, render_yuv
from mosaic_cli.stabilize.rolling import MidTimeFeed, RollingCorrection, RollingProbe, RowWarpLater, parse_rolling_shutter
from mosaic_cli.stabilize.shared_decode import SharedDecode, frame_bytes, ring_frames
from mosaic_cli.stabilize.smoothing import GaussianSmoother, L1Smoother, make_smoother
from mosaic_cli.stabilize.stream import PathFeed
from mosaic_cli.track import TrackResult, track_video
from mosaic_cli.video import VideoInfo, probe
from mosaic_cli.video.lens_filter import ImageFilter
from mosaic_cli.video.stream import VideoStream
from mosaic_cli.video.writer import OUTPUT_SUFFIXES, check_encoder, rewrite_container

# The estimator's default working width.  Stabilising shows every tracking error as shake:
# on shaky 1280x720 flights ORB at 640 px leaves 0.03-0.09 of the shake where 320 px leaves
# 0.03-0.15 (occasional bad fits at 320 px), for about 5 ms more per frame (docs/measurements/stabilize.md).
WORK_WIDTH = 640
PRESET = "veryfast"  # x264's preset unless --preset says otherwise


@dataclass
class StabilizeOptions:
    estimator: str | None = None  # None: DEFAULT_ESTIMATOR, or the network --weights hold
    work_width: int | None = None  # --work-width; None: WORK_WIDTH (classical estimators, never wider than the video)
    weights: str | None = None
    device: str = "auto"
    smoothing: str = "l1"  # or "gaussian"
    radius: int = 30  # gaussian only, frames
    # Of the stabilising correction: tilt (a similarity, plus the camera's pitch and roll shake
    # where the estimates show it: path.perspective_support), similarity, affine or homography.
    model: str = "tilt"
    crop: str | float | None = "auto"  # or the share of width and height kept, 0.5..1
    # What fills uncovered areas: black, replicate or reflect.  None: black with a fixed crop;
    # with --crop auto there are none (replicate keeps the half-pixel rim and the rare frame
    # the zoom limit cannot cover from turning dark).
    border: str | None = None
    crf: int = 18
    preset: str | None = None  # x264's; None: PRESET, or for a live run the one its pixel rate allows (live.stabilize.live_preset)
    # Burned-in overlays and --mask: kept out of the motion estimate only (the output is the
    # whole frame, overlays included, as the input has them).
    mask: MaskOptions = field(default_factory=MaskOptions)
    # One pass, each frame out within this many seconds (mosaic_cli/live/stabilize.py); None:
    # two passes, unless the input or the output is live (then DEFAULT_LATENCY there).
    latency: float | None = None
    timeout: float = DEFAULT_TIMEOUT  # a live input ends when it sends nothing for this long
    rolling_shutter: str | float = "off"  # auto, off or a readout in [0, 1] (stabilize/rolling.py)
    # --keep-lens with a lens applied (--lens FILE, or auto that found one): that lens.  The
    # tracking and the path still see the undistorted frames; the render reads the frames as the
    # lens saw them and writes its look (render.KeptLens).  None: the undistorted view.
    keep_lens: Lens | None = None

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Each flag, by the rule of the stage that uses it (the smoother, the motion model,
        the crop, the renderer, the estimator)."""
        if self.work_width is not None:
            check_work_width(self.work_width)
        check_device(self.device)
        if self.radius < 1:  # checked whichever the smoother: a value no smoother takes is a typo
            raise BadInput(f"--radius must be at least 1, got {self.radius}")
        make_smoother(self.smoothing, self.radius)
        motion_model(self.model)
        parse_crop(self.crop)
        if self.border is not None:
            parse_border(self.border)
        check_encoder(self.crf, self.preset or PRESET)
        if self.latency is not None and not self.latency > 0:
            raise BadInput(f"--latency must be positive, got {self.latency}")
        check_timeout(self.timeout)
        parse_rolling_shutter(self.rolling_shutter)


@dataclass
class StabilizeResult:
    frames: int
    size: tuple[int, int]
    fps: float
    warps: np.ndarray  # (N, 3, 3) input pixels -> output pixels
    # Wall seconds of each stage: "overlays" the time before the tracking could start (the
    # estimator's build, the overlays looked for beside it) and the time the tracking then lost
    # to them (its end waiting for the detection, a pass discarded for an overlay found); "track"
    # the kept tracking pass, "plan" its path's solves, "render" the render beside it from the
    # tracking's start, "rolling" the rolling shutter's share, "total" the whole.
    seconds: dict[str, float] = field(default_factory=dict)
    input_meta: dict | None = None  # set when the input decoded short (see video.reader.Shortfall)
    # The camera path as planned, for --plot: F_{t+1} (frame t+1 -> t, normalised) and each
    # output frame's view in its input frame (see plots.camera_path_series).
    motion: np.ndarray | None = None
    views: np.ndarray | None = None
    rolling: RollingCorrection | None = None  # --rolling-shutter: the readout and each band's correction
    # An overlay was found after the tracking had started without it: the tracking started again
    # (mosaic_cli/overlay/speculate.py); the warps are those of the final mask either way.
    overlay_restart: bool = False

    @property
    def cropping(self) -> float:
        return cropping_ratio(self.warps, self.size)

    @property
    def tightest_crop(self) -> tuple[float, int]:
        """The smallest frame cropping (the most zoomed-in output frame) and that frame's index:
        a mean near 1 hides a turn zoomed to 0.9."""
        per_frame = frame_cropping(self.warps, self.size)
        worst = int(np.argmin(per_frame))
        return float(per_frame[worst]), worst

    @property
    def distortion(self) -> float:
        return distortion(self.warps, self.size)

    @property
    def border(self) -> float:
        """The mean share of the output frame that no input pixel covers."""
        return float(border_fraction(self.warps, self.size).mean())


def stabilize(video: str | Path, out: str | Path, options: StabilizeOptions | None = None,
              warps_out: str | Path | None = None, compare: str | Path | None = None,
              show_progress: bool = True, *, lens: ImageFilter | None = None) -> StabilizeResult:
    """Write a stabilised copy of ``video`` to ``out`` (see the module docstring).  ``lens``:
    every reading of ``video`` through this filter (``--lens``: the tracking, the overlays, the
    rolling shutter's pass and the render see the undistorted view; with ``options.keep_lens``
    the render reads the frames as the lens saw them)."""
    options = options or StabilizeOptions()
    info, plan = check_request(video, out, options, warps_out, compare)
    clock = time.perf_counter()

    assert plan.build is not None  # check_request planned it
    # Rolling shutter: each row band's correction (rolling.py), planned at the render's first
    # frame: `auto`'s probe rides on the tracking pass's first frames, and a rolling shutter
    # found (or a readout given) is measured by a pass of its own beside the tracking.
    mode = parse_rolling_shutter(options.rolling_shutter)
    probe = RollingProbe(info) if mode == "auto" else None
    per_row = RowWarpLater(video, info, mode, BORDERS[plan.renderer.border], YUV_BLACK, show_progress, probe, lens) if mode != "off" else None

    # The path is planned as the pairs come in, and the render follows the plan (stream.py); with
    # a rolling shutter, from the motion between the frames' mid-time poses, the frames the rows
    # are corrected to (the pairs held until the corrections are planned: rolling.MidTimeFeed).
    feed = PathFeed(info.source_size, plan.model, plan.smoother, plan.crop)
    gate: PathFeed | MidTimeFeed = feed if per_row is None else MidTimeFeed(feed, per_row)
    with progress_group(disable=not show_progress):
        # The tracking starts once the estimator is built, the overlays still being looked for
        # beside it; its pairs reach the feed (and so the render) only once the mask is settled,
        # and it starts again if an overlay was found (track_video's ``mask``).
        pending, estimator = frame_mask_pending(plan.build, video, options.mask, info, show_progress, lens)
        with pending:
            built = time.perf_counter() - clock
            # One decode for both: the tracking reads each frame reduced, the render whole, through a
            # ring that covers the path's window (shared_decode.py).
            yuv = render_yuv(info, compare is not None)
            ring = ring_frames(plan.smoother, estimator, frame_bytes(info, yuv), rolling=per_row is not None)
            # --keep-lens: decoded as the lens saw them, the tracking's frames undistorted by the shared decode
            kept = options.keep_lens
            undistort = None if kept is None else functools.partial(remap_frame, lens=kept)
            shared = SharedDecode(video, info, yuv, estimator.input_width, ring, feed.starved, undistort=undistort,
                                  lens=lens if kept is None else None)
            warp_rows = per_row if kept is None else KeptLens(kept, info.source_size, BORDERS[plan.renderer.border], YUV_BLACK, per_row)
            tracking = TrackingPass(video, estimator, info, gate, show_progress, probe, pending, source=shared.tracking)
            render_clock = time.perf_counter()
            shared.start()
            tracking.start()
            try:
                written = plan.renderer.render(video, out, gate.warp, info, compare=compare, show_progress=show_progress,
                                               frames=info.frame_count, per_row=warp_rows, decoded=shared.render_frames())
                if isinstance(gate, MidTimeFeed):
                    gate.settle()  # (settled already unless no frame was rendered)
            except BaseException:
                gate.cancel()
                pending.cancel()  # a tracking pass still holding its pairs back ends at its next frame
                shared.stop()  # (a tracking pass waiting for a frame ends too)
                tracking.join()
                raise
            try:
                track = tracking.outcome()
            finally:
                shared.stop()  # (ended already: the render's last warps came with the tracking's end)
    # The overlays' share: the build (the detection beside it), the tracking's end waiting for
    # the detection, and a tracking pass discarded for an overlay found (left out of "track").
    lost = track.meta["overlay_wait_seconds"] + track.meta["overlay_lost_seconds"]
    seconds = {"overlays": built + lost}
    rolling = per_row.plan() if per_row is not None else None  # (planned already unless no frame was rendered)
    seconds.update(track=tracking.seconds - lost, plan=feed.plan_seconds, render=time.perf_counter() - render_clock,
                   rolling=per_row.seconds if per_row is not None else 0.0)
    if per_row is not None:
        seconds["rolling_cpu"] = per_row.cpu_seconds

    # What only the tracking pass knows, said in the outputs: where the audio ends (with the
    # frames it counted), and a truncated input (fewer frames than announced).
    short = track.meta.get("input")
    tags = {"comment": f"mosaic stabilize: {_shortfall_text(short)}"} if short else None
    if tags or (info.has_audio and track.frames != info.frame_count):
        for path in [out] + ([compare] if compare is not None else []):
            rewrite_container(path, audio_seconds=track.frames / info.fps if info.has_audio else None, metadata=tags)
    warps = _match_length(feed.warps, written)
    if warps_out is not None:
        write_warps(warps_out, warps, info.source_size, input_meta=short)
    seconds["total"] = time.perf_counter() - clock
    return StabilizeResult(written, info.source_size, info.fps, warps, seconds, input_meta=short, motion=feed.motion,
                           views=feed.views, rolling=rolling, overlay_restart=track.meta["overlay_restart"])


class TrackingPass(threading.Thread):
    """The tracking pass in a thread of its own, each pair handed to the path's feed as it is
    estimated (with ``mask``, a pending one: once it is settled, :func:`~mosaic_cli.track.track_video`);
    :meth:`outcome` waits for it and gives its result or raises its error."""

    def __init__(self, video: str | Path, estimator: Estimator, info: VideoInfo, feed: PathFeed | MidTimeFeed, show_progress: bool,
                 probe: RollingProbe | None = None, mask: PendingMask | None = None,
                 source: Callable[[Gate], VideoStream] | None = None):
        super().__init__(name="mosaic-track", daemon=True)
        self.video, self.estimator, self.info, self.feed, self.show_progress = video, estimator, info, feed, show_progress
        self.probe = probe  # --rolling-shutter auto: fed the first frames (estimators/rolling.py)
        self.mask = mask
        self.source = source  # each attempt's frames (the shared decode's); None: a decode of its own
        self.result: TrackResult | None = None
        self.error: BaseException | None = None
        self.seconds = 0.0

    def run(self) -> None:
        clock = time.perf_counter()
        try:
            self.result = track_video(self.video, self.estimator, show_progress=self.show_progress, info=self.info,
                                      on_pair=self.feed.add_pair, probe=self.probe, mask=self.mask, source=self.source)
            self.feed.finish()
        except BaseException as exc:  # the render learns of it from the feed; the caller from outcome()
            self.error = exc
            self.feed.fail(exc)
        finally:
            self.seconds = time.perf_counter() - clock

    def outcome(self) -> TrackResult:
        self.join()
        if self.error is not None:
            raise self.error
        assert self.result is not None
        return self.result


def _shortfall_text(short: dict) -> str:
    return f"input truncated or damaged, {short['frames_decoded']} of {short['frames_announced']} announced frames decoded"


@dataclass
class _Plan:
    """The stages, configured from the options."""

    build: Callable[[], Estimator] | None  # the estimator, built beside the overlay detection
    model: MotionModel
    smoother: L1Smoother | GaussianSmoother
    crop: float | None  # None: --crop auto
    renderer: Renderer


def check_request(video, out, options: StabilizeOptions, warps_out=None, compare=None) -> tuple[VideoInfo, _Plan]:
    """Every check of the input and the outputs, before any long work (the options checked
    themselves when they were made)."""
    outputs = {"output": out, "--warps": warps_out, "--compare": compare}
    given = {name: Path(p) for name, p in outputs.items() if p is not None}
    for path in given.values():
        check_writable(path)
    if Path(out).suffix.lower() not in OUTPUT_SUFFIXES:
        raise BadInput(f"output {out} must end in one of {', '.join(OUTPUT_SUFFIXES)}")
    if compare is not None and Path(compare).suffix.lower() not in OUTPUT_SUFFIXES:
        raise BadInput(f"--compare {compare} must end in one of {', '.join(OUTPUT_SUFFIXES)}")
    if warps_out is not None and Path(warps_out).suffix.lower() != ".json":
        raise BadInput(f"--warps {warps_out} must end in .json")
    source = Path(video).resolve()
    seen: dict[Path, str] = {}
    for name, path in given.items():
        resolved = path.resolve()
        if resolved == source:
            raise BadInput(f"{name} {path} is the input video itself")
        if resolved in seen:
            raise BadInput(f"{name} and {seen[resolved]} are the same file {path}")
        seen[resolved] = name
    crop = parse_crop(options.crop)
    border = options.border if options.border is not None else ("replicate" if crop is None else "black")
    plan = _Plan(
        build=None,
        model=motion_model(options.model),
        smoother=make_smoother(options.smoothing, options.radius),
        crop=crop,
        renderer=Renderer(border=parse_border(border), crf=options.crf, preset=options.preset or PRESET, device=_render_device(options.device)),
    )
    info = probe(video)
    check_mask_file(options.mask, info)
    plan.build = plan_estimator(options.estimator, work_width=options.work_width, weights=options.weights, device=options.device,
                                default_width=WORK_WIDTH)
    return info, plan


def _render_device(device: str) -> str | None:
    """The render's ``device`` (see :class:`Renderer`): None for ``--device cpu``, else the name,
    resolved when the render starts (so that checking the request imports no torch)."""
    return None if check_device(device) == "cpu" else device


def write_warps(path: str | Path, warps: np.ndarray, size: tuple[int, int], input_meta: dict | None = None) -> None:
    """``{"frames": N, "size": [w, h], "warps": [N 3x3]}``, input pixels -> output pixels; with
    ``"input": {"frames_decoded", "frames_announced", "truncated", "reason"}`` when the input decoded short."""
    doc = {
        "frames": int(len(warps)),
        "size": [int(size[0]), int(size[1])],
        "direction": "input_to_output",
        "warps": [[[float(v) for v in row] for row in W] for W in warps],
    }
    if input_meta:
        doc["input"] = input_meta
    write_json(path, doc)


def _match_length(warps: np.ndarray, frames: int) -> np.ndarray:
    """The warps of the frames actually written (the renderer reuses the last one when the
    second decode finds more frames than the first)."""
    if frames <= len(warps):
        return warps[:frames]
    return np.concatenate([warps, np.repeat(warps[-1:], frames - len(warps), axis=0)])
