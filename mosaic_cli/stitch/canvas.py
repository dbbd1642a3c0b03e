"""Stage 3a, the canvas: which keyframe the panorama is drawn in, how large it is, and
whether the placements are sane enough to draw at all."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.geometry import frame_corners, is_valid, normalize, project

MIN_SIZE = 64  # --max-size: a smaller panorama shows nothing


@dataclass
class CanvasOptions:
    reference: str = "middle"  # first | middle | a frame number
    # Longest side of the panorama, pixels; None: every pixel the keyframes hold (the canvas is
    # composed tile by tile on disk, so its size costs no memory).
    max_size: int | None = None
    # A map's ground resolution, metres per pixel (--gsd, with telemetry); None: the footage's own.
    gsd: float | None = None
    # A keyframe drawn larger/smaller than this (area ratio) against the reference is a sign
    # of a degenerate chain, not of a real change of altitude.
    max_area_ratio: float = 25.0

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        parse_reference(self.reference)
        if self.max_size is not None and self.max_size < MIN_SIZE:
            raise BadInput(f"--max-size must be at least {MIN_SIZE} pixels, got {self.max_size}")
        if self.gsd is not None and not (np.isfinite(self.gsd) and self.gsd > 0):
            raise BadInput(f"--gsd must be a ground distance above 0 (5cm, 0.05m), got {self.gsd}")


@dataclass
class Canvas:
    size: tuple[int, int]  # (W, H)
    to_canvas: np.ndarray  # reference frame source pixels -> panorama pixels
    scale: float  # panorama pixels per reference-frame pixel
    native_size: tuple[int, int] | None = None  # (W, H) at one panorama pixel per reference-frame pixel (scale 1)
    shrunk_by: str | None = None  # what scaled it down (an option, as the user reads it), if anything did

    def frame_to_canvas(self, placement: np.ndarray) -> np.ndarray:
        return normalize(self.to_canvas @ placement)


def parse_reference(spec: str) -> str | int:
    """'first', 'middle' or a frame number; BadInput for anything else."""
    text = str(spec).strip().lower()
    if text in ("first", "middle"):
        return text
    try:
        value = int(text)
    except ValueError:
        raise BadInput(f"--reference must be first, middle or a frame number, got {spec!r}") from None
    if value < 0:
        raise BadInput(f"--reference frame must be 0 or more, got {value}")
    return value


def choose_reference(frame_indices: list[int], spec: str | int, last_frame: int) -> int:
    """Position (in ``frame_indices``) of the reference keyframe: for a frame number, the
    keyframe nearest to it.  The middle one by default: distortion grows with the distance
    from the reference, so the middle halves the worst."""
    if spec == "first":
        return 0
    if spec == "middle":
        return (len(frame_indices) - 1) // 2
    assert isinstance(spec, (int, np.integer))  # parse_reference gives first, middle or a frame number
    if spec > last_frame:
        raise BadInput(f"--reference {spec} is past the last frame stitched ({last_frame})")
    return int(np.argmin(np.abs(np.asarray(frame_indices) - spec)))


def plan_canvas(
    placements: list[np.ndarray],
    frame_indices: list[int],
    size: tuple[int, int],
    options: CanvasOptions,
    drawn: list[bool] | None = None,
    gsd: float | None = None,
    limit: str | None = None,
) -> Canvas:
    """Bounding box of the ``drawn`` frames (default all), scaled down to ``options.gsd`` when
    the placements are ground pixels of ``gsd`` metres, and to ``options.max_size`` (``limit``:
    how to name that bound, when not --max-size); refuses degenerate placements of any frame
    (folded, behind the camera or blown up) with advice."""
    for H, index in zip(placements, frame_indices):
        if not is_valid(H, size, max_area_ratio=options.max_area_ratio):
            raise ProcessingError(
                f"the placement of frame {index} degenerates (folded, behind the camera, or more than "
                f"{options.max_area_ratio:.0f}x larger or smaller than the reference frame), so the canvas "
                f"would explode; the estimator lost track: try a --reference near that frame, a shorter part "
                f"(--start/--max-frames), or another --estimator"
            )
    drawn = [True] * len(placements) if drawn is None else drawn
    corners = np.concatenate([project(H, frame_corners(*size)) for H, d in zip(placements, drawn) if d])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    extent = hi - lo
    scale, shrunk_by = 1.0, None
    if gsd is not None and options.gsd is not None and options.gsd > gsd:
        scale, shrunk_by = gsd / options.gsd, f"--gsd {format_distance(options.gsd)}"
    if options.max_size and extent.max() * scale > options.max_size:
        scale, shrunk_by = options.max_size / float(extent.max()), limit or f"--max-size {options.max_size}"
    width = max(1, int(np.ceil(extent[0] * scale - 1e-6)))
    height = max(1, int(np.ceil(extent[1] * scale - 1e-6)))
    # Outer frame edges sit at pixel -0.5; the canvas' first pixel centre at its edge + 0.5.
    to_canvas = np.array([[scale, 0, -scale * lo[0] - 0.5], [0, scale, -scale * lo[1] - 0.5], [0, 0, 1.0]])
    native = (max(1, int(np.ceil(extent[0] - 1e-6))), max(1, int(np.ceil(extent[1] - 1e-6))))
    return Canvas((width, height), to_canvas, scale, native, shrunk_by)


def parse_distance(text: str) -> float:
    """A ground distance in metres from ``5cm``, ``0.05m``, ``50mm`` or ``0.05`` (metres)."""
    value = str(text).strip().lower().replace(" ", "")
    for unit, factor in (("mm", 1e-3), ("cm", 1e-2), ("m", 1.0)):
        if value.endswith(unit):
            value, scale = value[: -len(unit)], factor
            break
    else:
        scale = 1.0
    try:
        metres = float(value) * scale
    except ValueError:
        raise BadInput(f"--gsd must be a ground distance such as 5cm, 0.05m or 50mm, got {text!r}") from None
    if not (np.isfinite(metres) and metres > 0):
        raise BadInput(f"--gsd must be a ground distance above 0, got {text!r}")
    return metres


def format_distance(metres: float) -> str:
    return f"{metres * 100:g}cm" if metres < 1 else f"{metres:g}m"
