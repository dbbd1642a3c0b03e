"""Maps for virtual flights: a procedural aerial-like texture, and loading real orthophotos.

A map is an RGB uint8 array (H, W, 3); its pixel coordinates are the "map pixels" every
simulated homography starts from (OpenCV pixel-centre convention, see :mod:`mosaic_cli.geometry`).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.video.folders import check_intact

# Colours (RGB) of the land-cover classes of the procedural map.
_FIELD_COLOURS = np.array(
    [
        (96, 128, 56), (120, 142, 62), (150, 160, 80), (176, 164, 102), (140, 116, 78),
        (112, 96, 66), (186, 176, 120), (82, 110, 52), (160, 140, 96), (128, 150, 90),
    ],
    dtype=np.float32,
)
_ROOF_COLOURS = np.array(
    [(150, 70, 60), (120, 120, 124), (180, 176, 170), (92, 90, 96), (170, 110, 80), (210, 206, 200)], dtype=np.float32
)
MIN_MAP_SIDE = 64


def _noise(rng: np.random.Generator, shape: tuple[int, int], cell: int) -> np.ndarray:
    """Smooth value noise in [-1, 1] with features about ``cell`` pixels wide, float32 (h, w)."""
    h, w = shape
    gh, gw = max(2, h // cell + 2), max(2, w // cell + 2)
    coarse = rng.uniform(-1.0, 1.0, size=(gh, gw)).astype(np.float32)
    return cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)


def _fractal(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[int, ...], gain: float = 0.6) -> np.ndarray:
    out = np.zeros(shape, np.float32)
    amp, total = 1.0, 0.0
    for cell in cells:
        out += amp * _noise(rng, shape, cell)
        total += amp
        amp *= gain
    return out / total


def procedural_map(size: tuple[int, int] = (4096, 4096), seed: int = 0) -> np.ndarray:
    """An aerial-like RGB uint8 texture (H, W, 3) of ``size`` (W, H), deterministic in ``seed``.

    Fields (Voronoi patches with crop rows), roads, tree clumps and forests, buildings with
    shadows, a lake and multi-scale detail; fields and the water are low-texture areas.
    """
    W, H = int(size[0]), int(size[1])
    if W < MIN_MAP_SIDE or H < MIN_MAP_SIDE:
        raise BadInput(f"map size must be at least {MIN_MAP_SIDE}x{MIN_MAP_SIDE}, got {W}x{H}")
    rng = np.random.default_rng(seed)
    unit = max(W, H) / 4096.0  # features keep their pixel size; counts scale with the area
    area = W * H

    # --- fields: Voronoi cells at quarter resolution with wobbly borders
    q = 4
    qh, qw = max(8, H // q), max(8, W // q)
    n_fields = max(6, int(area / (380.0**2)))
    from scipy.spatial import cKDTree

    seeds = rng.uniform([0, 0], [qw, qh], size=(n_fields, 2))
    yy, xx = np.mgrid[0:qh, 0:qw].astype(np.float32)
    warp = 14.0 / q * 4
    xx += warp * _noise(rng, (qh, qw), 40)
    yy += warp * _noise(rng, (qh, qw), 40)
    _, labels_q = cKDTree(seeds).query(np.stack([xx.ravel(), yy.ravel()], axis=1), workers=-1)
    labels16 = cv2.resize(labels_q.reshape(qh, qw).astype(np.uint16), (W, H), interpolation=cv2.INTER_NEAREST)
    for _ in range(2):  # round off the staircase of the upscaled cell borders
        labels16 = cv2.medianBlur(labels16, 5)
    labels = labels16.astype(np.int32)
    del labels16

    base = _FIELD_COLOURS[rng.integers(0, len(_FIELD_COLOURS), n_fields)]
    base = base * rng.uniform(0.85, 1.15, size=(n_fields, 1)).astype(np.float32)
    theta = rng.uniform(0, np.pi, n_fields).astype(np.float32)
    period = rng.uniform(5.0, 14.0, n_fields).astype(np.float32)
    row_amp = np.where(rng.random(n_fields) < 0.55, rng.uniform(6, 18, n_fields), 0.0).astype(np.float32)
    tex_amp = rng.uniform(3, 14, n_fields).astype(np.float32)  # some fields are nearly flat

    xs = np.arange(W, dtype=np.float32)[None, :]
    ys = np.arange(H, dtype=np.float32)[:, None]
    k = (2 * np.pi / period).astype(np.float32)
    rows = xs * (np.cos(theta) * k)[labels]
    rows += ys * (np.sin(theta) * k)[labels]
    np.sin(rows, out=rows)
    rows *= row_amp[labels]
    detail = _fractal(rng, (H, W), (48, 12, 4), 0.7)
    detail *= tex_amp[labels]
    rows += detail
    del detail
    img = base[labels]
    img += rows[..., None]
    del rows
    # field borders: thin darker hedges
    edges = cv2.morphologyEx(labels.astype(np.float32), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    img[edges] *= 0.8
    del labels, edges

    # --- large-scale tone variation (soil moisture, illumination)
    img *= (1.0 + 0.12 * _fractal(rng, (H, W), (900, 300), 0.5))[..., None]
    img = np.clip(img, 0, 255).astype(np.uint8)

    # --- a lake or two: smooth, low texture
    for _ in range(rng.integers(1, 3)):
        cx, cy = rng.uniform(0.1, 0.9) * W, rng.uniform(0.1, 0.9) * H
        r = rng.uniform(120, 320) * unit
        angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)
        radius = r * (1 + 0.25 * np.sin(angles * rng.integers(2, 5) + rng.uniform(0, 6)) + 0.1 * rng.standard_normal(48))
        poly = np.stack([cx + radius * np.cos(angles), cy + radius * np.sin(angles)], 1).astype(np.int32)
        cv2.fillPoly(img, [poly], (58, 84, 88), lineType=cv2.LINE_AA)
        cv2.polylines(img, [poly], True, (120, 118, 92), thickness=max(2, int(5 * unit)), lineType=cv2.LINE_AA)

    # --- forests: dense clumps of trees; scattered trees
    def tree(x: float, y: float, r: float) -> None:
        g = rng.uniform(0.7, 1.2)
        shadow = (int(x + 0.5 * r), int(y + 0.6 * r))
        cv2.circle(img, shadow, int(r), (28, 36, 22), -1, cv2.LINE_AA)
        cv2.circle(img, (int(x), int(y)), int(r), (int(40 * g), int(82 * g), int(36 * g)), -1, cv2.LINE_AA)
        cv2.circle(img, (int(x - 0.3 * r), int(y - 0.3 * r)), max(1, int(0.45 * r)), (int(62 * g), int(112 * g), int(50 * g)), -1, cv2.LINE_AA)

    n_forests = max(1, int(area / (1400.0**2)))
    for _ in range(n_forests):
        cx, cy = rng.uniform(0, W), rng.uniform(0, H)
        rx, ry = rng.uniform(120, 400, size=2) * unit
        count = int(rx * ry / 90)
        for x, y in zip(rng.normal(cx, rx / 2, count), rng.normal(cy, ry / 2, count)):
            tree(x, y, rng.uniform(4, 11))
    for _ in range(int(area / 9000)):
        tree(rng.uniform(0, W), rng.uniform(0, H), rng.uniform(3, 9))

    # --- roads: smooth curves crossing the map, and a few tracks
    def road(width: float, colour: tuple[int, int, int], verge: tuple[int, int, int] | None) -> None:
        start = rng.uniform([0, 0], [W, H])
        heading = rng.uniform(0, 2 * np.pi)
        pts = [start]
        step = 40.0 * unit
        turn = 0.0
        for _ in range(int(2.5 * max(W, H) / step)):
            turn = 0.85 * turn + rng.normal(0, 0.05)
            heading += turn
            pts.append(pts[-1] + step * np.array([np.cos(heading), np.sin(heading)]))
        poly = np.array(pts, np.int32)
        if verge is not None:
            cv2.polylines(img, [poly], False, verge, thickness=int(width + 6), lineType=cv2.LINE_AA)
        cv2.polylines(img, [poly], False, colour, thickness=int(width), lineType=cv2.LINE_AA)
        if width >= 10:  # centre line, dashed
            for a, b in zip(poly[:-1:2], poly[1::2]):
                cv2.line(img, tuple(int(v) for v in a), tuple(int(v) for v in (a + 0.5 * (b - a))), (220, 216, 200), 1, cv2.LINE_AA)

    for _ in range(max(2, int(area / (2000.0**2)))):
        road(rng.uniform(10, 18), (84, 84, 88), (150, 146, 128))
    for _ in range(max(2, int(area / (1500.0**2)))):
        road(rng.uniform(3, 6), (168, 150, 118), None)

    # --- villages: clusters of buildings with shadows
    n_villages = max(1, int(area / (1300.0**2)))
    for _ in range(n_villages):
        cx, cy = rng.uniform(0, W), rng.uniform(0, H)
        spread = rng.uniform(80, 260) * unit
        orient = rng.uniform(0, np.pi)
        for _ in range(int(rng.integers(8, 40))):
            x, y = rng.normal(cx, spread), rng.normal(cy, spread)
            bw, bh = rng.uniform(10, 34), rng.uniform(8, 24)
            a = orient + rng.choice([0.0, np.pi / 2]) + rng.normal(0, 0.05)
            box = cv2.boxPoints(((float(x), float(y)), (float(bw), float(bh)), float(np.degrees(a))))
            cv2.fillPoly(img, [(box + [0.35 * bh, 0.45 * bh]).astype(np.int32)], (40, 42, 40), cv2.LINE_AA)
            roof = _ROOF_COLOURS[rng.integers(0, len(_ROOF_COLOURS))] * rng.uniform(0.85, 1.1)
            cv2.fillPoly(img, [box.astype(np.int32)], tuple(int(min(255, v)) for v in roof), cv2.LINE_AA)
            # a ridge line
            mid = box.mean(0)
            d = (box[1] - box[0]) / 2 if bw > bh else (box[2] - box[1]) / 2
            cv2.line(img, tuple((mid - 0.8 * d).astype(int)), tuple((mid + 0.8 * d).astype(int)), tuple(int(0.75 * v) for v in roof), 1, cv2.LINE_AA)

    # --- fine grain: sensor-like noise and a slight blur so nothing is perfectly flat or aliased
    grain = rng.normal(0.0, 2.5, size=(H, W, 1)).astype(np.float32)
    out = cv2.GaussianBlur(img, (3, 3), 0.6).astype(np.float32) + grain
    return np.clip(out, 0, 255).astype(np.uint8)


def _largest_rectangle(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(x, y, w, h) of the largest axis-aligned rectangle of True cells in ``mask``."""
    h, w = mask.shape
    heights = np.zeros(w, dtype=np.int64)
    best = (0, 0, 0, 0)
    best_area = 0
    for row in range(h):
        heights = np.where(mask[row], heights + 1, 0)
        stack: list[int] = []
        hs = heights.tolist() + [0]
        for col, height in enumerate(hs):
            while stack and hs[stack[-1]] >= height:
                top = stack.pop()
                left = stack[-1] + 1 if stack else 0
                area = hs[top] * (col - left)
                if area > best_area:
                    best_area = area
                    best = (left, row - hs[top] + 1, col - left, hs[top])
            stack.append(col)
    return best


