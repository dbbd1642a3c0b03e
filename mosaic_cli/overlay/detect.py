"""Burned-in overlays: find what stays put in the frame while the ground moves, and the user's
own ``--mask``, as one "use" mask (uint8, full resolution, 255 = ground to use).

Logos, OSD text, timestamps and letterbox bars do not move with the ground.  Left in, they
pull frame-to-frame estimates toward zero motion and get stitched into the panorama once per
keyframe.  The detector looks at a few dozen frames spread over the whole clip, read at up to
``trace_pixels`` (1280x720), in two passes:

1. **Regions**, on the frames scaled to a small working width (320 px), in colour:

   * static structure: at a ground pixel the image gradient points a different way in every
     sampled frame (the ground under it changes), at an overlay pixel it keeps its orientation
     (its sign flips with the ground behind the overlay's edge).  A pixel that has an edge along
     its dominant orientation in most samples (``persistence``) is static, in regions whose
     edges run more than one way (a straight road the camera follows slides along itself and
     keeps its orientation too, but only one).  Closing joins a logo's or a text line's edges
     into one region, and holes are filled (a logo's flat inside has no gradient);
   * letterbox bars: rows or columns at the frame's edges that hold one flat value in every
     sample (measured again at the read resolution).

2. **Tracing**, at the read resolution, within each region and its margin: the pixels that are
   **steady** (one colour in most samples) in colours that are far more frequent there than on
   the ground (the overlay's palette: flat ground is steady too, but in the ground's colours),
   and the pixels that show the palette's colours, in strokes, in a few samples (the glyphs of
   a running timestamp that change between samples).  A short closing and hole filling make
   them whole; the result is grown by ``smear_px`` (H.264 smears an overlay's colours a pixel
   or two past its edge) and never goes beyond the region's margin.  A region whose static
   edges the traced pixels do not explain (a semi-transparent overlay: neither steady nor of
   fixed colours) is masked whole, as the first pass found it.

When the ground hardly moves over the clip (a hovering camera) everything looks static; more
than ``max_static`` of the frame found static is taken for that and nothing is masked.

Memory: the samples are read one at a time, twice at most (:class:`VideoSamples`).  The first
read keeps them only at the working width (and the per-pixel gray range at the read
resolution, for the letterbox); the second, made only when there are regions to trace, keeps
only the crops of the regions' reaches.  The mask is the one all the samples held at once give.

:mod:`mosaic_cli.overlay.samples` reads the frames; :mod:`mosaic_cli.overlay.merge` merges the
result with the user's ``--mask`` file.
"""

from __future__ import annotations

from collections.abc import Iterable, Sized
from dataclasses import dataclass, field

import cv2
import numpy as np

from mosaic_cli.video.reader import scaled_size

PALETTE_BIN = 8  # gray levels per channel bin of the overlay's colours
PALETTE_MIN_PIXELS = 4  # steady pixels (with the bins beside theirs) that make a colour the overlay's


@dataclass
class OverlayOptions:
    samples: int = 32  # frames spread over the clip
    min_samples: int = 8  # fewer frames than this (a short photo folder): no detection
    width: int = 320  # the regions are found on the samples scaled to this width
    # A pixel is static when it has an edge of one orientation in at least this share of the
    # samples (ground: only while an edge happens to pass by).
    persistence: float = 0.7
    # Gradient (gray levels per working px) below which a sample has no edge at a pixel.
    min_gradient: float = 6.0
    close_px: int = 5  # closing radius joining an overlay's edges (working px)
    min_isotropy: float = 0.1  # a region's static edges must run more than one way (see _static_structure)
    min_area: int = 12  # static regions smaller than this (working px) are noise
    margin_px: float = 2.0  # the regions are traced this far beyond (working px)
    # The samples are read with at most this many pixels (and never above the source's size):
    # regions are found at ``width`` and traced pixel by pixel at this resolution.
    trace_pixels: int = 1280 * 720
    colour_tolerance: float = 20.0  # a sample's colour this close to the pixel's usual one is the same
    palette_ratio: float = 4.0  # the overlay's colours: this many times more frequent among steady pixels than on the ground
    min_hits: int = 2  # a pixel in the overlay's colours in at least this many samples is overlay
    hit_support: int = 3  # ... with at least this many of its 3x3 neighbours (itself included) in them too
    min_explained: float = 0.9  # a region is traced when its traced pixels explain this share of its static edges
    min_covered: float = 0.5  # ... and this share of its steady pixels (else it is masked whole)
    trace_close_px: int = 2  # closing of the traced pixels (at the trace resolution)
    smear_px: float = 2.0  # the traced mask is grown by this much (full-resolution px): H.264's colour smear
    bar_range: float = 10.0  # letterbox: an edge row/column within this gray range in every sample
    bar_ring: float = 64.0  # ... and the rows after them within this one (ringing near the bar's inner edge)
    max_bar: float = 0.25  # letterbox bars cover at most this share of each side
    max_static: float = 0.3  # more of the frame static: the ground did not move, mask nothing
    # Soft edges and codec halos (issue 40): each masked overlay is grown by as far as the
    # samples' mean still shows it beyond the mask (its soft, anti-aliased rim, H.264's halo
    # at a high crf), at most this many full-resolution px; 0: not grown.
    max_edge_px: int = 4
    # Codec halos (issue 40): each masked overlay is grown by as far as the samples' mean fine
    # detail (|Laplacian|) stays raised around it (H.264's ringing at a high crf), at most this
    # many px at the frames' read resolution; 0: not grown.
    max_halo_px: int = 16
    halo_level: float = 0.15  # the halo: detail raised by at least this share of the ground's own ...
    min_edge_area: int = 64  # full-resolution px: smaller masked specks are not grown (no ring to measure)
    # Only an overlay that hides the ground under it is grown (_hides_ground): its pixels' gray
    # range over the samples is at most this share of the ground's around it (opaque: codec
    # noise; translucent: the ground attenuated).  Grown regardless, the static blocks of ffmpeg's
    # testsrc2, which vary as much as the ground, went from 20% to 35% of the frame masked, and
    # its stitch fell apart.
    hidden_share: float = 0.8
    # ... and only one of at most this share of the frame: a logo, a watermark, an OSD box.
    max_edge_share: float = 0.1
    edge_level: float = 0.75  # gray levels: the overlay's mean contrast that still counts as its edge ...
    edge_sigmas: float = 4.0  # ... and standard errors of that mean (the ground's own noise, over the ring)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if self.samples < 4:
            raise ValueError(f"overlay detection needs at least 4 sample frames, got {self.samples}")
        if self.width < 32:
            raise ValueError(f"overlay detection width must be at least 32, got {self.width}")
        if self.trace_pixels < self.width * self.width:
            raise ValueError(f"overlay tracing needs at least {self.width}x{self.width} pixels, got {self.trace_pixels}")
        if not 1 <= self.hit_support <= 9 or self.min_hits < 1:
            raise ValueError(f"overlay hits need min_hits >= 1 and hit_support in 1..9, got {self.min_hits}, {self.hit_support}")
        if not 0.0 <= self.min_explained <= 1.0 or not 0.0 <= self.min_covered <= 1.0 or self.palette_ratio <= 0 or self.smear_px < 0 or self.trace_close_px < 0:
            raise ValueError("overlay tracing: min_explained and min_covered in [0, 1], palette_ratio > 0, smear_px and trace_close_px >= 0")


