"""``stitch --live``: a panorama that grows while the flight is still arriving.

The scan (stage 1 of :mod:`.pipeline`) runs on frames as they come off a live source; every
``every`` seconds, when keyframes were added, a preview is drawn in a background thread (the
scan goes on meanwhile; one preview at a time) and written atomically (a viewer reloading the
file never sees half an image).  Its cost is bounded: it is drawn at most
``PREVIEW_SIDE`` pixels on its longest side, from per-keyframe thumbnails made once (and shrunk
as the area flown grows), each warped only into its own bounding box, later keyframes over
earlier ones, no seams or blending.  With drift control on, the preview's placements are
refined incrementally (:class:`IncrementalRegistration`): each preview registers only the loop
pairs that became candidates since the last one (within the same ``max_loop_pairs`` budget) and
solves the joint placement again from the previous solution, over every loop closed so far.

When the stream ends (its end, ``--timeout``, Ctrl-C or SIGTERM) stages 2-5 run as they do
offline on the same keyframes: drift control over every loop closed, the reference frame,
exposure, seams, blending.  The final panorama is therefore the offline stitch of the frames
received.
"""

from __future__ import annotations

import contextlib
import itertools
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import cast

import cv2
import numpy as np

from mosaic_cli.atomic import atomic_path, check_writable
from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.estimators import Estimator
from mosaic_cli.geometry import frame_corners, normalize, project, resize_matrix
from mosaic_cli.live.loading import begin, built_beside, waited_for
from mosaic_cli.live.source import LiveStream, is_live_source
from mosaic_cli.live.timeline import Timeline
from mosaic_cli.overlay import check_mask_file, frame_mask, live_mask
from mosaic_cli.progress import stream_progress
from mosaic_cli.stitch.canvas import MIN_SIZE, CanvasOptions, parse_reference, plan_canvas
from mosaic_cli.stitch.features import FeatureExtractor, FeatureMatcher, FeatureOptions
from mosaic_cli.stitch.keyframes import FlightScanner, Keyframe, scan_flight
from mosaic_cli.stitch.options import StitchOptions
from mosaic_cli.stitch.output import check_outputs
from mosaic_cli.stitch.pipeline import StitchResult, finish_stitch
from mosaic_cli.stitch.registration import (
    Link,
    RegistrationOptions,
    RegistrationReport,
    link_loops,
    link_sequence,
    loop_candidates,
    refine_placements,
)
from mosaic_cli.stitch.scan import make_stitch_estimator
from mosaic_cli.stitch.spill import load_pixels
from mosaic_cli.video.lens_filter import ImageFilter
from mosaic_cli.video.reader import VideoInfo, probe, scaled_size

PREVIEW_SIDE = 1024
PREVIEW_FORMATS = (".png", ".jpg", ".jpeg")
DEFAULT_EVERY = 2.0


@dataclass
class PreviewOptions:
    path: Path | None = None
    every: float = DEFAULT_EVERY  # seconds between two previews
    side: int = PREVIEW_SIDE  # longest side, pixels

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if self.path is not None and Path(self.path).suffix.lower() not in PREVIEW_FORMATS:
            raise BadInput(f"--preview {self.path} must end in .png, .jpg or .jpeg")
        if not self.every > 0:
            raise BadInput(f"--every must be positive, got {self.every}")
        if self.side < MIN_SIZE:
            raise BadInput(f"the preview must be at least {MIN_SIZE} pixels, got {self.side}")


class IncrementalRegistration:
    """Drift control on the keyframes found so far, for the preview: loop registrations are
    made once and kept; every :meth:`update` adds the new keyframes (placed from the last
    refined one by the scan's chain), registers the new loop candidates and refines every
    placement jointly.  The final panorama does not use it: it runs the offline stage 2."""

    def __init__(self, source_size: tuple[int, int], options: RegistrationOptions, features: FeatureOptions):
        self.size = source_size
        self.options = options
        self.matcher = FeatureMatcher(FeatureExtractor(source_size, features))
        self.placements: list[np.ndarray] = []  # keyframe -> keyframe 0, refined
        self.loops: list[Link] = []
        self.tried: set[tuple[int, int]] = set()
        self.loops_closed = 0

    def update(self, keyframes: list[Keyframe]) -> list[np.ndarray]:
        """Keyframe -> keyframe 0 placements of every keyframe in ``keyframes``."""
        if not keyframes:
            return []
        scan = [normalize(np.linalg.inv(keyframes[0].placement) @ k.placement) for k in keyframes]
        if not self.placements:
            self.placements = [scan[0]]
        last = len(self.placements) - 1
        bridge = self.placements[last] @ np.linalg.inv(scan[last])
        self.placements += [normalize(bridge @ P) for P in scan[last + 1:]]
        if len(keyframes) < 2:
            return list(self.placements)
        report = RegistrationReport()
        sequence = [(i, k.link_to, k.link) for i, k in enumerate(keyframes) if k.link_to is not None and k.link_to < len(keyframes)]
        neighbours = link_sequence(sequence, self.placements, self.size, self.options, report)
        candidates = loop_candidates(self.placements, self.size, self.options, self.tried)
        self.tried |= set(candidates)
        features = [k.features for k in keyframes]
        self.loops += link_loops(features, self.placements, candidates, self.matcher, self.options, report, lambda *a, **k: None)
        report.links = neighbours + self.loops
        self.placements = refine_placements(self.placements, report, 0, self.size, self.options)
        self.loops = [link for link in report.links if link.kind == "loop"]
        self.loops_closed = len(self.loops)
        return list(self.placements)


