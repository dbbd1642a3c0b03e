"""Stage 3b, compositing with OpenCV's ``cv2.detail``: warp each keyframe within its own
bounding box, compensate exposure and find seams on small copies, then blend (multi-band by
default) at full size.  Uncovered canvas stays transparent (alpha 0)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

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
    strip_megapix: float = 4.0  # the blender works on horizontal strips of about this size
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


def compose(
    placed: list[PlacedImage],
    canvas_size: tuple[int, int],
    options: ComposeOptions,
    advance: Callable[..., None] = lambda *a, **k: None,
) -> np.ndarray:
    """The panorama as RGBA uint8 (H, W, 4).

    The blender runs on horizontal strips of the canvas (``strip_megapix``), each with a
    margin wide enough for its pyramid or feather, so its memory does not grow with the
    canvas; ``placed`` is consumed: an image's pixels are dropped after its last strip.
    ``advance(n)`` is called with the canvas rows finished, strip by strip."""
    W, H = canvas_size
    # compose() is given every image with its pixels (it drops them itself): image is not None here.
    found = [bounding_roi(p.to_canvas, (p.image.shape[1], p.image.shape[0]), canvas_size, p.reach) for p in placed]  # type: ignore[union-attr]
    keep = [k for k, r in enumerate(found) if r is not None]
    for k, r in enumerate(found):
        if r is None:  # entirely off the canvas
            drop_pixels(placed[k].image)
            placed[k].image = None
    placed = [placed[k] for k in keep]
    rois = [r for r in found if r is not None]
    seam_scale = _seam_scale([r.w * r.h for r in rois], W * H, options)
    compensator, seam_masks = _seams_and_exposure(placed, rois, seam_scale, options)
    advance(0, status="blending")
    blend = _blend_plan(options, float(np.sqrt(np.median([r.w * r.h for r in rois]))) if rois else 1.0)
    device = None if options.torch_device is None else resolve_device(options.torch_device)
    rgba = np.zeros((H, W, 4), np.uint8)
    # Strips start on the pyramid's grid, so that each strip decimates like the whole canvas.
    # At least twice the margin tall, or the margins would cost more than the strips.
    strip = max(64, 2 * blend.margin, int(options.strip_megapix * 1e6 / W))
    strip = -(-strip // blend.unit) * blend.unit
    # Each strip warps just the rows of each image it needs: no image is ever held warped in
    # full, so the memory stays bounded however the flight lies on the canvas.
    gains = compensator.getMatGains()
    finished: set[int] = set()
    # The pixels of the images the current strip reaches: arrays, or (torch_device) each image
    # on the device as it is sampled, uploaded once for all its strips, with its shrink ``S``.
    loaded: dict[int, Any] = {}
    for y0 in range(0, H, strip):
        y1 = min(H, y0 + strip)
        top, bottom = max(0, y0 - blend.margin), min(H, y1 + blend.margin)
        blender = blend.make((0, top, W, bottom - top), device)
        fed = False
        for k, roi in enumerate(rois):
            if k in finished or roi.y >= bottom or roi.y + roi.h <= top:
                continue
            rows = (max(top, roi.y) - roi.y, min(bottom, roi.y + roi.h) - roi.y)
            gain = gains[k] if gains else None
            if device is not None:
                if k not in loaded:
                    loaded[k] = _upload(placed[k], roi, gain, seam_masks[k], device)
                source, S = loaded[k]
                image, mask = _device_part(source, S, placed[k], roi, rows)
            else:
                if k not in loaded:
                    loaded[k] = load_pixels(placed[k].image)  # type: ignore[arg-type]  # dropped only once finished
                image, mask = _strip_part(loaded[k], placed[k].to_canvas, roi, rows, gain, seam_masks[k], placed[k].use, placed[k].rows)
            blender.feed(image, mask, (roi.x, roi.y + rows[0]))
            fed = True
        if fed:
            result, result_mask = blender.blend(None, None)
            band = slice(y0 - top, y1 - top)
            np.clip(result, 0, 255, out=result)
            out = rgba[y0:y1]
            out[..., :3] = result[band, :W]
            out[..., 3] = result_mask[band, :W]
            out[out[..., 3] == 0] = 0
            del result, result_mask
        del blender
        advance(y1 - y0)
        # An image that the next strip (its margin included) does not reach is done.
        next_top = y1 - blend.margin
        for k, roi in enumerate(rois):
            if k not in finished and (y1 >= H or roi.y + roi.h <= next_top):
                finished.add(k)
                loaded.pop(k, None)
                drop_pixels(placed[k].image)
                placed[k].image = None
    return rgba


def _strip_part(pixels: np.ndarray, to_canvas: np.ndarray, roi: Roi, rows: tuple[int, int], gain: np.ndarray | None,
                seam_mask: np.ndarray, use: np.ndarray | None = None, row_map: RowMap | None = None):
    """Rows ``rows`` (of its bounding box ``roi``) of an image: warped, exposure-compensated
    (``gain``: a scalar or a block map over the whole box, from ``getMatGains``) as int16 for
    the blender, and its blend mask (the seam mask within the image's coverage)."""
    r0, r1 = rows
    part = Roi(roi.x, roi.y + r0, roi.w, r1 - r0)
    warped, mask = warp_into(pixels, to_canvas, part, use, row_map)
    if gain is not None and gain.size == 1:
        warped = np.multiply(warped, float(gain.ravel()[0]), dtype=np.float32)
    elif gain is not None:
        full = cv2.resize(gain.astype(np.float32), (roi.w, roi.h), interpolation=cv2.INTER_LINEAR)
        warped = np.multiply(warped, full[r0:r1, :, None], dtype=np.float32)
    image = np.clip(np.rint(warped), 0, 255).astype(np.int16)
    seam = _seam_for(seam_mask, roi)[r0:r1]
    return image, cv2.bitwise_and(seam, mask)


def _seam_for(seam_mask: np.ndarray, roi: Roi) -> np.ndarray:
    """An image's blend mask at its box's full size, from its seam mask on the small copies."""
    return cv2.resize(cv2.dilate(seam_mask, None), (roi.w, roi.h), interpolation=cv2.INTER_LINEAR_EXACT)


def _upload(p: PlacedImage, roi: Roi, gain: np.ndarray | None, seam_mask: np.ndarray, device):
    """An image put on the torch ``device`` for :func:`_device_part`: what a warp samples of it
    (:func:`_sampled`), its coverage, blend mask and gain, and its shrink ``S``."""
    from mosaic_cli.stitch.device_blend import DeviceSource

    image, S, coverage = _sampled(load_pixels(p.image), p.to_canvas, p.use)  # type: ignore[arg-type]
    return DeviceSource(image, coverage, _seam_for(seam_mask, roi), gain, device), S


def _device_part(source, S: np.ndarray, p: PlacedImage, roi: Roi, rows: tuple[int, int]):
    """:func:`_strip_part` on the device: (3, h, w) float image and (h, w) uint8 mask tensors."""
    part = Roi(roi.x, roi.y + rows[0], roi.w, rows[1] - rows[0])
    if p.rows is None:
        return source.part(rows, T=_shift(part) @ p.to_canvas @ np.linalg.inv(S))
    return source.part(rows, maps=_row_maps(p.to_canvas, S, part, p.rows))


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
    margin: int  # rows a strip borrows from its neighbours
    unit: int = 1  # strips start at multiples of this

    def make(self, roi: tuple[int, int, int, int], device=None):
        """The blender of a strip ``roi``: OpenCV's, or with a torch ``device`` its counterpart in
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
    """The blender's settings, and the margin each strip needs: the multi-band pyramid's
    reach, or the feather's width."""
    width = frame_side * options.blend_strength / 100.0
    if options.blend == "multiband" and width >= 2:
        bands = max(1, int(np.log2(width)) - 1)
        # A 5-tap Gaussian at each of the levels reaches about 2 * (1 + 2 + ... + 2^bands) rows.
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
