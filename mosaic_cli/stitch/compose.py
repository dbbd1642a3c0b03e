"""Stage 3b, compositing with OpenCV's ``cv2.detail``: warp each keyframe within its own
bounding box, compensate exposure and find seams on small copies, then blend (multi-band by
default) at full size.  Uncovered canvas stays transparent (alpha 0)."""

from __future__ import annotations

import functools
import uuid
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import cv2
import numpy as np

from mosaic_cli.device import check_device, resolve_device
from mosaic_cli.errors import BadInput
from mosaic_cli.geometry import normalize, project, rect_corners, resize_matrix
from mosaic_cli.mask import work_mask
from mosaic_cli.stitch.spill import Pixels, drop_pixels, load_pixels

BLENDS = ("multiband", "feather", "none")
SEAMS = {
    "dp": lambda: cv2.detail_DpSeamFinder("COLOR"),
    "graphcut": lambda: cv2.detail_GraphCutSeamFinder("COST_COLOR"),
    "voronoi": lambda: cv2.detail.SeamFinder_createDefault(cv2.detail.SeamFinder_VORONOI_SEAM),
    "none": lambda: cv2.detail.SeamFinder_createDefault(cv2.detail.SeamFinder_NO),
}
EXPOSURES = {
    "gain-blocks": cv2.detail.ExposureCompensator_GAIN_BLOCKS,
    "gain": cv2.detail.ExposureCompensator_GAIN,
    "none": cv2.detail.ExposureCompensator_NO,
}


@dataclass
class ComposeOptions:
    blend: str = "multiband"
    # Blend width, percent of a frame's geometric mean side on the canvas.  OpenStitching sizes
    # it from the whole canvas, which suits a few photos; a flight of hundreds of frames would
    # then blend over several frames' width (ghosting) with a pyramid deeper than it needs.
    blend_strength: float = 10.0
    seam: str = "dp"
    exposure: str = "gain-blocks"
    # Seams and exposure gains are found on small copies: each keyframe about this size ...
    seam_megapix: float = 0.05
    # ... and all of them together no larger than this (bounds the memory for long flights).
    seam_canvas_megapix: float = 2.0
    tile: int = 2048  # the blender works on square tiles of this side (canvas px), each with its margin
    cache_megabytes: float = 128.0  # keyframe pixels held between the tiles that reach them
    max_exposure_blocks: int = 1500  # gain-blocks solves a dense system over all blocks
    # --fill-holes: interior transparent holes (ground under a masked overlay that no keyframe
    # saw) up to this share of the covered area are inpainted; 0 leaves them transparent.
    fill_holes: float = 0.0
    # The torch device ("cuda", "cuda:1", "cpu") that warps the keyframes onto the canvas and
    # blends them (stitch/device_blend.py: OpenCV's blenders step by step); seams and
    # exposure stay on the CPU.  None: OpenCV on the CPU.  stitch sets it from --device when
    # that is a GPU; "cpu" runs the torch path on the CPU (tests).
    torch_device: str | None = None

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if self.blend not in BLENDS:
            raise BadInput(f"--blend must be one of {', '.join(BLENDS)}, got {self.blend!r}")
        if self.seam not in SEAMS:
            raise BadInput(f"--seam must be one of {', '.join(SEAMS)}, got {self.seam!r}")
        if not 0.0 <= self.fill_holes <= 1.0:
            raise BadInput(f"--fill-holes: the largest hole to fill must be a share of the panorama in 0..1, got {self.fill_holes}")
        if self.exposure not in EXPOSURES:
            raise BadInput(f"--exposure must be one of {', '.join(EXPOSURES)}, got {self.exposure!r}")
        if self.torch_device is not None:
            check_device(self.torch_device)


RowMap = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class PlacedImage:
    image: Pixels | None  # RGB uint8, in memory or spilled to a file; compose() drops it once drawn
    to_canvas: np.ndarray  # image pixels -> canvas pixels
    use: np.ndarray | None = None  # pixels to draw (uint8, 255 = use, any size of the image's aspect); None: all
    # A rolling shutter (stitch --rolling-shutter): ``to_canvas`` places the image's mid-time pose
    # and ``rows`` maps points of that pose (x, y arrays, image px) to where the image's own rows
    # have them; each canvas pixel is then sampled through both (a remap, not one homography).
    rows: RowMap | None = None
    reach: float = 0.0  # image px the rows' pixels can lie beyond the mid-time outline