@dataclass(frozen=True)
class Letterbox:
    top: int = 0
    bottom: int = 0
    left: int = 0
    right: int = 0  # full-resolution pixels

    @property
    def any(self) -> bool:
        return bool(self.top or self.bottom or self.left or self.right)


@dataclass
class Detection:
    """What :func:`detect_overlays` found: ``use`` is None when nothing is to be excluded."""

    use: np.ndarray | None  # (h, w) uint8 full resolution, 255 = use
    letterbox: Letterbox = field(default_factory=Letterbox)
    static_fraction: float = 0.0  # of the frame, before any margin (0 when rejected)
    rejected: bool = False  # static everywhere: the ground did not move enough to tell
    samples: int = 0
    too_few: bool = False  # fewer frames than min_samples: not attempted

    @property
    def excluded(self) -> float:
        return 0.0 if self.use is None else float(np.count_nonzero(self.use == 0)) / self.use.size


def detect_overlays(frames: Iterable[np.ndarray], full_size: tuple[int, int], options: OverlayOptions | None = None) -> Detection:
    """Pure detector: ``frames`` are RGB (or gray) frames of one clip spread over it, any one
    size (regions are found at ``width``, then traced at the frames' own resolution); the mask
    comes back at ``full_size`` (w, h).  Fewer than ``min_samples`` frames (a short photo
    folder) cannot tell a fixed edge from a coincidence, nor can frames of several sizes:
    nothing is detected.

    ``frames`` is iterated twice at most, and holds one frame at a time if it can (a list, or
    :class:`VideoSamples`, which reads the frames again on each iteration).  The first pass
    keeps each frame only at the working width (and the letterbox's per-pixel gray range at the
    frames' own); the regions are found there.  Only when there are regions, and the frames
    are wider than ``width``, a second pass keeps the crops of the regions' reaches, which are
    then traced."""
    o = options or OverlayOptions()
    if isinstance(frames, Sized) and len(frames) < o.min_samples:
        return Detection(None, samples=len(frames), too_few=True)
    first = _first_pass(frames, o)
    if first is None:  # frames of several sizes (a folder of mixed photos: the reader refuses it anyway)
        return Detection(None, samples=0, too_few=True)
    work, count = first.work, len(first.work)
    if count < o.min_samples:
        return Detection(None, samples=count, too_few=True)
    fine_w, fine_h = first.size
    box = _letterbox(work, o)
    static, edges = _static_structure(work, box, o)
    fraction = float(np.count_nonzero(static)) / static.size
    rejected = fraction > o.max_static
    if rejected:
        static[:] = False
        fraction = 0.0
    # Bars found at the working width are measured again at the frames' own.
    scaled = first.gray_range is not None
    bars = _bars_at(_letterbox_of(*first.gray_range, o) if any(box) and scaled else box, (fine_w, fine_h), full_size)
    full = np.zeros((full_size[1], full_size[0]), np.uint8)
    if static.any():
        reach = _reach(static, o)
        plan = _trace_plan(static, reach, box, (fine_w, fine_h), o)
        boxes = [tuple(int(v) for v in plan.stats[k, :4]) for k in range(1, len(plan.stats))]
        # The crops of the regions' reaches, at the frames' own resolution: read again when the
        # first pass kept the frames only at the working width.
        crops = _crops(frames if scaled else work, boxes, count)
        traced = _trace(plan, crops, work, edges, o).astype(np.uint8) * 255
        if o.smear_px > 0:
            r = max(1, int(np.ceil(o.smear_px * fine_w / full_size[0])))
            traced = cv2.dilate(traced, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        # Never beyond the regions' reach: where the trace cannot tell overlay from ground
        # (flat ground around it), the mask is the region and its margin.
        full = np.minimum(_exclude_at(traced, full_size), _exclude_at(reach, full_size))
        if o.max_edge_px > 0 and first.gray_mean is not None:
            lo, hi = first.gray_range if first.gray_range is not None else (np.min(work, axis=0), np.max(work, axis=0))
            full = _grow_soft_edges(full, first.gray_mean, first.detail_mean, len(work), o, bars,
                                    (hi.astype(np.float32) - lo.astype(np.float32)))
    full[: bars.top] = 255
    full[full.shape[0] - bars.bottom :] = 255
    full[:, : bars.left] = 255
    full[:, full.shape[1] - bars.right :] = 255
    use = None if not full.any() else np.where(full > 0, 0, 255).astype(np.uint8)
    return Detection(use, bars, fraction, rejected, count)


@dataclass
class _FirstPass:
    work: list[np.ndarray]  # the samples at the working width
    size: tuple[int, int]  # (w, h) of the frames as given
    gray_range: tuple[np.ndarray, np.ndarray] | None  # per-pixel gray min and max at that size; None: work is the frames
    gray_mean: np.ndarray | None = None  # (h, w) float32 at that size: the samples' mean gray (the soft edges' evidence)
    detail_mean: np.ndarray | None = None  # (h, w) float32 at that size: the samples' mean |Laplacian| (the codec halo's evidence)


def _first_pass(frames: Iterable[np.ndarray], o: OverlayOptions) -> _FirstPass | None:
    """The samples scaled to the working width, one frame held at a time, and the per-pixel
    gray range of the frames as given (the letterbox is measured again there); None when the
    frames are not all one size."""
    work: list[np.ndarray] = []
    shape = None
    lo = hi = None
    total = detail = None
    for frame in frames:
        if shape is None:
            shape = frame.shape
        elif frame.shape != shape:
            return None
        fine_h, fine_w = shape[:2]
        gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)
        if total is None:
            total = np.zeros(gray.shape, np.float32)
            detail = np.zeros(gray.shape, np.float32)
        total += gray
        detail += np.abs(cv2.Laplacian(gray, cv2.CV_32F, borderType=cv2.BORDER_REPLICATE))
        if fine_w <= o.width:
            work.append(frame)
            continue
        work.append(cv2.resize(frame, scaled_size((fine_w, fine_h), o.width), interpolation=cv2.INTER_AREA))
        if lo is None:
            lo, hi = gray.copy(), gray.copy()
        else:
            np.minimum(lo, gray, out=lo)
            np.maximum(hi, gray, out=hi)
    if shape is None:
        return _FirstPass([], (0, 0), None)
    n = max(1, len(work))
    return _FirstPass(work, (shape[1], shape[0]), None if lo is None else (lo, hi), total / n, detail / n)