@dataclass
class _Thumb:
    image: np.ndarray  # RGBA, opaque
    scale: float  # thumbnail pixels per source pixel


@dataclass
class LivePreview:
    """Draws the keyframes found so far (see the module doc), in a thread of its own.

    :meth:`maybe_update`, called by the scan, starts a preview in the background when one is due
    and none is being drawn; the scan goes on meanwhile.  The preview works on a snapshot of the
    keyframes taken then: copies, with the pixels of those it has not seen yet loaded at once
    (the scan may later shrink or drop what it holds).  The thumbnails, the incremental
    registration and the written file belong to the drawing thread; :meth:`finish` waits for
    it and draws the last preview."""

    options: PreviewOptions
    source_size: tuple[int, int]
    registration: IncrementalRegistration | None = None  # None: the scan's placements
    written: int = 0
    seconds: float = 0.0  # spent drawing and writing previews
    _thumbs: dict[int, _Thumb] = field(default_factory=dict)
    _images: dict[int, np.ndarray] = field(default_factory=dict)  # pixels not yet made thumbnails
    _sent: set[int] = field(default_factory=set)  # keyframes whose pixels a snapshot carried
    _drawn_keyframes: int = 0
    _due: float = 0.0
    _worker: threading.Thread | None = None
    _error: BaseException | None = None

    def maybe_update(self, keyframes: list[Keyframe], now: float | None = None) -> bool:
        """Start a preview when one is due, keyframes were added since the last and the last is
        written (a preview that comes due while one is being drawn waits for it: one at a time)."""
        self._raise()
        now = time.monotonic() if now is None else now
        if self.options.path is None or now < self._due or len(keyframes) == self._drawn_keyframes:
            return False
        if self.busy:
            return False
        snapshot = self._snapshot(keyframes)
        self._drawn_keyframes = len(keyframes)
        self._worker = threading.Thread(target=self._draw_in_background, args=(snapshot,), daemon=True,
                                        name="stitch-preview")
        self._worker.start()
        return True

    @property
    def busy(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    def finish(self, keyframes: list[Keyframe]) -> None:
        """Wait for the preview being drawn, then draw the last one here."""
        self.wait()
        self.update(self._snapshot(keyframes))

    def wait(self) -> None:
        if self._worker is not None:
            self._worker.join()
            self._worker = None
        self._raise()

    def _raise(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def _snapshot(self, keyframes: list[Keyframe]) -> list[Keyframe]:
        shots = []
        for k in keyframes:
            image = None
            if k.composited and k.image is not None and k.index not in self._sent:
                image = load_pixels(k.image)
                self._sent.add(k.index)
            shots.append(replace(k, image=image))
        return shots

    def _draw_in_background(self, snapshot: list[Keyframe]) -> None:
        try:
            self.update(snapshot)
        except BaseException as exc:  # raised in the scan's thread at its next call
            self._error = exc
        # The next one is due a period after this one is written: at most one preview at a
        # time, and a pause between two however long each takes.
        self._due = time.monotonic() + self.options.every

    def update(self, keyframes: list[Keyframe]) -> None:
        """Draw ``keyframes`` (a snapshot) and write the preview atomically."""
        if self.options.path is None:
            return
        clock = time.perf_counter()
        for k in keyframes:
            if k.image is not None:  # a snapshot's pixels, loaded by _snapshot
                self._images[k.index] = cast(np.ndarray, k.image)
        image = self.draw(keyframes)
        if image is not None:
            with atomic_path(self.options.path) as tmp:
                params = [cv2.IMWRITE_PNG_COMPRESSION, 1] if tmp.suffix.lower() == ".png" else [cv2.IMWRITE_JPEG_QUALITY, 85]
                if not cv2.imwrite(str(tmp), cv2.cvtColor(image, cv2.COLOR_RGBA2BGRA if tmp.suffix.lower() == ".png"
                                                           else cv2.COLOR_RGBA2BGR), params):
                    raise ProcessingError(f"{self.options.path}: OpenCV could not write the preview")
            self.written += 1
        self.seconds += time.perf_counter() - clock

    def draw(self, keyframes: list[Keyframe]) -> np.ndarray | None:
        """RGBA preview of the composited keyframes, None while they cannot be drawn sanely."""
        if self.registration is not None:
            placements = self.registration.update(keyframes)
        else:
            placements = [k.placement for k in keyframes]
        drawn = [(k, P) for k, P in zip(keyframes, placements)
                 if k.composited and (k.index in self._images or k.index in self._thumbs)]
        if not drawn:
            return None
        try:
            canvas = plan_canvas([P for _, P in drawn], [k.index for k, _ in drawn], self.source_size,
                                 CanvasOptions(max_size=self.options.side))
        except ProcessingError:
            return None  # a placement degenerated; the final stitch will say so
        W, H = canvas.size
        out = np.zeros((H, W, 4), np.uint8)
        for k, P in drawn:
            thumb = self._thumb(k, canvas.scale)
            M = normalize(canvas.frame_to_canvas(P) @ np.linalg.inv(
                resize_matrix(self.source_size, (thumb.image.shape[1], thumb.image.shape[0]))))
            self._paste(out, thumb.image, M)
        return out

    def _thumb(self, keyframe: Keyframe, scale: float) -> _Thumb:
        """The keyframe at about ``scale`` (never larger than held); made once, shrunk when the
        canvas scale drops well below it."""
        thumb = self._thumbs.get(keyframe.index)
        if thumb is None:
            image = cv2.cvtColor(self._images.pop(keyframe.index), cv2.COLOR_RGB2RGBA)  # opaque
            thumb = _Thumb(image, image.shape[1] / self.source_size[0])
        if thumb.scale > 1.5 * scale:
            w, h = self.source_size
            size = (max(2, round(w * scale)), max(2, round(h * scale)))
            thumb = _Thumb(cv2.resize(thumb.image, size, interpolation=cv2.INTER_AREA), size[0] / w)
        self._thumbs[keyframe.index] = thumb
        return thumb

    @staticmethod
    def _paste(out: np.ndarray, image: np.ndarray, M: np.ndarray) -> None:
        """Warp ``image`` (RGBA, opaque) by ``M`` (image pixels -> canvas pixels) over ``out``,
        within its bounding box: the pixels it does not reach are left as they are."""
        h, w = image.shape[:2]
        corners = project(M, frame_corners(w, h))
        x0, y0 = np.floor(corners.min(axis=0)).astype(int)
        x1, y1 = np.ceil(corners.max(axis=0)).astype(int) + 1
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, out.shape[1]), min(y1, out.shape[0])
        if x1 <= x0 or y1 <= y0:
            return
        shift = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1.0]]) @ M
        region = np.ascontiguousarray(out[y0:y1, x0:x1])
        cv2.warpPerspective(image, shift, (x1 - x0, y1 - y0), dst=region, flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_TRANSPARENT)
        out[y0:y1, x0:x1] = region


