"""Burned-in overlays for simulated flights: a static logo, a running timestamp and black
letterbox bars, drawn into every rendered frame at fixed frame positions, as drone apps and
video editors burn them in.  The exact pixels drawn are known, so a detector (and a stitch
that must keep them out of the panorama) can be scored against them.

    spec = OverlaySpec.parse("logo,timestamp,letterbox")
    burner = OverlayBurner(spec, (1280, 720), fps=30.0)
    frame = burner.draw(frame, t)          # RGB uint8, drawn in place of the ground
    burner.drawn                           # (h, w) bool: every pixel drawn in some frame so far

Colours are chosen saturated (magenta logo, yellow text with a black outline) so that a test
can check that none of them reaches a panorama of a map that has no such colours.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.errors import BadInput

KINDS = ("logo", "timestamp", "letterbox")
LOGO_RGB = (255, 0, 255)  # magenta: a colour the procedural map never has
TEXT_RGB = (255, 255, 0)  # yellow
OUTLINE_RGB = (0, 0, 0)


@dataclass(frozen=True)
class OverlaySpec:
    logo: bool = False
    timestamp: bool = False
    letterbox: bool = False
    logo_width: float = 0.12  # of the frame width, top-left corner
    text_height: float = 0.045  # timestamp cap height, of the frame height, bottom-right
    bar_height: float = 0.08  # letterbox bars, of the frame height, top and bottom
    start_seconds: int = 12 * 3600 + 34 * 60 + 50  # the clock at frame 0 (12:34:50)

    @staticmethod
    def parse(text: str | None) -> OverlaySpec:
        """``"logo,timestamp"``, ``"all"`` or ``"none"``/``""`` (nothing)."""
        names = [n.strip().lower() for n in (text or "").split(",") if n.strip()]
        if names == ["all"]:
            names = list(KINDS)
        if names == ["none"]:
            names = []
        unknown = [n for n in names if n not in KINDS]
        if unknown:
            raise BadInput(f"--overlays: unknown overlay {unknown[0]!r} (choose from {', '.join(KINDS)}, or all)")
        return OverlaySpec(**{n: True for n in names})

    @property
    def any(self) -> bool:
        return self.logo or self.timestamp or self.letterbox

    @property
    def names(self) -> list[str]:
        return [k for k in KINDS if getattr(self, k)]


class OverlayBurner:
    """Draws the overlays of ``spec`` into frames of ``size`` (w, h) and remembers which pixels
    it drew (``drawn``: the union over every frame drawn so far)."""

    def __init__(self, spec: OverlaySpec, size: tuple[int, int], fps: float):
        self.spec = spec
        self.size = (int(size[0]), int(size[1]))
        self.fps = float(fps) if fps > 0 else 30.0
        w, h = self.size
        self.drawn = np.zeros((h, w), bool)
        self._text_drawn = np.zeros((h, w), bool)
        self._static_rgb = np.zeros((h, w, 3), np.uint8)
        self._static = np.zeros((h, w), bool)
        self._bars = np.zeros((h, w), bool)
        self._logo = np.zeros((h, w), bool)
        if spec.letterbox:
            bar = max(1, round(spec.bar_height * h))
            self._bars[:bar] = self._bars[h - bar :] = True  # black: the RGB is already 0
            self._static |= self._bars
        if spec.logo:
            self._draw_logo()
        self.drawn |= self._static
        # The timestamp: a fixed font size, placed right-aligned at the widest text it shows.
        self._font = cv2.FONT_HERSHEY_DUPLEX
        cap = max(6.0, spec.text_height * h)
        self._scale = cap / 22.0  # Hershey duplex caps are ~22 px tall at scale 1
        self._thick = max(1, round(self._scale * 1.5))
        (tw, th), base = cv2.getTextSize("00:00:00.00", self._font, self._scale, self._thick)
        margin = round(0.02 * w)
        bottom = h - (round(spec.bar_height * h) if spec.letterbox else 0)
        self._origin = (w - margin - tw, bottom - margin - base)

    def _draw_logo(self) -> None:
        w, h = self.size
        side = max(8, round(self.spec.logo_width * w))
        x0 = round(0.03 * w)
        y0 = x0 + (round(self.spec.bar_height * h) if self.spec.letterbox else 0)  # below a letterbox bar
        lh = max(6, round(side * 0.5))
        layer = np.zeros((h, w), np.uint8)
        cv2.rectangle(layer, (x0, y0), (x0 + side - 1, y0 + lh - 1), 255, thickness=-1)
        self._static_rgb[layer > 0] = LOGO_RGB
        # A white "M" inside (structure a detector can latch on, as a real logo has).
        glyph = np.zeros_like(layer)
        scale = lh / 30.0
        (gw, gh), _ = cv2.getTextSize("M", cv2.FONT_HERSHEY_SIMPLEX, scale, max(1, round(scale * 2)))
        org = (x0 + (side - gw) // 2, y0 + (lh + gh) // 2)
        cv2.putText(glyph, "M", org, cv2.FONT_HERSHEY_SIMPLEX, scale, 255, max(1, round(scale * 2)), cv2.LINE_AA)
        inside = (glyph > 127) & (layer > 0)
        self._static_rgb[inside] = (255, 255, 255)
        self._logo = layer > 0
        self._static |= self._logo

    def text(self, t: int) -> str:
        seconds = self.spec.start_seconds + t / self.fps
        hh, rest = divmod(seconds, 3600)
        mm, ss = divmod(rest, 60)
        return f"{int(hh):02d}:{int(mm):02d}:{ss:05.2f}"

    def draw(self, frame: np.ndarray, t: int) -> np.ndarray:
        """``frame`` (RGB uint8) with the overlays of frame ``t`` burned in (a new array)."""
        out = frame.copy()
        out[self._static] = self._static_rgb[self._static]
        if self.spec.timestamp:
            w, h = self.size
            layer = np.zeros((h, w), np.uint8)
            outline = np.zeros((h, w), np.uint8)
            text = self.text(t)
            cv2.putText(outline, text, self._origin, self._font, self._scale, 255, self._thick + 2 * max(1, self._thick // 2 + 1), cv2.LINE_8)
            cv2.putText(layer, text, self._origin, self._font, self._scale, 255, self._thick, cv2.LINE_8)
            out[outline > 0] = OUTLINE_RGB
            out[layer > 0] = TEXT_RGB
            self.drawn |= outline > 0
            self._text_drawn |= outline > 0
        return out

    def regions(self) -> np.ndarray:
        """(h, w) bool: the overlays' boxes (the logo's rectangle, the bounding box of every
        timestamp drawn so far, the bars): what a detector should mask, glyph gaps included."""
        out = self._static.copy()
        ys, xs = np.nonzero(self._text_drawn)
        if len(xs):
            out[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1] = True
        return out

    def kinds(self) -> dict[str, np.ndarray]:
        """(h, w) bool per overlay of the spec (``"logo"``, ``"timestamp"``, ``"letterbox"``):
        the pixels it drew in some frame so far; their union is ``drawn``."""
        found = {"logo": self._logo, "timestamp": self._text_drawn, "letterbox": self._bars}
        return {k: found[k].copy() for k in self.spec.names}

    def use_mask(self) -> np.ndarray:
        """The exact truth as a ``--mask`` image: uint8, 255 where no overlay was ever drawn."""
        return np.where(self.drawn, 0, 255).astype(np.uint8)


def overlay_mask_path(video: str | Path) -> Path:
    """Where ``mosaic simulate --overlays`` writes the exact overlay mask of ``video``."""
    p = Path(video)
    return p.with_name(p.stem + ".mask.png")


def write_mask(path: str | Path, use: np.ndarray) -> None:
    """A uint8 mask as a PNG, atomically."""
    from mosaic_cli.atomic import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp:
        ok, data = cv2.imencode(".png", use)
        if not ok:
            raise OSError(f"{path}: could not encode the mask")
        Path(tmp).write_bytes(data.tobytes())


__all__ = ["KINDS", "LOGO_RGB", "TEXT_RGB", "OverlayBurner", "OverlaySpec", "overlay_mask_path", "write_mask"]