def _crops(frames: Iterable[np.ndarray], boxes: list[tuple[int, int, int, int]], count: int) -> list[np.ndarray]:
    """Per box (x, y, w, h): the (K, h, w[, c]) stack of that crop of the first ``count``
    frames, one frame held at a time.  Fewer than ``count`` when the frames, read again, end
    early or change size (a file written while it is read)."""
    stacks: list[np.ndarray] = []
    shape = None
    n = 0
    for frame in frames:
        if shape is None:
            shape = frame.shape
            stacks = [np.empty((count, h, w) + shape[2:], frame.dtype) for x, y, w, h in boxes]
        if n >= count or frame.shape != shape:
            break
        for stack, (x, y, w, h) in zip(stacks, boxes):
            stack[n] = frame[y : y + h, x : x + w]
        n += 1
    return [s[:n] for s in stacks] if stacks else [np.empty((0, h, w), np.uint8) for x, y, w, h in boxes]


def _letterbox(frames: list[np.ndarray], o: OverlayOptions) -> tuple[int, int, int, int]:
    """(top, bottom, left, right) rows/columns, at the frames' resolution, flat in every
    sample: :func:`_letterbox_of` their per-pixel gray range."""
    stack = np.stack([f if f.ndim == 2 else cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames])
    return _letterbox_of(stack.min(axis=0), stack.max(axis=0), o)


