"""Stage 1, the streaming pass: decode once, chain the estimator's pairwise homographies and
keep the keyframes the panorama is made of.

A frame becomes a keyframe when it covers enough new ground (its overlap with the last
keyframe falls below ``new_ground``) and it is sharp and well exposed; blurred, black or
over-exposed frames are passed over while a better one may still come.  Only keyframes that
add ground not yet covered keep their pixels (at the scale the canvas will need); keyframes
over ground already covered keep only their features, as anchors for drift control.  So the
memory grows with the area flown over, not with the number of frames.  Each keyframe is placed
by registering it directly with the previous one (SIFT), not by the dozens of pairwise
estimates in between; the estimator only tracks the frames from one keyframe to the next.

When the estimator loses the flight, the next frames are registered directly against the last
keyframes; a frame the estimator follows again but that registers with none of them (a cut)
starts a new *segment*, with its own world, which the register stage relocalises against the
keyframes of the others (:mod:`.segments`).  Photos (an image folder) are not video: the
estimator is not used at all; each photo is registered directly with the previous one (or
the last few), and a photo that registers with none starts a new segment.

Placements here are "world" transforms: frame pixels -> pixels of the first frame (the
anchor), full-resolution source pixels.  They are affine: chained homographies accumulate
perspective error, and far from the anchor that error grows without bound (the estimated
horizon closes in until frames fold), whereas this bookkeeping (overlaps, coverage, canvas
extent, starting values) needs only a stable, roughly metric world.  The perspective is
recovered from the full registrations by the joint refinement (:mod:`.registration`).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.estimators import Estimator, PairEstimate
from mosaic_cli.geometry import frame_corners, is_valid, project
from mosaic_cli.mask import fill_masked, work_mask
from mosaic_cli.stitch.features import FeatureExtractor, FeatureMatcher, FeatureOptions, Features, PairMatch, corner_distance
from mosaic_cli.stitch.guide import GroundGuide
from mosaic_cli.stitch.spill import Pixels, SpilledImage, drop_pixels, load_pixels
from mosaic_cli.video.decode import gray_at
from mosaic_cli.video.info import PhotoFit

FIT_MASK_WIDTH = 1024  # px: a fitted photo's mask of its own pixels (blurred edges are not drawn: see work_mask)


@dataclass
class KeyframeOptions:
    new_ground: float = 0.6  # a keyframe is due once the overlap with the last one drops below this
    force_overlap: float = 0.35  # ... and is taken (the sharpest candidate) at the latest here
    last_overlap: float = 0.9  # the flight's last frame is kept if it overlaps the last keyframe less
    # "Sharp": Laplacian variance at least this fraction of the recent sharp level (the 80th
    # percentile over a window, so that a run of blurred frames does not lower the bar).
    sharpness_ratio: float = 0.6
    sharpness_percentile: float = 80.0
    sharpness_window: int = 31
    dark_level: float = 25.0  # mean gray below this: a black frame
    bright_level: float = 235.0  # mean gray above this: over-exposed
    max_clipped: float = 0.3  # ... or more than this fraction of pixels saturated
    min_contrast: float = 4.0  # gray standard deviation below this: a blank frame
    min_new_coverage: float = 0.1  # a keyframe keeps its pixels if it adds this much new ground
    coverage_cells: int = 16  # coverage is tracked on cells 1/16 of a frame width wide
    min_confidence: float = 0.0  # estimates at or below this confidence count as failures
    # A keyframe's direct registration to the previous one must agree with the chain this well
    # (fraction of the frame diagonal, at the corners) to replace it.
    link_tolerance: float = 0.25
    # ... unless it has this many inliers: then the estimator was wrong (frames further apart
    # than it can follow, say) and the registration overrules the chain.
    override_inliers: int = 60
    relocalise_keyframes: int = 3  # a lost frame is registered against this many last keyframes
    quality_width: int = 320
    # The chained placement may make a frame this many times larger/smaller than the anchor.
    max_scale_change: float = 10.0

    def __post_init__(self) -> None:
        self.validate()
        # A keyframe is forced no later than it is due: a lower --overlap lowers both.
        self.force_overlap = min(self.force_overlap, self.new_ground)

    def validate(self) -> None:
        if not 0.05 <= self.new_ground <= 0.95:
            raise BadInput(f"--overlap must be between 0.05 and 0.95, got {self.new_ground}")


@dataclass(frozen=True)
class FrameQuality:
    sharpness: float  # variance of the Laplacian at quality_width
    brightness: float
    contrast: float
    clipped: float  # fraction of saturated pixels

    def well_exposed(self, o: KeyframeOptions) -> bool:
        return (
            o.dark_level <= self.brightness <= o.bright_level
            and self.contrast >= o.min_contrast
            and self.clipped <= o.max_clipped
        )


def measure_quality(gray: np.ndarray) -> FrameQuality:
    mean, std = cv2.meanStdDev(gray)
    sharpness = float(cv2.Laplacian(gray, cv2.CV_32F).var())
    clipped = float(np.count_nonzero(gray >= 250)) / gray.size
    return FrameQuality(sharpness, float(mean[0, 0]), float(std[0, 0]), clipped)


@dataclass
class Keyframe:
    index: int  # frame number in the video
    placement: np.ndarray  # frame -> world (affine, see the module doc), source pixels
    features: Features
    quality: FrameQuality
    link: PairMatch | None = None  # direct registration to the previous keyframe (this -> it)
    image: Pixels | None = None  # RGB at ``scale`` x source size, while it is held (maybe in a file)
    scale: float = 1.0
    composited: bool = False  # drawn in the panorama (else used for registration only)
    segment: int = 0  # the stretch of flight followed without a break; placements are in its world
    link_to: int | None = None  # position of the keyframe ``link`` registers this one to
    # Its pixels to draw where not the scan's ``use``: its flight's overlay mask (several
    # flights), or its part of the frame (a photo of another shape, fitted into the folder's frame)
    use: np.ndarray | None = None
    fit: PhotoFit | None = None  # a photo of another camera: where in the frame its pixels lie


@dataclass(frozen=True)
class FlightSpan:
    """One of several flights in the one count of frames: ``start`` .. ``start + frames - 1``."""

    name: str
    start: int
    frames: int

    def holds(self, index: int) -> bool:
        return self.start <= index < self.start + self.frames


@dataclass
class FlightScan:
    keyframes: list[Keyframe]
    source_size: tuple[int, int]
    fps: float
    frames: int  # frames read
    first_index: int
    failed_pairs: int = 0
    relocalised: list[int] = field(default_factory=list)
    seconds: float = 0.0
    # Frames that went into no keyframe's place and why: photos (each is a keyframe unless
    # named here) and video frames that could not be placed (between a cut and a new segment).
    dropped: list[tuple[int, str]] = field(default_factory=list)
    photos: bool = False
    use: np.ndarray | None = None  # burned-in overlays and --mask (255 = ground): never drawn
    pairs_tried: int = 0  # photos: the pairs the scan matched (the GPS guide keeps them few per photo)
    flights: list[FlightSpan] = field(default_factory=list)  # several flights laid end to end (stitch/flights.py)

    @property
    def composited(self) -> list[Keyframe]:
        return [k for k in self.keyframes if k.composited]


class KeyframeStore:
    """Holds keyframe pixels at the scale the canvas will need: the longest side of the area
    flown so far must fit ``max_size`` (with a margin, as the final reference frame may be
    larger than the anchor); images already held shrink when the area outgrows them.  With
    ``spill``, a folder, the pixels are held there in files rather than in memory (see
    :mod:`.spill`)."""

    MARGIN = 1.2
    SHRINK_BELOW = 0.9  # re-scale held images only when they are this much too large

    def __init__(self, source_size: tuple[int, int], decode_scale: float, max_size: int | None, spill: str | Path | None = None):
        self.source_size = source_size
        self.decode_scale = decode_scale
        self.max_size = max_size
        self.spill = spill
        self.scale = decode_scale
        self._lo = np.array([np.inf, np.inf])
        self._hi = -self._lo

    def keep(self, keyframe: Keyframe, frame: np.ndarray, world_corners: np.ndarray) -> None:
        self._lo = np.minimum(self._lo, world_corners.min(axis=0))
        self._hi = np.maximum(self._hi, world_corners.max(axis=0))
        if self.max_size:
            extent = float(np.max(self._hi - self._lo))
            self.scale = min(self.decode_scale, self.MARGIN * self.max_size / max(extent, 1.0))
        image, keyframe.scale = self._resized(frame, self.decode_scale, self.scale)
        keyframe.image = self._held(image)
        keyframe.composited = True

    def shrink(self, keyframes: Iterable[Keyframe]) -> None:
        for k in keyframes:
            if k.image is not None and self.scale < self.SHRINK_BELOW * k.scale:
                image, k.scale = self._resized(load_pixels(k.image), k.scale, self.scale)
                drop_pixels(k.image)
                k.image = self._held(image)

    def _held(self, image: np.ndarray) -> Pixels:
        image = np.asarray(image)  # the pixels alone: a decoded frame's luma plane and gray copies are not kept
        return SpilledImage(image, self.spill) if self.spill is not None else image

    def _resized(self, image: np.ndarray, have: float, want: float) -> tuple[np.ndarray, float]:
        if want >= have * 0.999:
            return image, have
        w, h = self.source_size
        size = (max(2, round(w * want)), max(2, round(h * want)))
        return cv2.resize(image, size, interpolation=cv2.INTER_AREA), size[0] / w


class CoverageMap:
    """Which coarse world cells the composited keyframes already cover (a set: unbounded world)."""

    def __init__(self, source_size: tuple[int, int], cells_per_width: int):
        self.cell = source_size[0] / cells_per_width
        self.covered: set[tuple[int, int]] = set()

    def cells(self, world_corners: np.ndarray) -> set[tuple[int, int]]:
        q = world_corners / self.cell
        lo = np.floor(q.min(axis=0)).astype(int)
        hi = np.ceil(q.max(axis=0)).astype(int)
        grid = np.zeros((hi[1] - lo[1] + 1, hi[0] - lo[0] + 1), np.uint8)
        cv2.fillConvexPoly(grid, np.round((q - lo) * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
        ys, xs = np.nonzero(grid)
        return set(zip((xs + lo[0]).tolist(), (ys + lo[1]).tolist()))

    def new_fraction(self, cells: set) -> float:
        return len(cells - self.covered) / max(1, len(cells))

    def add(self, cells: set) -> None:
        self.covered |= cells


def overlap_fraction(H_frame_to_key: np.ndarray, size: tuple[int, int]) -> float:
    """The fraction of a keyframe's area that a frame, mapped by ``H``, covers."""
    quad = project(H_frame_to_key, frame_corners(*size)).astype(np.float32)
    rect = frame_corners(*size).astype(np.float32)
    area, _ = cv2.intersectConvexConvex(quad, rect)
    return max(0.0, float(area)) / (size[0] * size[1])


