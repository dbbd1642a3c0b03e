"""Burned-in overlays for simulated flights: a static logo, a running timestamp and black
letterbox bars, drawn into every rendered frame at fixed frame positions, as drone apps and
video editors burn them in.  The exact pixels drawn are known, so a detector (and a stitch
that must keep them out of the panorama) can be scored against them.

Two more are as hard as real ones (issue 40): ``watermark``, a white diamond alpha-blended
over the ground at ``opacity`` (0.5-1) with soft, anti-aliased edges (its alpha falls off over
a few pixels, so the ground shows through everywhere and its rim has no hard edge), and
``osd``, a semi-transparent dark box with running white telemetry text in it.  Their
footprint (``drawn``) is every pixel whose alpha is above 0 in some frame: the soft edge's
faintest pixels included.  ``--overlays watermark:0.6`` sets the opacity.

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

KINDS = ("logo", "timestamp", "letterbox", "watermark", "osd")
CLASSIC = ("logo", "timestamp", "letterbox")  # what "all" names (the translucent ones are asked for by name)
TRANSLUCENT = ("watermark", "osd")  # these take an opacity: "watermark:0.6"
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
    watermark: bool = False
    osd: bool = False
    watermark_opacity: float = 0.7  # of full opacity, the diamond's inside (its rim is brighter, its edge soft)
    osd_opacity: float = 0.6  # the OSD box's dark fill (its text is drawn at full opacity)
    watermark_width: float = 0.1  # of the frame width, top-right corner
    soft_px: float = 1.5  # the translucent overlays' edges: Gaussian fall-off, px at 720p (scaled with the frame)

    @staticmethod
    def parse(text: str | None) -> OverlaySpec:
        """``"logo,timestamp"``, ``"watermark:0.6,osd"``, ``"all"`` (logo, timestamp,
        letterbox) or ``"none"``/``""`` (nothing)."""
        names = [n.strip().lower() for n in (text or "").split(",") if n.strip()]
        if names == ["all"]:
            names = list(CLASSIC)
        if names == ["none"]:
            names = []
        fields: dict = {}
        for item in names:
            name, _, value = item.partition(":")
            name = name.strip()
            if name not in KINDS:
                raise BadInput(f"--overlays: unknown overlay {name!r} (choose from {', '.join(KINDS)}, or all)")
            fields[name] = True
            if value:
                if name not in TRANSLUCENT:
                    raise BadInput(f"--overlays: {name} takes no opacity (only {' and '.join(TRANSLUCENT)} do), got {item!r}")
                try:
                    opacity = float(value)
                except ValueError:
                    opacity = -1.0
                if not 0.05 <= opacity <= 1.0:
                    raise BadInput(f"--overlays: the opacity of {name} must be a number in 0.05..1, got {value!r}")
                fields[f"{name}_opacity"] = opacity
        return OverlaySpec(**fields)

    @property
    def any(self) -> bool:
        return self.logo or self.timestamp or self.letterbox or self.watermark or self.osd

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
        # The translucent overlays: alpha (0..1) and colour, blended over the ground.
        self._alpha = np.zeros((h, w), np.float32)
        self._alpha_rgb = np.zeros((h, w, 3), np.float32)
        self._watermark = np.zeros((h, w), bool)
        self._osd = np.zeros((h, w), bool)
        self._soft = max(0.5, spec.soft_px * h / 720.0)
        if spec.watermark:
            self._draw_watermark()
        if spec.osd:
            self._draw_osd_box()
        self.drawn |= self._static | self._watermark | self._osd
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

    def _soft_layer(self, draw) -> np.ndarray:
        """(h, w) float32 coverage 0..1 of what ``draw(layer, scale)`` fills (255) on a 4x
        canvas: anti-aliased by the 4x supersampling, then softened by a Gaussian of
        ``soft`` px (a real logo's edge is rendered smooth, then scaled by the app); alpha
        below one gray level's worth (1/255) is cut, so that the footprint is finite."""
        w, h = self.size
        big = np.zeros((4 * h, 4 * w), np.uint8)
        draw(big, 4)
        layer = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        layer = cv2.GaussianBlur(layer, (0, 0), self._soft)
        layer[layer < 1.0 / 255.0] = 0.0
        return layer

    def _blend_static(self, alpha: np.ndarray, rgb: tuple[int, int, int]) -> None:
        """Composite a static layer (``alpha``, one colour) over those already held ("over")."""
        a = alpha[..., None]
        self._alpha_rgb = self._alpha_rgb * (1 - a) + a * np.array(rgb, np.float32)
        self._alpha = self._alpha * (1 - alpha) + alpha
        # _alpha_rgb holds the premultiplied colour: the ground is weighted by 1 - _alpha.

    def _draw_watermark(self) -> None:
        """A white diamond, top-right: its inside at ``watermark_opacity``, a brighter rim."""
        w, h = self.size
        side = max(8, round(self.spec.watermark_width * w))
        margin = round(0.03 * w)
        top = margin + (round(self.spec.bar_height * h) if self.spec.letterbox else 0)
        cx, cy = w - margin - side / 2, top + side / 2
        rim = max(1.0, side / 12)

        def diamond(grow: float):
            def draw(layer, s):
                r = side / 2 + grow
                pts = np.array([[cx, cy - r], [cx + r, cy], [cx, cy + r], [cx - r, cy]]) * s
                cv2.fillPoly(layer, [np.round(pts).astype(np.int32)], 255, lineType=cv2.LINE_8)
            return draw

        outer = self._soft_layer(diamond(0.0))
        inner = self._soft_layer(diamond(-rim * np.sqrt(2)))
        opacity = self.spec.watermark_opacity
        alpha = np.clip(inner * opacity + (outer - inner) * min(1.0, opacity + 0.25), 0.0, 1.0)
        self._blend_static(alpha, (255, 255, 255))
        self._watermark = alpha > 0

    def _draw_osd_box(self) -> None:
        """A dark box, bottom-left, at ``osd_opacity``: the running telemetry text goes in it."""
        w, h = self.size
        margin = round(0.03 * w)
        bottom = h - margin - (round(self.spec.bar_height * h) if self.spec.letterbox else 0)
        bw, bh = round(0.3 * w), max(8, round(0.07 * h))
        self._osd_box = (margin, bottom - bh, bw, bh)

        def box(layer, s):
            cv2.rectangle(layer, (margin * s, (bottom - bh) * s), ((margin + bw) * s - 1, bottom * s - 1), 255, thickness=-1)

        alpha = self._soft_layer(box) * self.spec.osd_opacity
        self._blend_static(alpha, (0, 0, 0))
        self._osd = alpha > 0
        self._osd_scale = (0.6 * bh) / 22.0
        self._osd_thick = max(1, round(self._osd_scale * 1.2))
        (_, th), _ = cv2.getTextSize("A", cv2.FONT_HERSHEY_SIMPLEX, self._osd_scale, self._osd_thick)
        self._osd_origin = (margin + max(2, round(0.04 * bw)), bottom - (bh - th) // 2)

    def osd_text(self, t: int) -> str:
        """The OSD's running telemetry at frame ``t``: height and speed change every frame."""
        seconds = t / self.fps
        return f"H {100 + 2.5 * np.sin(seconds):5.1f}m  S {8 + np.cos(0.7 * seconds):4.1f}m/s"

    def text(self, t: int) -> str:
        seconds = self.spec.start_seconds + t / self.fps
        hh, rest = divmod(seconds, 3600)
        mm, ss = divmod(rest, 60)
        return f"{int(hh):02d}:{int(mm):02d}:{ss:05.2f}"

    def draw(self, frame: np.ndarray, t: int) -> np.ndarray:
        """``frame`` (RGB uint8) with the overlays of frame ``t`` burned in (a new array)."""
        out = frame.copy()
        out[self._static] = self._static_rgb[self._static]
        if self.spec.watermark or self.spec.osd:
            out = self._translucent(out, t)
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

    def _translucent(self, out: np.ndarray, t: int) -> np.ndarray:
        """``out`` with the watermark, the OSD box and the OSD's text of frame ``t`` blended in."""
        alpha, premul = self._alpha, self._alpha_rgb
        if self.spec.osd:
            x, y, bw, bh = self._osd_box
            ink = np.zeros(out.shape[:2], np.uint8)
            # White, anti-aliased, at full opacity, clipped to the box (its glyphs never leave it).
            cv2.putText(ink, self.osd_text(t), self._osd_origin, cv2.FONT_HERSHEY_SIMPLEX, self._osd_scale, 255, self._osd_thick,
                        cv2.LINE_AA)
            inside = np.zeros_like(ink)
            inside[y : y + bh, x : x + bw] = 1
            a = ink.astype(np.float32) / 255.0 * inside
            premul = premul * (1 - a[..., None]) + a[..., None] * 255.0
            alpha = alpha * (1 - a) + a
            self.drawn |= a > 0
            self._osd |= a > 0
        mixed = out.astype(np.float32) * (1 - alpha[..., None]) + premul
        return np.clip(np.rint(mixed), 0, 255).astype(np.uint8)

    def alpha(self) -> np.ndarray:
        """(h, w) float32 0..1: the translucent overlays' static opacity (watermark, OSD box)."""
        return self._alpha.copy()

    def regions(self) -> np.ndarray:
        """(h, w) bool: the overlays' boxes (the logo's rectangle, the bounding box of every
        timestamp drawn so far, the bars): what a detector should mask, glyph gaps included."""
        out = self._static | self._watermark | self._osd
        ys, xs = np.nonzero(self._text_drawn)
        if len(xs):
            out[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1] = True
        return out

    def kinds(self) -> dict[str, np.ndarray]:
        """(h, w) bool per overlay of the spec (``"logo"``, ``"timestamp"``, ``"letterbox"``,
        ``"watermark"``, ``"osd"``): the pixels it drew in some frame so far (for the
        translucent ones, every pixel of alpha above 0: the footprint); their union is ``drawn``."""
        found = {"logo": self._logo, "timestamp": self._text_drawn, "letterbox": self._bars, "watermark": self._watermark,
                 "osd": self._osd}
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


__all__ = ["CLASSIC", "KINDS", "TRANSLUCENT", "LOGO_RGB", "TEXT_RGB", "OverlayBurner", "OverlaySpec", "overlay_mask_path", "write_mask"]