@dataclass
class LiveStitchResult(StitchResult):
    """A live stitch's result: the stitch's, and what the scan of the arriving frames did."""

    previews: int = 0  # previews written
    preview_seconds: float = 0.0  # drawing them, in all
    ended_by: str | None = None  # a live source: what ended it ("end of stream", "timeout", "Ctrl-C", "SIGTERM")
    timeline: Timeline | None = None  # each frame's time stamps by stage (live/timeline.py)


def stitch_live(source: str, out: str | Path, estimator: Estimator | None = None, options: StitchOptions | None = None,
                transforms: str | Path | None = None, preview: PreviewOptions | None = None,
                show_progress: bool = True, info: VideoInfo | None = None, *, lens: ImageFilter | None = None) -> LiveStitchResult:
    """Stitch ``source`` (a live source, or a file read as one) into ``out``, writing a growing
    preview on the way when ``preview.path`` is given.  ``estimator``: None builds the one
    ``options`` name once the request is checked.  ``info``: a file's probe, when the caller has it.
    ``lens``: each frame through this filter as it arrives (``--lens``), the mask carried into
    the undistorted frame."""
    options = options or StitchOptions()
    preview = preview or PreviewOptions()
    reference = check_live_request(out, transforms, options, preview)
    live = is_live_source(source)
    if not live:
        info = info if info is not None else probe(source)
    check_mask_file(options.mask, None if live else info)
    loading = None
    owned = estimator is None  # built here, so closed here
    if estimator is None and live:  # the socket listens at once, the network loading beside it
        loading = built_beside(lambda: make_stitch_estimator(options), after_start=True)
    elif estimator is None:
        estimator = make_stitch_estimator(options)
    masked = None
    if not live:
        # A file read as a stream is there whole: its overlays are found before the scan starts.
        masked = frame_mask(source, options.mask, info, show_progress, lens)
    track = _georef_telemetry(source, out, options, live, info)
    with tempfile.TemporaryDirectory(prefix="mosaic-stitch-") as spill:
        seconds: dict[str, float] = {}
        clock = time.perf_counter()
        with waited_for(loading), LiveStream(str(source), "rgb", timeout=options.timeout, quiet=not show_progress, live=live,
                                             info=info, on_started=lambda: begin(loading), lens=lens) as stream:
            info = stream.info
            if estimator is None:
                assert loading is not None
                estimator = loading.result()
            max_size = options.canvas.max_size
            width = None
            if max_size and max(info.source_size) > max_size:
                width = max(2, int(info.source_size[0] * max_size / max(info.source_size)))
            decode_size = scaled_size(info.source_size, width)
            stream.info = replace(info, size=decode_size)
            if masked is None:  # a live input: only --mask, sized by the stream's first frame
                masked = live_mask(options.mask, info.source_size, show_progress, lens)
            estimator.set_mask(masked.use)
            scanner = FlightScanner(info.source_size, decode_size, info.fps, 0, options.keyframes, options.features,
                                    max_size, spill if options.spill else None, masked.use)
            registration = (IncrementalRegistration(info.source_size, options.registration, options.features)
                            if options.registration.enabled else None)
            drawer = LivePreview(preview, info.source_size, registration)
            # When each frame came off the decoder and when the scan was done with it: how far
            # the scan falls behind the stream (python -m benchmarks live).
            timeline = Timeline(("arrived", "scanned"))

            def frames() -> Iterator[np.ndarray]:
                for arrival in stream.arrivals():
                    timeline.stamp("arrived", arrival.time)
                    yield arrival.frame

            try:
                with stream_progress(f"scan ({estimator.name}, live)", disable=not show_progress) as advance:
                    def step(n: int = 1, status: str | None = None) -> None:
                        timeline.stamp("scanned", frames=n)
                        if n and drawer.maybe_update(scanner.keyframes):  # not for the scan's closing status
                            status = f"{status or ''} preview {drawer.written + 1}"
                        advance(n, status=status)

                    scan = scan_flight(itertools.islice(frames(), options.max_frames), estimator, scanner, step)
            except BaseException:
                with contextlib.suppress(Exception):
                    drawer.wait()  # its file written or removed, not left half-way
                raise
            drawer.finish(scan.keyframes)  # the last ground too, before the long final stages
            if owned:
                estimator.close()  # its pool's threads: nothing is estimated after the scan
        seconds["scan"] = time.perf_counter() - clock
        seconds["overlays"] = masked.seconds
        if not scan.keyframes:
            raise BadInput(f"{source}: no frame is usable (all black, blank or over-exposed)")
        # The stages after the scan as in pipeline.stitch, on the same keyframes.
        result = finish_stitch(scan, reference, out, options, transforms, show_progress, seconds, masked, track)
        return LiveStitchResult(**vars(result), previews=drawer.written, preview_seconds=drawer.seconds,
                                ended_by=stream.ended_by if live else None, timeline=timeline)