class FlightScanner:
    """Consumes frames and their pairwise estimates in order and builds the keyframe list."""

    def __init__(
        self,
        source_size: tuple[int, int],
        decode_size: tuple[int, int],
        fps: float,
        first_index: int,
        options: KeyframeOptions,
        feature_options: FeatureOptions,
        max_size: int | None,
        spill: str | Path | None = None,
        use: np.ndarray | None = None,
        guide: GroundGuide | None = None,
        photo_fits: Iterable[PhotoFit] = (),
    ):
        self.o = options
        self.guide = guide  # a photo folder's GPS: which keyframes to match a photo with, and how
        self.use = use  # burned-in overlays (255 = ground): no features there, never drawn
        self.fits = {f.index: f for f in photo_fits}  # photos of another camera, by frame index
        self.size = source_size
        self.fps = fps
        self.index = first_index - 1
        self.first_index = first_index
        self.extract = FeatureExtractor(source_size, feature_options, use)
        self.matcher = FeatureMatcher(self.extract)
        self.store = KeyframeStore(source_size, decode_size[0] / source_size[0], max_size, spill)
        self.coverage: dict[int, CoverageMap] = {}  # per segment: each has its own world
        self.keyframes: list[Keyframe] = []
        self.placement: np.ndarray | None = None  # of the current frame, None while lost
        self.segment = 0
        self.previous: int | None = None  # position of the keyframe new ones are linked to
        self.failed_pairs = 0
        self.relocalised: list[int] = []
        self.dropped: list[tuple[int, str]] = []
        self.photos = False
        self.pairs_tried = 0
        self._sharpness: deque[float] = deque(maxlen=options.sharpness_window)
        self._candidate: tuple | None = None  # (sharpness, index, frame, quality, placement)
        self._last: tuple | None = None  # the same, of the last sharp and well exposed frame
        self._quality_size = (options.quality_width, max(1, round(source_size[1] * options.quality_width / source_size[0])))
        self._corners = frame_corners(*source_size)

    # -- per frame -------------------------------------------------------------------
    def first(self, frame: np.ndarray) -> None:
        self.index += 1
        self.placement = np.eye(3)
        self._consider(frame, self._quality(frame))

    def step(self, frame: np.ndarray, estimate: PairEstimate) -> None:
        self.index += 1
        quality = self._quality(frame)
        self.placement = self._place(frame, estimate)
        if self.placement is not None:
            self._consider(frame, quality)
        else:
            self.dropped.append((self.index, "lost: the estimator failed and it registers with no recent keyframe"))

    def photo(self, frame: np.ndarray) -> None:
        """A photo of a folder: registered directly (features) with the previous keyframe or,
        failing that, with the last few; every photo becomes a keyframe or is named dropped."""
        self.photos = True
        self.index += 1
        fit = self.fits.get(self.index)
        part = fit if fit is not None and not fit.fills(self.size) else None  # a photo of another shape
        use = self._fitted_use(part.box) if part is not None else None
        quality = self._quality(frame if part is None else frame[part.region((frame.shape[1], frame.shape[0]), self.size)])
        if not quality.well_exposed(self.o):
            self.dropped.append((self.index, _exposure_problem(quality, self.o)))
            return
        features = self.extract(frame, use)
        if len(features) < self.matcher.options.min_inliers:
            self.dropped.append((self.index, f"featureless: {len(features)} SIFT features"))
            return
        for position in self._photo_candidates():
            key = self.keyframes[position]
            self.pairs_tried += 1
            match = self.matcher.match(features, key.features)
            guided = self.guide.predicted(self.index, key.index) if self.guide is not None else None
            if match is None and guided is not None:
                match = self.matcher.match_guided(features, key.features, *guided)
            if match is not None:
                if self.guide is not None:
                    self.guide.learn(self.index, key.index, match.H)
                self.segment, self.previous = key.segment, position
                self._add(self.index, frame, quality, key.placement @ self._affine(match.H), features, (position, match), use, fit)
                return
        if self.keyframes:
            self._new_segment()
        self._add(self.index, frame, quality, np.eye(3), features, use=use, fit=fit)

    def _fitted_use(self, box: tuple[int, int, int, int]) -> np.ndarray:
        """The pixels of a fitted photo's frame in its ``box`` (and not an overlay's), at a
        width of at most :data:`FIT_MASK_WIDTH`; a pixel partly outside the photo is not used."""
        size = (min(self.size[0], FIT_MASK_WIDTH), max(1, round(self.size[1] * min(self.size[0], FIT_MASK_WIDTH) / self.size[0])))
        s = size[0] / self.size[0]
        x, y, w, h = box
        use = np.zeros((size[1], size[0]), np.uint8)
        use[math.ceil(y * s):math.floor((y + h) * s), math.ceil(x * s):math.floor((x + w) * s)] = 255
        return use if self.use is None else cv2.bitwise_and(use, work_mask(self.use, size))

    def _photo_candidates(self) -> list[int]:
        """The keyframes (positions) a new photo is matched against, in order: the previous
        one, those the GPS says it overlaps (nearest first; survey lines' neighbours among
        them), then the last few (the GPS may be wrong)."""
        recent = range(len(self.keyframes) - 1, max(-1, len(self.keyframes) - 1 - self.o.relocalise_keyframes), -1)
        order = [self.previous] if self.previous is not None else []
        if self.guide is not None:
            at = {k.index: p for p, k in enumerate(self.keyframes)}
            order += [at[i] for i in self.guide.candidates(self.index, list(at)) or []]
        order += list(recent)
        return list(dict.fromkeys(order))

    def discard(self) -> None:
        """Drop every keyframe and its pixels (their spilled files deleted now): the scan is
        void (an overlay found after it started, :mod:`mosaic_cli.overlay.speculate`)."""
        for keyframe in self.keyframes:
            drop_pixels(keyframe.image)
            keyframe.image = None
        self.keyframes = []
        self._candidate = self._last = None

    def finish(self) -> FlightScan:
        # The flight's last ground: the best frame since the last keyframe, if it adds any.
        ending = self._candidate or self._last
        last = self.keyframes[self.previous] if self.previous is not None else None
        if ending is not None and last is not None and ending[1] > last.index:
            _, index, frame, quality, placement = ending
            if overlap_fraction(np.linalg.inv(last.placement) @ placement, self.size) < self.o.last_overlap:
                self._add(index, frame, quality, placement)
        self.store.shrink(self.keyframes)
        return FlightScan(
            self.keyframes, self.size, self.fps, self.index - self.first_index + 1, self.first_index,
            self.failed_pairs, self.relocalised, dropped=self.dropped, photos=self.photos, use=self.use,
            pairs_tried=self.pairs_tried,
        )

    # -- placement -------------------------------------------------------------------
    def _place(self, frame: np.ndarray, estimate: PairEstimate) -> np.ndarray | None:
        ok = estimate.confidence > self.o.min_confidence and is_valid(estimate.H, self.size, max_area_ratio=2.0)
        if not ok:
            self.failed_pairs += 1
        if ok and self.placement is not None:
            chained = self.placement @ np.linalg.inv(self._affine(estimate.H))
            self._check_chain(chained)
            return chained
        if not self.keyframes:
            # Nothing placed yet: start the world afresh at this frame.
            self._candidate = None
            return np.eye(3)
        placement = self._relocalise(frame)
        if placement is None and ok:
            # The estimator follows this ground but it registers with no recent keyframe: a
            # cut.  A new segment starts here; the register stage relocalises it.
            self._new_segment()
            return np.eye(3)
        return placement

    def _new_segment(self) -> None:
        self.segment = 1 + max(k.segment for k in self.keyframes)
        self.previous = None
        self._candidate = self._last = None

    def _relocalise(self, frame: np.ndarray) -> np.ndarray | None:
        """Register the frame directly against the last keyframes (the estimator lost it)."""
        features = self.extract(frame)
        first = max(0, len(self.keyframes) - self.o.relocalise_keyframes)
        for position in range(len(self.keyframes) - 1, first - 1, -1):
            key = self.keyframes[position]
            match = self.matcher.match(features, key.features)
            if match is not None:
                self.relocalised.append(self.index)
                # Go on in that keyframe's segment (a short break may have started another).
                self.segment, self.previous = key.segment, position
                return key.placement @ self._affine(match.H)
        return None

    def _check_chain(self, placement: np.ndarray) -> None:
        limit = self.o.max_scale_change**2
        if not is_valid(placement, self.size, max_area_ratio=limit):
            raise ProcessingError(
                f"the chained homographies degenerate at frame {self.index} ({_timecode(self.index, self.fps)}): "
                f"the frame would be mapped behind the camera, folded, or over {limit:.0f}x its size, so the "
                f"canvas would explode; the estimator lost track there: stitch a shorter part "
                f"(--start/--max-frames) or try another --estimator"
            )

    # -- keyframe choice -------------------------------------------------------------
    def _quality(self, frame: np.ndarray) -> FrameQuality:
        quality = measure_quality(gray_at(frame, self._quality_size))
        if quality.well_exposed(self.o):
            self._sharpness.append(quality.sharpness)
        return quality

    def _consider(self, frame: np.ndarray, quality: FrameQuality) -> None:
        if not quality.well_exposed(self.o):
            return
        sharp = quality.sharpness >= self.o.sharpness_ratio * float(np.percentile(self._sharpness, self.o.sharpness_percentile))
        if sharp:
            self._last = (quality.sharpness, self.index, frame, quality, self.placement)
        if self.previous is None:  # the segment's first keyframe
            if sharp:
                self._add(self.index, frame, quality, self.placement)
            return
        last = self.keyframes[self.previous]
        overlap = overlap_fraction(np.linalg.inv(last.placement) @ self.placement, self.size)
        if overlap >= self.o.new_ground:
            return
        if sharp:
            self._add(self.index, frame, quality, self.placement)
            return
        if self._candidate is None or quality.sharpness > self._candidate[0]:
            self._candidate = (quality.sharpness, self.index, frame, quality, self.placement)
        if overlap < self.o.force_overlap:
            _, index, frame, quality, placement = self._candidate
            self._add(index, frame, quality, placement)

    def _anchor(self, keyframe: Keyframe, previous: Keyframe) -> None:
        """Place a new keyframe by registering it directly with the previous one, when that
        agrees with the estimator's chain: one accurate step instead of dozens of small ones,
        so the world placement of a long flight does not drift into perspective nonsense."""
        chained = np.linalg.inv(previous.placement) @ keyframe.placement
        tolerance = self.o.link_tolerance * float(np.hypot(*self.size))
        match = self.matcher.match(keyframe.features, previous.features)
        if match is not None and corner_distance(match.H, chained, self.size) > tolerance and match.inliers < self.o.override_inliers:
            match = None  # disagrees with the chain, and not convincingly enough to overrule it
        keyframe.link = match
        keyframe.link_to = self.previous
        if keyframe.link is not None:
            anchored = previous.placement @ self._affine(keyframe.link.H)
            # The frames after the keyframe were chained from its old placement: move them too.
            if self.placement is not None:
                self.placement = anchored @ np.linalg.inv(keyframe.placement) @ self.placement
            keyframe.placement = anchored

    def _affine(self, H: np.ndarray) -> np.ndarray:
        return closest_affine(H, self.size)

    def _add(self, index, frame, quality, placement, features: Features | None = None, link: tuple | None = None,
             use: np.ndarray | None = None, fit: PhotoFit | None = None) -> None:
        """A new keyframe in the current segment: ``link`` (position, match) when it was
        registered already (photos), else it is anchored to the previous keyframe.  ``use``:
        its own pixels to draw where not the scan's (a fitted photo's)."""
        self._candidate = self._last = None
        keyframe = Keyframe(index, placement, features if features is not None else self.extract(frame), quality,
                            segment=self.segment, use=use, fit=fit)
        use = use if use is not None else self.use
        if link is not None:
            keyframe.link_to, keyframe.link = link
        elif self.previous is not None:
            self._anchor(keyframe, self.keyframes[self.previous])
        placement = keyframe.placement
        world = project(placement, self._corners)
        coverage = self.coverage.setdefault(self.segment, CoverageMap(self.size, self.o.coverage_cells))
        cells = coverage.cells(world)
        if not coverage.covered or coverage.new_fraction(cells) >= self.o.min_new_coverage:
            coverage.add(cells)
            # Overlay pixels are replaced by the ground around them: the blender's pyramid
            # reaches a few pixels past the mask's edge.  (A video's frame becomes RGB only here:
            # see video.YuvFrame.)
            pixels = np.asarray(frame)
            self.store.keep(keyframe, pixels if use is None else fill_masked(pixels, use), world)
            self.store.shrink(self.keyframes)
        self.keyframes.append(keyframe)
        self.previous = len(self.keyframes) - 1