def _letterbox_of(lo: np.ndarray, hi: np.ndarray, o: OverlayOptions) -> tuple[int, int, int, int]:
    """(top, bottom, left, right) rows/columns whose per-pixel gray range over the samples
    (``lo``, ``hi``) is flat, with the rows next to them that hold within ``bar_ring`` (the
    codec rings a few rows into a bar near its inner edge, far less than the ground varies).
    Judged in gray: H.264's chroma, at half resolution, rings a few pixels into a bar."""
    lo, hi = lo.astype(np.int16), hi.astype(np.int16)
    h, w = lo.shape

    def spread(lo_line: np.ndarray, hi_line: np.ndarray) -> int:
        return int(hi_line.max()) - int(lo_line.min())

    def run(n: int, line) -> int:
        k, limit = 0, int(o.max_bar * n)
        while k < limit and spread(*line(k)) <= o.bar_range:
            k += 1
        while 0 < k < limit and spread(*line(k)) <= o.bar_ring:
            k += 1
        return k

    return (
        run(h, lambda k: (lo[k], hi[k])),
        run(h, lambda k: (lo[h - 1 - k], hi[h - 1 - k])),
        run(w, lambda k: (lo[:, k], hi[:, k])),
        run(w, lambda k: (lo[:, w - 1 - k], hi[:, w - 1 - k])),
    )


def _static_structure(frames: list[np.ndarray], box: tuple[int, int, int, int], o: OverlayOptions) -> tuple[np.ndarray, np.ndarray]:
    """(h, w) bool twice: regions of pixels whose edge keeps one orientation in every sample
    (see the module doc), with edges of several orientations, holes filled; and the static
    edge pixels inside them."""
    h, w = frames[0].shape[:2]
    # The orientation is compared through the doubled angle (gx^2 - gy^2, 2 gx gy): an overlay's
    # edge against changing ground flips its sign whenever the ground is brighter than the
    # overlay, but keeps its orientation.
    sum_a = np.zeros((h, w), np.float32)
    sum_b = np.zeros((h, w), np.float32)
    sum_e = np.zeros((h, w), np.float32)
    for frame in frames:
        a, b, e = _colour_tensor(frame)
        sum_a += a
        sum_b += b
        sum_e += e
    # Persistence: in how many samples the pixel has an edge (Sobel's 3x3 kernel has a gain of
    # 8 over a unit step per pixel) along the pixel's dominant orientation (within 20 degrees).
    # One strong edge passing by in one sample is not an overlay; a fixed edge is there in all.
    norm = np.maximum(cv2.magnitude(sum_a, sum_b), 1e-6)
    ua, ub = sum_a / norm, sum_b / norm
    strong = (8.0 * o.min_gradient) ** 2
    aligned_cos = float(np.cos(np.radians(2 * 20.0)))
    edges = np.zeros((h, w), np.uint16)
    for frame in frames:  # computed again rather than held: three float images per sample
        a, b, e = _colour_tensor(frame)  # e: the channels' mean squared gradient
        edges += ((e >= strong) & (a * ua + b * ub >= aligned_cos * e)).astype(np.uint16)
    static = edges >= o.persistence * len(frames)
    # The bars are masked on their own; their inner edge (bar against ground, blurred over a
    # pixel or two by the scaling and the Sobel) is not an overlay.
    top, bottom, left, right = (k + BAR_MARGIN if k else 0 for k in box)
    static[:top] = static[h - bottom :] = False
    static[:, :left] = static[:, w - right :] = False
    mask = static.astype(np.uint8) * 255
    if o.close_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * o.close_px + 1, 2 * o.close_px + 1))
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, k)
    regions, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    # A region is kept when it is large enough and its static edges run more than one way.  A
    # straight edge sliding along itself (a road the camera follows) keeps its orientation
    # too, but it is one orientation; logos and text have corners.  Isotropy: the ratio of the
    # small to the large eigenvalue of the region's summed structure tensor.
    inside = labels[static]
    tensor_e = np.bincount(inside, sum_e[static], regions)
    tensor_a = np.bincount(inside, sum_a[static], regions)
    tensor_b = np.bincount(inside, sum_b[static], regions)
    spread = np.hypot(tensor_a, tensor_b)
    isotropy = (tensor_e - spread) / np.maximum(tensor_e + spread, 1e-6)
    keep = (stats[:, cv2.CC_STAT_AREA] >= o.min_area) & (isotropy >= o.min_isotropy)
    keep[0] = False
    mask = np.where(keep[labels], 255, 0).astype(np.uint8)
    # Fill holes: a logo's flat inside has no gradient to be found by.
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(mask, contours, -1, 255, thickness=cv2.FILLED)
    return mask > 0, static & (mask > 0)