@dataclass(frozen=True)
class Roi:
    x: int
    y: int
    w: int
    h: int

    @property
    def corner(self) -> tuple[int, int]:
        return (self.x, self.y)

    def scaled(self, s: float) -> Roi:
        x0, y0 = int(np.floor(self.x * s)), int(np.floor(self.y * s))
        x1, y1 = int(np.ceil((self.x + self.w) * s)), int(np.ceil((self.y + self.h) * s))
        return Roi(x0, y0, max(1, x1 - x0), max(1, y1 - y0))


def bounding_roi(H: np.ndarray, image_size: tuple[int, int], canvas_size: tuple[int, int], reach: float = 0.0) -> Roi | None:
    """The canvas pixels an image mapped by ``H`` can touch (its outline grown by ``reach``
    image px), clipped to the canvas."""
    q = project(H, rect_corners(-0.5, -0.5, *image_size))
    pad = reach * _local_scale(H, *image_size) if reach > 0 else 0.0
    x0, y0 = np.floor(q.min(axis=0) - pad + 0.5).astype(int)
    x1, y1 = np.ceil(q.max(axis=0) + pad - 0.5).astype(int)
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, canvas_size[0] - 1), min(y1, canvas_size[1] - 1)
    if x1 < x0 or y1 < y0:
        return None
    return Roi(int(x0), int(y0), int(x1 - x0 + 1), int(y1 - y0 + 1))