def closest_affine(H: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The affine transform closest to ``H`` over a frame of ``size`` (corners and centre)."""
    points = np.vstack([frame_corners(*size), [[(size[0] - 1) / 2, (size[1] - 1) / 2]]])
    design = np.hstack([points, np.ones((5, 1))])
    A, *_ = np.linalg.lstsq(design, project(H, points), rcond=None)
    return np.vstack([A.T, [0.0, 0.0, 1.0]])


def _exposure_problem(quality: FrameQuality, o: KeyframeOptions) -> str:
    if quality.brightness < o.dark_level:
        return f"black (mean gray {quality.brightness:.0f})"
    if quality.brightness > o.bright_level or quality.clipped > o.max_clipped:
        return f"over-exposed ({quality.clipped:.0%} saturated)"
    return f"blank (gray contrast {quality.contrast:.1f})"


def _timecode(index: int, fps: float) -> str:
    seconds = index / fps if fps > 0 else 0.0
    return f"{int(seconds // 60):02d}:{seconds % 60:05.2f}"


def scan_flight(
    frames: Iterable[np.ndarray],
    estimator: Estimator,
    scanner: FlightScanner,
    advance: Callable[..., None] = lambda *a, **k: None,
) -> FlightScan:
    """Feed every frame to the estimator once; each frame is judged when its estimate
    (frame t-1 -> t) arrives, which for a batching estimator may be a few frames later."""
    start = time.perf_counter()
    estimator.reset(scanner.size)
    waiting: deque[np.ndarray] = deque()
    for k, frame in enumerate(frames):
        if k == 0:
            scanner.first(frame)
        else:
            waiting.append(frame)
        for estimate in estimator.feed(frame):
            scanner.step(waiting.popleft(), estimate)
        advance(1, status=f"{len(scanner.keyframes)} keyframes")
    for estimate in estimator.finish():
        scanner.step(waiting.popleft(), estimate)
    scan = scanner.finish()
    advance(0, status=f"{len(scan.keyframes)} keyframes")  # with the last, which finish() may add
    scan.seconds = time.perf_counter() - start
    return scan


def scan_photos(photos: Iterable[np.ndarray], scanner: FlightScanner, advance: Callable[..., None] = lambda *a, **k: None) -> FlightScan:
    """A folder of photos: no estimator, each photo registered directly (see ``photo``)."""
    start = time.perf_counter()
    for photo in photos:
        scanner.photo(photo)
        advance(1, status=f"{len(scanner.keyframes)} placed")
    scan = scanner.finish()
    advance(0, status=f"{len(scan.keyframes)} placed")
    scan.seconds = time.perf_counter() - start
    return scan