def _georef_telemetry(source: str, out: str | Path, options: StitchOptions, live: bool, info: VideoInfo | None = None):
    """The telemetry, before any work: an explicit --telemetry file; a file read as live may
    hold a track of its own, a stream (stdin, URL) cannot be probed for one."""
    from mosaic_cli.geo.stitching import check_plain_output, georef_telemetry, map_output_flag

    georef = options.georef
    if georef is None:
        check_plain_output(out, "--telemetry none was given")
        return None
    if live and georef.telemetry is None:
        if wanted := map_output_flag(out) + georef.without_telemetry():
            raise BadInput(f"{wanted[0]} with a live input needs --telemetry (a stream cannot be searched for a GPS track)")
        return None
    return georef_telemetry(source, out, georef, info=info)  # the stream's length is unknown: coverage is checked after the scan


def check_live_request(out, transforms, options: StitchOptions, preview: PreviewOptions) -> str | int:
    """The checks of scan._check_inputs that need no probe of the input, and the preview's;
    the reference (see canvas.parse_reference)."""
    check_outputs(out, transforms, options.canvas.max_size)
    if preview.path is not None:
        check_writable(preview.path)
        if Path(preview.path).resolve() == Path(out).resolve():
            raise BadInput("--preview must differ from the panorama output")
    if options.start != 0:
        raise BadInput("--start is not available with --live or a live input")
    return parse_reference(options.canvas.reference)