def nodata_mask(rgb_or_bgr: np.ndarray, alpha: np.ndarray | None = None, alpha_threshold: int = 250, min_hole: int = 200) -> np.ndarray:
    """True where an orthophoto holds no data: transparent pixels, and the flat white or black
    fill that many orthomosaics carry outside their footprint (even when fully opaque):
    white regions touching the border or larger than ``min_hole`` pixels, black regions
    touching the border (border regions smaller than 0.05 % of the image are kept)."""
    h, w = rgb_or_bgr.shape[:2]
    invalid = np.zeros((h, w), bool) if alpha is None else alpha < alpha_threshold
    colour = rgb_or_bgr[..., :3]
    for fill, is_white in (((colour >= 250).all(axis=2)), True), (((colour <= 2).all(axis=2)), False):
        if not fill.any():
            continue
        count, labels, stats, _ = cv2.connectedComponentsWithStats(fill.astype(np.uint8), connectivity=8)
        x, y, bw, bh, area = (stats[:, k] for k in range(5))
        touches = ((x == 0) | (y == 0) | (x + bw == w) | (y + bh == h)) & (area >= max(16, h * w // 2000))
        bad = touches | ((area >= min_hole) if is_white else np.zeros_like(touches))
        bad[0] = False  # background of the component labelling
        if bad.any():
            invalid |= bad[labels]
    return invalid


def valid_rectangle(valid: np.ndarray, max_side: int = 400) -> tuple[int, int, int, int]:
    """The largest axis-aligned rectangle (x, y, w, h) inside the True pixels of ``valid``.

    Searched on a conservative downscale (a coarse cell counts only when all of it is valid)."""
    H, W = valid.shape
    valid = valid.astype(np.uint8)
    if valid.all():
        return (0, 0, W, H)
    factor = max(1, int(np.ceil(max(H, W) / max_side)))
    if factor > 1:
        ch, cw = H // factor, W // factor
        cells = valid[: ch * factor, : cw * factor].reshape(ch, factor, cw, factor).min(axis=(1, 3))
    else:
        cells = valid
    x, y, w, h = _largest_rectangle(cells.astype(bool))
    return (x * factor, y * factor, w * factor, h * factor)


def load_map(path: str | Path | None, seed: int = 0) -> np.ndarray:
    """An RGB uint8 map: the procedural one for ``None``, else the image at ``path``.

    Orthomosaics are cropped to their largest valid rectangle: opaque (alpha >= 250) and not
    the flat white or black fill outside the footprint (see :func:`nodata_mask`); 16-bit
    images are scaled to 8 bits; gray ones become RGB."""
    if path is None:
        return procedural_map(seed=seed)
    p = Path(path)
    if not p.exists():
        raise BadInput(f"{p}: no such file")
    if p.is_dir():
        raise BadInput(f"{p}: is a folder, not a map image")
    check_intact(p, "copy it again")  # OpenCV would fly over a JPEG cut short, its missing rows grey
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise BadInput(f"{p}: not an image OpenCV can read")
    if img.dtype == np.uint16:
        img = (img / 257.0).round().astype(np.uint8)
    elif img.dtype != np.uint8:
        img = cv2.normalize(img.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    alpha = img[:, :, 3] if img.shape[2] == 4 else None
    invalid = nodata_mask(img, alpha)
    x, y, w, h = valid_rectangle(~invalid)
    if w < MIN_MAP_SIDE or h < MIN_MAP_SIDE:
        raise BadInput(f"{p}: the valid (opaque, non-fill) part of the image is too small to fly over ({w}x{h} px)")
    rgb = cv2.cvtColor(img[y : y + h, x : x + w, :3], cv2.COLOR_BGR2RGB)
    if rgb.shape[0] < MIN_MAP_SIDE or rgb.shape[1] < MIN_MAP_SIDE:
        raise BadInput(f"{p}: map of {rgb.shape[1]}x{rgb.shape[0]} px is too small (at least {MIN_MAP_SIDE}x{MIN_MAP_SIDE})")
    return np.ascontiguousarray(rgb)