def _reach(regions: np.ndarray, o: OverlayOptions) -> np.ndarray:
    """uint8 (h, w), 255 = the regions (working resolution) grown by the margin: where their
    overlays' pixels are traced."""
    reach = regions.astype(np.uint8) * 255
    r = int(np.ceil(o.margin_px))
    if r > 0:
        reach = cv2.dilate(reach, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return reach


@dataclass
class _TracePlan:
    """Where the regions are traced, at the frames' resolution, before any frame is read there."""

    labels: np.ndarray  # (H, W) int32: the reaches' connected components (0: not traced)
    stats: np.ndarray  # cv2.connectedComponentsWithStats's, row k = component k (x, y, w, h, area)
    region: np.ndarray  # (H, W) bool: the regions themselves (without the margin)
    bars: np.ndarray  # (h, w) uint8 at the working resolution, 255 = the letterbox bars and their margin
    reach_work: np.ndarray  # (h, w) uint8 at the working resolution: the regions grown by the margin


def _trace_plan(regions: np.ndarray, reach_work: np.ndarray, box: tuple[int, int, int, int], fine_size: tuple[int, int],
                o: OverlayOptions) -> _TracePlan:
    """The reaches to trace at ``fine_size`` (w, h): the regions (working resolution) grown by the
    margin (``reach_work``, :func:`_reach`), less the letterbox ``box``; one component each."""
    work_h, work_w = regions.shape
    top, bottom, left, right = (k + BAR_MARGIN if k else 0 for k in box)
    bars = np.zeros((work_h, work_w), np.uint8)
    bars[:top] = bars[work_h - bottom :] = 255
    bars[:, :left] = bars[:, work_w - right :] = 255
    reach = np.minimum(_exclude_at(reach_work, fine_size), 255 - _exclude_at(bars, fine_size))
    region = _exclude_at(regions.astype(np.uint8) * 255, fine_size) > 0
    _, labels, stats, _ = cv2.connectedComponentsWithStats(reach, connectivity=8)
    return _TracePlan(labels, stats, region, bars, reach_work)


def _trace(plan: _TracePlan, crops: list[np.ndarray], work: list[np.ndarray], edges: np.ndarray, o: OverlayOptions) -> np.ndarray:
    """(H, W) bool at the frames' resolution: the overlay pixels of the regions (found in
    ``work``, the samples at the working resolution), traced pixel by pixel within each
    region's reach (``plan``; ``crops``: per reach, the samples' crop of its bounding box at the
    frames' resolution).  The ground is what lies outside the reaches and the bars.  A region
    whose traced pixels do not explain it keeps its whole reach: when they leave more than
    ``1 - min_explained`` of its static ``edges`` farther than the margin from any (an overlay
    neither steady nor of fixed colours, as some semi-transparent ones), or cover less than
    ``min_covered`` of its steady pixels (an overlay in the ground's own colours)."""
    fine_h, fine_w = plan.labels.shape
    work_h, work_w = edges.shape
    ground = _ground_colours(work, np.maximum(plan.reach_work, plan.bars))
    out = np.zeros((fine_h, fine_w), bool)
    # An edge pixel (working resolution) is explained when a traced pixel lies within the
    # margin of it: an overlay's edge runs along its border (blurred by a pixel or two).
    r = int(np.ceil(o.margin_px))
    near = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    for k, stack in enumerate(crops, start=1):
        x, y, w, h = (int(v) for v in plan.stats[k, :4])
        inside = plan.labels[y : y + h, x : x + w] == k
        if len(stack) == 0:  # the frames could not be read again: the region is masked whole
            out[y : y + h, x : x + w] |= inside
            continue
        evidence, steady = _pixel_evidence(stack, ground, o)
        traced = _closed_and_filled(evidence & inside, o.trace_close_px) & inside
        on_work = np.zeros((fine_h, fine_w), np.uint8)
        on_work[y : y + h, x : x + w] = traced * 255
        on_work = cv2.dilate(np.maximum(cv2.resize(on_work, (work_w, work_h), interpolation=cv2.INTER_AREA), plan.bars), near) > 0
        own_edges = edges & (cv2.resize(np.where(plan.labels == k, 255, 0).astype(np.uint8), (work_w, work_h), interpolation=cv2.INTER_AREA) > 0)
        explained = np.count_nonzero(own_edges & ~on_work) <= (1 - o.min_explained) * np.count_nonzero(own_edges)
        still = steady & inside & plan.region[y : y + h, x : x + w]
        covered = np.count_nonzero(still & traced) >= o.min_covered * np.count_nonzero(still)
        out[y : y + h, x : x + w] |= traced if explained and covered else inside
    return out


def _grow_soft_edges(full: np.ndarray, mean: np.ndarray, detail: np.ndarray | None, samples: int, o: OverlayOptions,
                     bars: Letterbox = Letterbox(), gray_range: np.ndarray | None = None) -> np.ndarray:
    """``full`` (uint8 (H, W), 255 = overlay) with each overlay grown over its soft edge and
    codec halo, measured: ``mean`` is the samples' mean gray (any size; scaled to ``full``'s).

    The ground moves under a static overlay, so the mean of many samples is a smooth field
    (the ground's mean, noisy by sigma / sqrt(samples)) plus what the overlay adds at each
    pixel: alpha * (its colour - the ground) on its soft rim, and the codec's halo around it.
    Per overlay (connected component), in rings of 1 px around the mask, the mean of that
    excess signed by the overlay's own contrast at the nearest masked pixel (a white logo
    lifts its rim, a dark OSD box darkens it; the ground's noise averages out) is compared
    with ``edge_level`` and ``edge_sigmas`` standard errors; the mask grows by the rings
    that still show the overlay (then one more: the last ring seen is partly beyond).  The
    field is the mean beyond ``max_edge_px``, filled in smoothly (normalised convolution).
    Ground alone grows nothing: it has no overlay to be signed by.  ``gray_range`` (the samples'
    per-pixel max - min, any size): where given, only an overlay that hides the ground under it
    (:func:`_hides_ground`) is grown; and only one of at most ``max_edge_share`` of the frame."""
    H, W = full.shape
    if (mean.shape[1], mean.shape[0]) != (W, H):
        mean = cv2.resize(mean, (W, H), interpolation=cv2.INTER_LINEAR)
    if gray_range is not None and (gray_range.shape[1], gray_range.shape[0]) != (W, H):
        gray_range = cv2.resize(gray_range, (W, H), interpolation=cv2.INTER_LINEAR)
    if detail is not None and (detail.shape[1], detail.shape[0]) != (W, H):
        detail = cv2.resize(detail, (W, H), interpolation=cv2.INTER_LINEAR)
    R = int(o.max_edge_px)
    halo_r = int(o.max_halo_px) if detail is not None else 0
    # The ground the halo is measured on: not another overlay, nor a letterbox bar or the rows
    # its own edge rings (nor the frame's outermost pixels, where the Laplacian sees the border).
    ground = full == 0
    edge = BAR_MARGIN + 2
    ground[: bars.top + edge if bars.top else 2] = False
    ground[H - (bars.bottom + edge if bars.bottom else 2) :] = False
    ground[:, : bars.left + edge if bars.left else 2] = False
    ground[:, W - (bars.right + edge if bars.right else 2) :] = False
    count, labels, stats, _ = cv2.connectedComponentsWithStats((full > 0).astype(np.uint8), connectivity=8)
    out = full.copy()
    for k in range(1, count):
        x, y, w, h = (int(v) for v in stats[k, :4])
        if not o.min_edge_area <= stats[k, cv2.CC_STAT_AREA] <= o.max_edge_share * H * W:
            continue
        pad = max(2 * R + 8, halo_r + HALO_FIELD[1] + 2)
        x0, y0, x1, y1 = max(0, x - pad), max(0, y - pad), min(W, x + w + pad), min(H, y + h + pad)
        inside = labels[y0:y1, x0:x1] == k
        m = mean[y0:y1, x0:x1]
        dist = cv2.distanceTransform(np.where(inside, 0, 255).astype(np.uint8), cv2.DIST_L2, 5)
        # The contrast is read a smear deeper than the mask's edge: the mask was grown over the
        # codec's smear, and the ground there would sign its own neighbours (a bias, not an edge).
        e = int(np.ceil(o.smear_px)) + 1
        core = cv2.erode(inside.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * e + 1, 2 * e + 1))) > 0
        if not core.any():
            core = inside
        if gray_range is not None and not _hides_ground(gray_range[y0:y1, x0:x1], core, dist, ground[y0:y1, x0:x1], o):
            continue  # it varies as the ground does: no overlay over it
        _, nearest = cv2.distanceTransformWithLabels(np.where(core, 0, 255).astype(np.uint8), cv2.DIST_L2, 5,
                                                     labelType=cv2.DIST_LABEL_PIXEL)
        field_ring = (dist > R) & (dist <= 2 * R + 8)
        if np.count_nonzero(field_ring) < 16:
            continue
        sigma = max(2.0, R / 2)
        weight = cv2.GaussianBlur(field_ring.astype(np.float32), (0, 0), sigma)
        field = cv2.GaussianBlur(m * field_ring, (0, 0), sigma) / np.maximum(weight, 1e-6)
        excess = m - field
        # The overlay's contrast at each masked pixel, carried out to the pixels nearest it.
        sign_of = np.zeros(int(nearest.max()) + 1, np.float32)
        sign_of[nearest[core]] = np.sign(excess[core])
        signed = excess * sign_of[nearest]
        grow, before = 0, np.inf
        for d in range(1, R + 1):
            ring = (dist > d - 1) & (dist <= d)
            n = np.count_nonzero(ring)
            if n < 8:
                break
            values = signed[ring]
            level = float(values.mean())
            error = float(values.std()) / np.sqrt(n)
            # An overlay's edge fades outward; a ring brighter than the one inside it is the ground's own structure.
            if level < max(o.edge_level, o.edge_sigmas * error) or level > before + o.edge_sigmas * error:
                break
            grow, before = d, level
        if grow:
            grow = min(R, grow + 1)
        if grow and halo_r:
            # A soft-edged overlay (its rim shows in the mean): the codec halo around it too.
            # A hard-edged opaque one (a logo, a timestamp) is left to smear_px.
            grow = max(grow, _halo_rings(detail[y0:y1, x0:x1], dist, ground[y0:y1, x0:x1], halo_r, o))
        if grow:
            grown = dist <= grow
            out[y0:y1, x0:x1][grown] = 255
    return out