def warp_into(image: np.ndarray, H: np.ndarray, roi: Roi, use: np.ndarray | None = None,
              rows: RowMap | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The image and its coverage mask warped by ``H`` (image -> canvas) into ``roi`` only; the
    pixels ``use`` excludes (burned-in overlays) are not covered.  Shrinks the image first when
    the warp shrinks it, so that bilinear sampling does not alias.  ``rows`` (see
    :class:`PlacedImage`): each canvas pixel is sampled through ``H``, then through ``rows``."""
    image, S, coverage = _sampled(image, H, use)
    ones = np.full(image.shape[:2], 255, np.uint8) if coverage is None else coverage
    if rows is None:
        T = _shift(roi) @ H @ np.linalg.inv(S)
        warped = cv2.warpPerspective(image, T, (roi.w, roi.h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        mask = cv2.warpPerspective(ones, T, (roi.w, roi.h), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        return warped, mask
    u, v = _row_maps(H, S, roi, rows)
    warped = cv2.remap(image, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    mask = cv2.remap(ones, u, v, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return warped, mask


def _sampled(image: np.ndarray, H: np.ndarray, use: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The pixels a warp by ``H`` samples: the image shrunk first (``INTER_AREA``) when the warp
    shrinks it, so that bilinear sampling does not alias; ``S`` the image -> those pixels; their
    coverage (uint8, 255 = use; None: all)."""
    S = np.eye(3)
    scale = _local_scale(H, image.shape[1], image.shape[0])
    if scale < 0.8:
        size = (max(2, round(image.shape[1] * scale)), max(2, round(image.shape[0] * scale)))
        S = resize_matrix((image.shape[1], image.shape[0]), size)
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    return image, S, work_mask(use, (image.shape[1], image.shape[0]))


def _shift(roi: Roi) -> np.ndarray:
    return np.array([[1, 0, -roi.x], [0, 1, -roi.y], [0, 0, 1.0]])


def _row_maps(H: np.ndarray, S: np.ndarray, roi: Roi, rows: RowMap) -> tuple[np.ndarray, np.ndarray]:
    """The pixels (float32 (h, w) x and y, as ``cv2.remap`` takes) of the shrunk image (``S``)
    that each pixel of ``roi`` samples: canvas -> the image's mid-time pose (its pixels before
    any shrinking, ``H``) -> its rows (``rows``) -> the shrunk pixels."""
    gx, gy = np.meshgrid(np.arange(roi.w, dtype=np.float64), np.arange(roi.h, dtype=np.float64))
    Hi = np.linalg.inv(_shift(roi) @ H)
    z = Hi[2, 0] * gx + Hi[2, 1] * gy + Hi[2, 2]
    x, y = rows((Hi[0, 0] * gx + Hi[0, 1] * gy + Hi[0, 2]) / z, (Hi[1, 0] * gx + Hi[1, 1] * gy + Hi[1, 2]) / z)
    return (S[0, 0] * x + S[0, 2]).astype(np.float32), (S[1, 1] * y + S[1, 2]).astype(np.float32)


def _local_scale(H: np.ndarray, w: int, h: int) -> float:
    c = np.array([[w / 2, h / 2], [w / 2 + 1, h / 2], [w / 2, h / 2 + 1]])
    q = project(H, c)
    (ax, ay), (bx, by) = q[1] - q[0], q[2] - q[0]
    return float(np.sqrt(abs(ax * by - ay * bx)))


class MemoryCanvas:
    """The panorama held in memory, RGBA uint8 (H, W, 4): compose's sink when it is given none
    (tests, small previews, ``--fill-holes``)."""

    def __init__(self, canvas_size: tuple[int, int]):
        self.rgba = np.zeros((canvas_size[1], canvas_size[0], 4), np.uint8)

    def write(self, x: int, y: int, rgba: np.ndarray) -> None:
        self.rgba[y:y + rgba.shape[0], x:x + rgba.shape[1]] = rgba


class TileSink(Protocol):
    """Where compose puts each finished tile, RGBA uint8 (h, w, 4) at canvas pixel (x, y); a
    tile nothing covers is not written (the sink's pixels start transparent)."""

    def write(self, x: int, y: int, rgba: np.ndarray) -> None: ...


@dataclass
class ComposePlan:
    """What every tile of a canvas is blended from, decided once: the images on the canvas
    (``placed``, each with its box ``rois[k]``), their seam masks and exposure gains (found on
    small copies), the blender's settings and the tiles' side.  :func:`compose_tile` blends one
    tile from it, here or in another process (stitch/cluster.py)."""

    placed: list[PlacedImage]
    rois: list[Roi]
    seam_masks: list[np.ndarray]
    gains: list[np.ndarray] | None
    blend: _BlendPlan
    side: int
    canvas_size: tuple[int, int]
    torch_device: str | None = None
    cache_megabytes: float = 128.0
    # Names this plan among others (a worker keeps a plan's keyframes under it: ids are reused)
    token: str = field(default_factory=lambda: uuid.uuid4().hex)

    @property
    def tiles(self) -> list[tuple[int, int]]:
        """Each tile's top-left canvas pixel, row by row."""
        W, H = self.canvas_size
        return [(x0, y0) for y0 in range(0, H, self.side) for x0 in range(0, W, self.side)]

    def last_tiles(self) -> dict[int, int]:
        """Each image's last tile (its number in :attr:`tiles`): after it, its pixels can go."""
        W = self.canvas_size[0]
        return {k: _tile_number(*_reach(r, self.side, self.blend.margin, self.canvas_size)[1], W, self.side) for k, r in enumerate(self.rois)}


def plan_compose(placed: list[PlacedImage], canvas_size: tuple[int, int], options: ComposeOptions) -> ComposePlan:
    """The :class:`ComposePlan` of these images: those entirely off the canvas dropped (their
    pixels too), seams and exposure found on small copies (bounded by ``seam_megapix``)."""
    W, H = canvas_size
    # compose() is given every image with its pixels (it drops them itself): image is not None here.
    found = [bounding_roi(p.to_canvas, (p.image.shape[1], p.image.shape[0]), canvas_size, p.reach) for p in placed]  # type: ignore[union-attr]
    for k, r in enumerate(found):
        if r is None:  # entirely off the canvas
            drop_pixels(placed[k].image)
            placed[k].image = None
    placed = [p for p, r in zip(placed, found) if r is not None]
    rois = [r for r in found if r is not None]
    seam_scale = _seam_scale([r.w * r.h for r in rois], W * H, options)
    compensator, seam_masks = _seams_and_exposure(placed, rois, seam_scale, options)
    blend = _blend_plan(options, _frame_side(rois))
    return ComposePlan(placed, rois, seam_masks, compensator.getMatGains() or None, blend, _tile_side(blend, options), canvas_size,
                       options.torch_device, options.cache_megabytes)


def compose_tile(plan: ComposePlan, x0: int, y0: int, held: HeldKeyframes, device=None) -> np.ndarray | None:
    """The tile at canvas pixel (x0, y0): RGBA uint8 (h, w, 4), transparent where nothing is
    drawn; None when no image reaches it.  ``held``: the images' sources kept between tiles."""
    W, H = plan.canvas_size
    blend, side = plan.blend, plan.side
    x1, y1 = min(W, x0 + side), min(H, y0 + side)
    left, top = max(0, x0 - blend.margin), max(0, y0 - blend.margin)
    window = Roi(left, top, min(W, x1 + blend.margin) - left, min(H, y1 + blend.margin) - top)
    blender = blend.make((window.x, window.y, window.w, window.h), device)
    fed = False
    for k, roi in enumerate(plan.rois):
        part = _overlap(roi, window)
        if part is None:
            continue
        p, gain = plan.placed[k], plan.gains[k] if plan.gains else None
        if device is not None:
            source, S = held.get(k, functools.partial(_upload, p, roi, gain, plan.seam_masks[k], device))
            image, mask = _device_part(source, S, p, roi, part)
        else:
            pixels, small_seam, small_gain = held.get(k, functools.partial(_host_source, p, roi, gain, plan.seam_masks[k]))
            image, mask = _tile_part(pixels, p.to_canvas, roi, part, small_gain, _seam_at(small_seam, roi), p.use, p.rows)
        blender.feed(image, mask, part.corner)
        fed = True
    if not fed:
        return None
    result, result_mask = blender.blend(None, None)
    core = (slice(y0 - window.y, y1 - window.y), slice(x0 - window.x, x1 - window.x))
    np.clip(result, 0, 255, out=result)
    rgba = np.empty((y1 - y0, x1 - x0, 4), np.uint8)
    rgba[..., :3] = result[core]
    rgba[..., 3] = result_mask[core]
    rgba[rgba[..., 3] == 0] = 0
    return rgba


TileRunner = Callable[[ComposePlan, "TileSink", Callable[..., None]], None]


def compose(
    placed: list[PlacedImage],
    canvas_size: tuple[int, int],
    options: ComposeOptions,
    advance: Callable[..., None] = lambda *a, **k: None,
    sink: TileSink | None = None,
    runner: TileRunner | None = None,
) -> np.ndarray | None:
    """The panorama as RGBA uint8 (H, W, 4), or None when each tile went to ``sink``.

    The blender runs on square tiles of the canvas (``options.tile``), each with a margin wide
    enough for its pyramid or feather, so its memory does not grow with the canvas; the pixels
    of the images a tile reaches are held in a cache of at most ``options.cache_megabytes``
    (least recently used go first).  ``placed`` is consumed: an image's pixels are dropped
    after its last tile.  ``advance(n)`` is called with the tiles finished.  ``runner``: blends
    the plan's tiles elsewhere (stitch/cluster.py: on a Dask cluster) into ``sink``, the same
    pixels; None: here, one tile after the other."""
    plan = plan_compose(placed, canvas_size, options)
    advance(0, status="blending")
    canvas = MemoryCanvas(canvas_size) if sink is None else None
    out: TileSink = canvas if canvas is not None else sink  # type: ignore[assignment]
    if runner is not None:
        runner(plan, out, advance)
        for p in plan.placed:
            drop_pixels(p.image)
            p.image = None
        return None if canvas is None else canvas.rgba
    device = None if options.torch_device is None else resolve_device(options.torch_device)
    last = plan.last_tiles()
    held = HeldKeyframes(options.cache_megabytes)
    for number, (x0, y0) in enumerate(plan.tiles):
        rgba = compose_tile(plan, x0, y0, held, device)
        if rgba is not None:
            out.write(x0, y0, rgba)
        advance(1)
        for k in [k for k, t in last.items() if t == number]:  # its last tile: its pixels and its file go
            held.drop(k)
            drop_pixels(plan.placed[k].image)
            plan.placed[k].image = None
            del last[k]
    return None if canvas is None else canvas.rgba


def tile_count(placed: list[PlacedImage], canvas_size: tuple[int, int], options: ComposeOptions) -> int:
    """How many tiles :func:`compose` blends these images in (its progress counts them)."""
    rois = [r for p in placed if (r := bounding_roi(p.to_canvas, (p.image.shape[1], p.image.shape[0]), canvas_size, p.reach))]  # type: ignore[union-attr]
    side = _tile_side(_blend_plan(options, _frame_side(rois)), options)
    return (-(-canvas_size[0] // side)) * (-(-canvas_size[1] // side))


def _frame_side(rois: list[Roi]) -> float:
    """A keyframe's typical side on the canvas: what the blend width is a share of."""
    return float(np.sqrt(np.median([r.w * r.h for r in rois]))) if rois else 1.0


def _tile_side(blend: _BlendPlan, options: ComposeOptions) -> int:
    """Tiles start on the pyramid's grid, so that each tile decimates like the whole canvas; at
    least twice the margin wide, or the margins would cost more than the tiles."""
    side = max(64, 2 * blend.margin, options.tile)
    return -(-side // blend.unit) * blend.unit


def _overlap(a: Roi, b: Roi) -> Roi | None:
    x0, y0 = max(a.x, b.x), max(a.y, b.y)
    x1, y1 = min(a.x + a.w, b.x + b.w), min(a.y + a.h, b.y + b.h)
    return Roi(x0, y0, x1 - x0, y1 - y0) if x1 > x0 and y1 > y0 else None


def _reach(roi: Roi, side: int, margin: int, canvas_size: tuple[int, int]) -> tuple[tuple[int, int], tuple[int, int]]:
    """The tiles (column, row) whose windows (the tile and its margin) an image's box touches:
    the first and the last."""
    cols, rows = -(-canvas_size[0] // side), -(-canvas_size[1] // side)

    def span(lo: int, size: int, count: int) -> tuple[int, int]:
        # tile i's window is [i * side - margin, (i + 1) * side + margin)
        return max(0, (lo - margin) // side), min(count - 1, (lo + size - 1 + margin) // side)

    (c0, c1), (r0, r1) = span(roi.x, roi.w, cols), span(roi.y, roi.h, rows)
    return (c0, r0), (c1, r1)


def _tile_number(column: int, row: int, width: int, side: int) -> int:
    return row * (-(-width // side)) + column


class HeldKeyframes:
    """The sources of the images the recent tiles reached, at most ``megabytes`` together (the
    least recently used go first; one is always kept, however large)."""

    def __init__(self, megabytes: float):
        self.budget = megabytes * 1e6
        self.items: OrderedDict[int, tuple[Any, int]] = OrderedDict()

    def get(self, key: int, make: Callable[[], Any]) -> Any:
        if key in self.items:
            self.items.move_to_end(key)
            return self.items[key][0]
        value = make()
        size = _nbytes(value)
        while self.items and sum(s for _, s in self.items.values()) + size > self.budget:
            self.items.popitem(last=False)
        self.items[key] = (value, size)
        return value

    def drop(self, key: int) -> None:
        self.items.pop(key, None)


def _nbytes(value: Any) -> int:
    if isinstance(value, tuple):
        return sum(_nbytes(v) for v in value)
    if isinstance(value, np.ndarray):
        return value.nbytes
    return int(getattr(value, "nbytes", 0))


def _host_source(p: PlacedImage, roi: Roi, gain: np.ndarray | None, seam_mask: np.ndarray):
    """An image as its tiles read it on the CPU: its pixels, its blend mask as found on the small
    copies (dilated; each tile resizes it over the box, _seam_at: held whole, it was a third of
    what the cache held) and its exposure gain (None, a scalar or the small block map: each tile
    resizes its part)."""
    return load_pixels(p.image), cv2.dilate(seam_mask, None), gain  # type: ignore[arg-type]  # dropped only once finished


def _gain_part(gain: np.ndarray, roi: Roi, part: Roi) -> np.ndarray:
    """The ``part`` of the block gains resized over the whole box ``roi`` (bilinear at the
    resized pixel centres, edges replicated, as ``cv2.resize``), without the whole."""
    sx, sy = gain.shape[1] / roi.w, gain.shape[0] / roi.h
    x0, y0 = part.x - roi.x, part.y - roi.y
    M = np.array([[sx, 0.0, (x0 + 0.5) * sx - 0.5], [0.0, sy, (y0 + 0.5) * sy - 0.5]])
    return cv2.warpAffine(gain.astype(np.float32), M, (part.w, part.h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


def _tile_part(pixels: np.ndarray, to_canvas: np.ndarray, roi: Roi, part: Roi, gain: np.ndarray | None,
               seam: np.ndarray, use: np.ndarray | None = None, row_map: RowMap | None = None):
    """The part ``part`` (canvas pixels, within its box ``roi``) of an image: warped,
    exposure-compensated (``gain``: a scalar or a block map over the whole box, from
    ``getMatGains``) as int16 for the blender, and its blend mask (``seam``, over the whole box,
    within the image's coverage)."""
    warped, mask = warp_into(pixels, to_canvas, part, use, row_map)
    if gain is not None and gain.size == 1:
        warped = np.multiply(warped, float(gain.ravel()[0]), dtype=np.float32)
    elif gain is not None:
        warped = np.multiply(warped, _gain_part(gain, roi, part)[..., None], dtype=np.float32)
    image = np.clip(np.rint(warped), 0, 255).astype(np.int16)
    rows, cols = slice(part.y - roi.y, part.y - roi.y + part.h), slice(part.x - roi.x, part.x - roi.x + part.w)
    return image, cv2.bitwise_and(np.ascontiguousarray(seam[rows, cols]), mask)


def _seam_for(seam_mask: np.ndarray, roi: Roi) -> np.ndarray:
    """An image's blend mask at its box's full size, from its seam mask on the small copies."""
    return _seam_at(cv2.dilate(seam_mask, None), roi)


def _seam_at(dilated: np.ndarray, roi: Roi) -> np.ndarray:
    """The dilated small seam mask over the box's full size (exact fixed-point bilinear: the same
    pixels however often it is made)."""
    return cv2.resize(dilated, (roi.w, roi.h), interpolation=cv2.INTER_LINEAR_EXACT)


def _upload(p: PlacedImage, roi: Roi, gain: np.ndarray | None, seam_mask: np.ndarray, device):
    """An image put on the torch ``device`` for :func:`_device_part`: what a warp samples of it
    (:func:`_sampled`), its coverage, blend mask and gain, and its shrink ``S``."""
    from mosaic_cli.stitch.device_blend import DeviceSource

    image, S, coverage = _sampled(load_pixels(p.image), p.to_canvas, p.use)  # type: ignore[arg-type]
    return DeviceSource(image, coverage, _seam_for(seam_mask, roi), gain, device), S


def _device_part(source, S: np.ndarray, p: PlacedImage, roi: Roi, part: Roi):
    """:func:`_tile_part` on the device: (3, h, w) float image and (h, w) uint8 mask tensors."""
    box = (part.x - roi.x, part.y - roi.y, part.x - roi.x + part.w, part.y - roi.y + part.h)
    if p.rows is None:
        return source.part(box, T=_shift(part) @ p.to_canvas @ np.linalg.inv(S))
    return source.part(box, maps=_row_maps(p.to_canvas, S, part, p.rows))


def _seam_scale(areas: list[int], canvas_area: int, options: ComposeOptions) -> float:
    per_image = np.sqrt(options.seam_megapix * 1e6 / max(1.0, float(np.mean(areas))))
    whole = np.sqrt(options.seam_canvas_megapix * 1e6 / max(1.0, float(np.sum(areas))))
    return float(min(1.0, per_image, whole))


def _exposure_compensator(name: str, areas: list[int], max_blocks: int):
    """Gain blocks sized so that all images together have at most ``max_blocks`` blocks
    (OpenCV solves one dense system over every block); plain gains when even that is too many."""
    if name != "gain-blocks":
        return cv2.detail.ExposureCompensator_createDefault(EXPOSURES[name])
    per_image = min(48, max_blocks // max(1, len(areas)))
    if per_image < 4:
        return cv2.detail.ExposureCompensator_createDefault(EXPOSURES["gain"])
    side = max(16, int(np.ceil(np.sqrt(float(np.mean(areas)) / per_image))))
    return cv2.detail_BlocksGainCompensator(side, side)


def _seams_and_exposure(placed, rois, seam_scale, options):
    """Exposure gains and seam masks from small copies (bounded by ``seam_megapix``)."""
    small_rois = [r.scaled(seam_scale) for r in rois]
    S = resize_matrix((1.0, 1.0), (seam_scale, seam_scale))
    images, masks = [], []
    for p, roi in zip(placed, small_rois):
        warped, mask = warp_into(load_pixels(p.image), normalize(S @ p.to_canvas), roi, p.use, p.rows)
        images.append(warped)
        masks.append(mask)
    corners = [r.corner for r in small_rois]
    compensator = _exposure_compensator(options.exposure, [r.w * r.h for r in small_rois], options.max_exposure_blocks)
    compensator.feed(corners=corners, images=images, masks=masks)
    if len(placed) > 1:
        found = SEAMS[options.seam]().find([i.astype(np.float32) for i in images], corners, masks)
        masks = [m.get() if isinstance(m, cv2.UMat) else m for m in found]
    return compensator, masks


@dataclass
class _BlendPlan:
    kind: str
    bands: int
    width: float  # blend width, pixels
    margin: int  # pixels a tile borrows from its neighbours on each side
    unit: int = 1  # tiles start at multiples of this

    def make(self, roi: tuple[int, int, int, int], device=None):
        """The blender of a tile's window ``roi``: OpenCV's, or with a torch ``device`` its counterpart in
        device_blend.py."""
        if device is not None:
            from mosaic_cli.stitch import device_blend

            on_device: device_blend.MultiBandBlender | device_blend.FeatherBlender | device_blend.PlainBlender
            if self.kind == "multiband":
                on_device = device_blend.MultiBandBlender(self.bands, device)
            elif self.kind == "feather":
                on_device = device_blend.FeatherBlender(1.0 / self.width, device)
            else:
                on_device = device_blend.PlainBlender(device)
            on_device.prepare(roi)
            return on_device
        if self.kind == "multiband":
            blender = cv2.detail.MultiBandBlender(0, self.bands)
        elif self.kind == "feather":
            blender = cv2.detail.FeatherBlender(1.0 / self.width)
        else:
            blender = cv2.detail.Blender_createDefault(cv2.detail.Blender_NO)
        blender.prepare(roi)
        return blender


def _blend_plan(options: ComposeOptions, frame_side: float) -> _BlendPlan:
    """The blender's settings, and the margin each tile needs: the multi-band pyramid's
    reach, or the feather's width."""
    width = frame_side * options.blend_strength / 100.0
    if options.blend == "multiband" and width >= 2:
        bands = max(1, int(np.log2(width)) - 1)
        # A 5-tap Gaussian at each of the levels reaches about 2 * (1 + 2 + ... + 2^bands) pixels.
        return _BlendPlan("multiband", bands, width, 4 * 2**bands, 2**bands)
    if options.blend == "feather" and width >= 1:
        return _BlendPlan("feather", 0, width, int(np.ceil(width)) + 8)
    return _BlendPlan("none", 0, 1.0, 0)


def fill_holes(rgba: np.ndarray, max_share: float, radius: int = 5) -> int:
    """Inpaint (``cv2.inpaint``, Telea) the small interior transparent holes of a panorama
    (H, W, 4) uint8 in place; returns the pixels filled.  A hole is a connected transparent
    region (alpha 0) that touches no edge of the canvas (outside the flight is not a hole)
    and holds at most ``max_share`` of the covered pixels.  Each hole is filled from its
    surroundings within a crop around it (a panorama may be gigabytes) and made opaque."""
    if max_share <= 0:
        return 0
    H, W = rgba.shape[:2]
    empty = (rgba[..., 3] == 0).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(empty, connectivity=4)
    largest = max_share * max(1, H * W - int(np.count_nonzero(empty)))
    filled = 0
    for k in range(1, count):
        x, y, w, h, area = (int(v) for v in stats[k])
        if x == 0 or y == 0 or x + w == W or y + h == H or area > largest:
            continue
        pad = 2 * radius + 2
        x0, y0, x1, y1 = max(0, x - pad), max(0, y - pad), min(W, x + w + pad), min(H, y + h + pad)
        hole = (labels[y0:y1, x0:x1] == k).astype(np.uint8)
        crop = rgba[y0:y1, x0:x1]
        painted = cv2.inpaint(np.ascontiguousarray(crop[..., :3]), hole, radius, cv2.INPAINT_TELEA)
        inside = hole > 0
        crop[..., :3][inside] = painted[inside]
        crop[..., 3][inside] = 255
        filled += area
    return filled