def _hides_ground(gray_range: np.ndarray, core: np.ndarray, dist: np.ndarray, ground: np.ndarray, o: OverlayOptions) -> bool:
    """Whether an overlay hides the ground under it: the samples' gray range (per-pixel
    max - min, a crop) in its ``core`` has a median of at most ``hidden_share`` of the ground's,
    8-24 px around it.  Measured at 320x180 and 1280x720: a watermark at 0.5 opacity 40 against
    86 levels, an OSD box at 0.6 36 against 103, an opaque one codec noise (8); ffmpeg's
    testsrc2, whose static blocks the detector also masks, 140 against 125."""
    ring = (dist > 8) & (dist <= 24) & ground
    if np.count_nonzero(ring) < 16:
        return False
    return float(np.median(gray_range[core])) <= o.hidden_share * float(np.median(gray_range[ring]))


HALO_FIELD = (8, 32)  # the ground's own detail is measured this far beyond max_halo_px (px, after the noise rings)


def _halo_rings(detail: np.ndarray, dist: np.ndarray, ground: np.ndarray, R: int, o: OverlayOptions) -> int:
    """How many px of codec halo lie around one overlay (``dist``: each pixel's distance from
    its mask, in the crop of ``detail``, the samples' mean |Laplacian|); 0 when none shows.

    H.264 quantises an overlay's edge with the ground behind it: ringing and deblocking add
    fine detail a block or so past the edge, whatever the ground, while the ground moves on.
    So the mean |Laplacian| of many samples is a smooth field (the ground's mean detail), raised
    near the overlay as far as its halo reaches.  The field is the mean detail
    ``R + HALO_FIELD[0]`` to ``R + HALO_FIELD[1]`` px beyond the mask, filled in smoothly
    (normalised convolution); the rings 1 px wide from ``R`` to ``R + HALO_FIELD[0]`` measure
    how far that fill is off on ground alone (the noise: their RMS relative excess).  The mask
    grows by the rings, from the inside, whose relative excess stays above ``halo_level`` and
    ``edge_sigmas`` times that noise (then one more: the last ring seen is partly beyond), at
    most ``R``.  An overlay with no halo (a hard edge at a low crf) grows nothing."""
    near, far = R + HALO_FIELD[0], R + HALO_FIELD[1]
    band = (dist > near) & (dist <= far) & ground
    if np.count_nonzero(band) < 64:
        return 0
    sigma = max(2.0, R / 2)
    weight = cv2.GaussianBlur(band.astype(np.float32), (0, 0), sigma)
    field = cv2.GaussianBlur(detail * band, (0, 0), sigma) / np.maximum(weight, 1e-6)
    levels = []
    for d in range(1, near + 1):
        ring = (dist > d - 1) & (dist <= d) & ground & (weight > 1e-3)
        expected = float(field[ring].sum()) if np.count_nonzero(ring) >= 8 else 0.0
        levels.append(float(detail[ring].sum()) / expected - 1.0 if expected > 0 else np.nan)
    # The noise: how much one ring's level differs from the next's on the ground beyond R
    # (a smooth field fills in smoothly; what is left from ring to ring is the samples' noise).
    steps = np.diff(np.array(levels[R - 1 : near]))
    steps = steps[np.isfinite(steps)]
    noise = float(np.sqrt(np.mean(steps**2) / 2)) if len(steps) >= 3 else np.inf
    threshold = max(o.halo_level, o.edge_sigmas * noise)
    grow, before = 0, np.inf
    for d in range(1, R + 1):
        level = levels[d - 1]
        if not np.isfinite(level) or level < threshold or level > before + threshold:
            break
        grow, before = d, level
    return min(R, grow + 1) if grow else 0


def _closed_and_filled(mask: np.ndarray, radius: int) -> np.ndarray:
    """bool ``mask`` closed with a disc of ``radius`` px (nothing beyond its border), its holes
    filled."""
    out = mask.astype(np.uint8) * 255
    if radius > 0 and out.any():
        out = cv2.copyMakeBorder(out, radius, radius, radius, radius, cv2.BORDER_CONSTANT, value=0)
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
        out = cv2.morphologyEx(out, cv2.MORPH_CLOSE, disc)[radius:-radius, radius:-radius].copy()
    contours, _ = cv2.findContours(out, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, contours, -1, 255, thickness=cv2.FILLED)
    return out > 0


def _ground_colours(work: list[np.ndarray], not_ground: np.ndarray) -> np.ndarray:
    """Flat float over the colour bins (``PALETTE_BIN`` levels per channel, each with the bins
    beside it): the share of the ground's pixels (where ``not_ground`` is 0, in every other
    sample) of each colour."""
    channels = 1 if work[0].ndim == 2 else work[0].shape[2]
    bins = 256 // PALETTE_BIN
    counts = np.zeros(bins**channels, np.float64)
    outside = not_ground == 0
    for frame in work[::2]:
        counts += np.bincount(_colour_bin(frame)[outside], minlength=counts.size)
    return _spread_bins(counts, channels) / max(1.0, counts.sum())


def _spread_bins(counts: np.ndarray, channels: int) -> np.ndarray:
    """Flat counts over colour bins, each summed with the bins beside it (3 per channel): a
    colour on a bin's border, compression noise."""
    bins = 256 // PALETTE_BIN
    out = counts.reshape((bins,) * channels)
    for axis in range(channels):
        spread = out.copy()
        lower, upper = [slice(None)] * channels, [slice(None)] * channels
        lower[axis], upper[axis] = slice(None, -1), slice(1, None)
        spread[tuple(lower)] += out[tuple(upper)]
        spread[tuple(upper)] += out[tuple(lower)]
        out = spread
    return out.ravel()


def _colour_bin(image: np.ndarray) -> np.ndarray:
    """(h, w) intp: each pixel's colour bin (``PALETTE_BIN`` levels per channel)."""
    bins = 256 // PALETTE_BIN
    if image.ndim == 2:
        return (image // PALETTE_BIN).astype(np.intp)
    index = np.zeros(image.shape[:2], np.intp)
    for c in range(image.shape[2]):
        index = index * bins + (image[..., c] // PALETTE_BIN)
    return index


def _pixel_evidence(stack: np.ndarray, ground: np.ndarray, o: OverlayOptions) -> tuple[np.ndarray, np.ndarray]:
    """(h, w) bool twice: the pixels of a crop (``stack``: K samples, RGB or gray) that show an
    overlay, and the steady ones (in any colour).

    The overlay's colours (its palette) are those of the crop's **steady** pixels (one colour
    in ``persistence`` of the samples) that are ``palette_ratio`` times more frequent among
    them than on the ground (``ground``: shares per colour bin); flat ground is steady too, but
    in the ground's own colours.  A pixel is overlay when it is steady in a palette colour (a
    logo, the glyphs of a text that do not change), or shows palette colours, in strokes, in at
    least ``min_hits`` samples (glyphs that change, as a running timestamp's digits)."""
    k = len(stack)
    if stack.ndim == 3:
        stack = stack[..., None]
    h, w, channels = stack.shape[1:]
    # The pixel's usual colour: the median of its samples, channel by channel.
    middle = k // 2
    typical = np.partition(np.ascontiguousarray(stack.reshape(k, -1).T), middle, axis=1)[:, middle].reshape(h, w, channels)
    steady_count = np.zeros((h, w), np.uint16)
    for frame in stack:
        steady_count += _channel_max(cv2.absdiff(frame, typical)) <= o.colour_tolerance
    steady = steady_count >= o.persistence * k
    if not steady.any():
        return steady, steady
    usual = _colour_bin(typical)
    counts = _spread_bins(np.bincount(usual[steady], minlength=ground.size).astype(np.float64), channels)
    palette = (counts >= o.palette_ratio * ground * counts.sum()) & (counts >= PALETTE_MIN_PIXELS)
    evidence = steady & palette[usual]
    hits = np.zeros((h, w), np.uint16)
    box = np.ones((3, 3), np.uint8)
    for frame in stack:
        inked = palette[_colour_bin(frame)].view(np.uint8)
        if o.hit_support > 1:
            # A glyph is a stroke: a lone pixel of ground in one of the overlay's colours is not.
            support = cv2.filter2D(inked, -1, box, borderType=cv2.BORDER_REPLICATE)
            inked = inked & (support >= o.hit_support)
        hits += inked
    return evidence | (hits >= o.min_hits), steady


def _channel_max(image: np.ndarray) -> np.ndarray:
    """The largest channel value of each pixel of an (h, w, c) uint8 image."""
    if image.ndim == 2 or image.shape[2] == 1:
        return image.reshape(image.shape[:2])
    out = image[..., 0].copy()
    for c in range(1, image.shape[2]):
        np.maximum(out, image[..., c], out=out)
    return out


def _colour_tensor(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The doubled-angle gradient (gx^2 - gy^2, 2 gx gy) and the squared gradient, averaged over
    the colour channels: a magenta logo on green fields of the same gray level has edges too."""
    smooth = cv2.GaussianBlur(frame, (0, 0), 0.8).astype(np.float32)  # compression noise is not structure
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE)
    xx, yy, xy = gx * gx, gy * gy, gx * gy
    if frame.ndim == 3:
        mean = np.full((1, frame.shape[2]), 1.0 / frame.shape[2], np.float32)
        xx, yy, xy = cv2.transform(xx, mean), cv2.transform(yy, mean), cv2.transform(xy, mean)
    return xx - yy, 2.0 * xy, xx + yy


def _exclude_at(exclude: np.ndarray, full_size: tuple[int, int]) -> np.ndarray:
    """The working-size exclusion scaled to ``full_size``, conservatively: a full-resolution
    pixel is excluded when any part of it touches an excluded working pixel."""
    if (exclude.shape[1], exclude.shape[0]) == tuple(full_size):
        return exclude.copy()
    up = cv2.resize(exclude, tuple(full_size), interpolation=cv2.INTER_LINEAR)
    return np.where(up > 0, 255, 0).astype(np.uint8)


BAR_MARGIN = 2


def _bars_at(box: tuple[int, int, int, int], work: tuple[int, int], full_size: tuple[int, int]) -> Letterbox:
    """Bars in working px -> full-resolution px, rounded outward and grown by ``BAR_MARGIN``
    working px: the codec rings a row or two across the bar's edge, which then is not flat."""
    top, bottom, left, right = box
    sx, sy = full_size[0] / work[0], full_size[1] / work[1]

    def up(n: int, s: float, limit: int) -> int:
        return 0 if n == 0 else min(limit, int(np.ceil((n + BAR_MARGIN) * s)))

    return Letterbox(up(top, sy, full_size[1]), up(bottom, sy, full_size[1]), up(left, sx, full_size[0]), up(right, sx, full_size[0]))


__all__ = ["Detection", "Letterbox", "OverlayOptions", "detect_overlays"]
