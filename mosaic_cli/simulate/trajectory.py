"""Camera paths of simulated drone flights, one kind per profile, as exact homographies.

The virtual camera is a pinhole looking (almost) straight down on the map plane.  With the
map in pixels as world units, frame size (w, h), focal length f (frame pixels) and a camera
above map point (X, Y) at altitude Z = f * s (s: map pixels per frame pixel at the nadir),

    map_to_frame = K @ R @ [[1, 0, -X], [0, 1, -Y], [0, 0, Z]],   K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]

where R = Rx(pitch) @ Ry(roll) @ Rz(heading) holds the heading and a slight tilt.  Every
matrix is exact: the rendered pixels are produced from these very matrices.

Motion speeds are in "1280x720-equivalent pixels per frame at the frame centre", the unit of
the paper (a frame of width w moves ``speed * w / 1280`` of its own pixels per frame).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry import frame_corners, normalize, project
from mosaic_cli.geometry.rolling_shutter import ROW_BANDS, band_centres, mid_row, row_times

REFERENCE_WIDTH = 1280.0
MIN_GROUND_SAMPLE = 1.0 / 8.0  # at most 8x upsampling of the map
FOOTPRINT_FRACTION = 0.6  # the footprint's bounding circle spans this much of the map's shorter side
SMALL_MAP_FRACTION = 0.8  # ... up to this much on small maps, to upsample them less
SMALL_MAP_SAMPLE = 0.25  # "small": flying at FOOTPRINT_FRACTION would upsample more than 4x


@dataclass(frozen=True)
class Degradation:
    """What a profile does to the pixels (never to the geometry): the camera and the codec.

    Amplitudes are drawn per flight or vary slowly per frame within these ranges."""

    exposure: float = 0.3  # amplitude of the slow log-gain drift (auto exposure hunting)
    exposure_jumps: float = 0.0  # size of sudden log-gain steps (auto exposure catching up)
    noise: tuple[float, float] = (3.0, 6.0)  # sensor noise sigma, gray levels
    shutter: tuple[float, float] = (0.8, 0.8)  # motion blur length as a fraction of the motion between frames
    shake_blur_px: float = 6.0  # extra blur episodes (1280x720-equivalent px)
    vignette: tuple[float, float] = (0.0, 0.0)  # brightness lost at the frame corners, per flight
    contrast: tuple[float, float] = (1.0, 1.0)  # contrast kept: haze, low-texture ground (fields, sand, water)


@dataclass(frozen=True)
class Profile:
    """What a flight of one kind looks like."""

    name: str
    description: str
    speed: tuple[float, float]  # 1280x720-equivalent px/frame at the frame centre
    path: str = "wander"  # "wander" (smooth random loop) or "lawnmower"
    heading_deg: float = 12.0  # amplitude of heading changes
    tilt_deg: float = 3.0  # constant tilt up to this, plus a slow +-1.5 degree sway
    altitude_drift: float = 0.06  # relative amplitude of altitude changes
    jitter_px: float = 0.0  # 3-8 Hz shake amplitude, 1280x720-equivalent px
    jitter_deg: float = 0.0  # 3-8 Hz shake rotation amplitude
    # 3-8 Hz pitch and roll shake amplitude, degrees: the camera turns about its own centre, which
    # shifts the view by about focal * angle and keystones it (a perspective change no in-plane
    # shake has).  Drawn after the in-plane shake, so the flights of the other profiles stay as they were.
    jitter_tilt_deg: float = 0.0
    effects: Degradation | None = None  # exposure, noise, blur, vignetting, haze (pixels only)
    speed_periods: tuple[float, float] = (4.0, 15.0)  # seconds: how fast the speed changes
    heading_periods: tuple[float, float] = (20.0, 60.0)  # seconds: how fast the heading turns
    altitude_periods: tuple[float, float] = (20.0, 60.0)
    crf: int = 18  # H.264 quality the flight is encoded at unless --crf says otherwise
    bursts: tuple[str, ...] = ()  # frames without a motion cue (simulate.bursts.KINDS), unless --bursts says otherwise


PROFILES: dict[str, Profile] = {
    p.name: p
    for p in (
        Profile("paper", "slow drone flight like the paper's videos: 1-2 px/frame, slow heading changes, altitude drift", (1.0, 2.0)),
        Profile("survey", "lawnmower back-and-forth lines that revisit the ground, 4-7 px/frame", (4.0, 7.0), path="lawnmower", heading_deg=2.0),
        Profile("fast", "fast flight, 10-20 px/frame", (10.0, 20.0), heading_deg=20.0),
        Profile("shaky", "the paper path plus 3-8 Hz shake (a few px, small rotation)", (1.0, 2.0), jitter_px=3.0, jitter_deg=0.3),
        Profile("shaky-tilt", "the shaky flight with 3-8 Hz pitch and roll shake as well (the camera tilting up to "
                "0.3 degrees about its own centre: the view shifts and keystones)", (1.0, 2.0), jitter_px=3.0,
                jitter_deg=0.3, jitter_tilt_deg=0.3),
        Profile("hard", "the paper path with exposure drift, sensor noise and motion blur", (1.0, 2.0), effects=Degradation()),
        Profile(
            "extreme",
            "fast degraded flight: 25-60 px/frame, fast yaw turns and altitude changes, exposure drift and jumps, "
            "noise, motion blur, vignetting, haze, low-bitrate H.264",
            (25.0, 60.0),
            heading_deg=120.0,
            altitude_drift=0.25,
            speed_periods=(2.0, 8.0),
            heading_periods=(6.0, 20.0),
            altitude_periods=(6.0, 20.0),
            effects=Degradation(exposure=0.25, exposure_jumps=0.15, noise=(4.0, 8.0), shutter=(0.05, 0.3),
                                shake_blur_px=3.0, vignette=(0.3, 0.5), contrast=(0.35, 1.0)),
            crf=30,
        ),
        Profile(
            "bursts",
            "an ordinary flight (8-30 px/frame, exposure drift, noise, motion blur) where every 12-30 frames "
            "1-3 frames carry no motion cue: glare, a gust's heavy blur, near-black or featureless frames, "
            "a dropped or duplicated frame",
            (8.0, 30.0),
            heading_deg=20.0,
            effects=Degradation(),
            bursts=("glare", "blur", "dark", "flat", "drop", "duplicate"),
        ),
    )
}


@dataclass(frozen=True)
class NoiseVibration:
    """Band-limited noise vibration (``--vibration noise:LO-HI,PX[,DEG]``): on each of the x and
    y shifts (``px`` 1280-wide px RMS) and the rotation about the frame centre (``deg`` degrees
    RMS), an independent sum of ``NOISE_COMPONENTS`` sinusoids whose frequencies are spread evenly
    (one drawn in each of as many equal slices) over [``low_hz``, ``high_hz``], with random phases:
    a flat spectrum over the band, Gaussian to the eye, and an exact function of time."""

    low_hz: float
    high_hz: float
    px: float
    deg: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.low_hz) and np.isfinite(self.high_hz) and 0.0 < self.low_hz < self.high_hz <= 240.0):
            raise BadInput(f"--vibration noise:LO-HI needs 0 < LO < HI <= 240 Hz, got {self.low_hz:g}-{self.high_hz:g}")
        if not (0.0 <= self.px <= 50.0 and 0.0 <= self.deg <= 5.0):
            raise BadInput(f"--vibration noise: PX in [0, 50] and DEG in [0, 5], got {self.px:g},{self.deg:g}")

    @property
    def any(self) -> bool:
        return self.px > 0 or self.deg > 0

    def describe(self) -> str:
        return f"noise:{self.low_hz:g}-{self.high_hz:g},{self.px:g},{self.deg:g}"


@dataclass(frozen=True)
class RollingShutter:
    """A rolling-shutter camera on a vibrating drone (``mosaic simulate --rolling-shutter R
    --vibration ...``): row y of frame t sees the camera at time ``t + readout * y / h``.

    Vibration: a sinusoidal shake of the camera at ``vibration_hz``, ``vibration_px`` (1280-wide
    px) of translation in x and y (phases drawn from the seed) and a rotation that moves the
    frame corners by a fifth of that, added to the trajectory and sampled at each row's time.
    ``tones``: more such sinusoids, (hz, px) each (``--vibration 12,2+31,1``); ``noise``:
    band-limited noise on the shifts and the rotation (:class:`NoiseVibration`), as a motor and
    propellers shake a drone.  All of them are summed, exact functions of time."""

    readout: float = 0.0  # fraction of the frame interval, 0..1 (0: global shutter)
    vibration_hz: float = 0.0
    vibration_px: float = 0.0
    bands: int = ROW_BANDS  # row bands of the ground truth (and of the rendering's rule)
    tones: tuple[tuple[float, float], ...] = ()  # further tones (hz, px), after the first
    noise: NoiseVibration | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.readout <= 1.0:
            raise BadInput(f"--rolling-shutter must be in [0, 1] (a fraction of the frame interval), got {self.readout:g}")
        for hz, px in ((self.vibration_hz, self.vibration_px), *self.tones):
            if px < 0 or not 0.0 <= hz <= 240.0:
                raise BadInput(f"--vibration must be HZ,PX with 0 <= HZ <= 240 and PX >= 0, got {hz:g},{px:g}")
            if px > 50:
                raise BadInput(f"--vibration amplitude must be at most 50 px, got {px:g}")
        if self.bands < 1:
            raise ValueError(f"row bands must be at least 1, got {self.bands}")

    @property
    def vibrates(self) -> bool:
        return (self.vibration_px > 0 and self.vibration_hz > 0) or any(px > 0 and hz > 0 for hz, px in self.tones) \
            or (self.noise is not None and self.noise.any)

    @property
    def any(self) -> bool:
        return self.readout > 0 or self.vibrates

    @property
    def broadband(self) -> bool:
        """More than today's one tone: further tones or noise (the truth then records ``vibration``)."""
        return bool(self.tones) or self.noise is not None

    def describe(self) -> str:
        """The ``--vibration`` text of this vibration."""
        items = [f"{self.vibration_hz:g},{self.vibration_px:g}"] if self.vibration_px > 0 or not self.broadband else []
        items += [f"{hz:g},{px:g}" for hz, px in self.tones]
        if self.noise is not None:
            items.append(self.noise.describe())
        return "+".join(items)


@dataclass
class FlightPlan:
    """The exact geometry of one simulated flight (and the effects to render, if any)."""

    map_to_frame: np.ndarray  # (N, 3, 3): map pixel -> frame pixel
    smooth_map_to_frame: np.ndarray  # (N, 3, 3): the same path without shake
    size: tuple[int, int]  # frame (w, h)
    profile: str
    seed: int
    map_size: tuple[int, int] = (0, 0)  # (W, H) of the map flown over
    fps: float = 30.0
    effects: dict[str, np.ndarray] = field(default_factory=dict)  # per-frame arrays (hard profile)
    bursts: list = field(default_factory=list)  # simulate.bursts.Burst: the frames without a motion cue
    # A rolling shutter (and vibration): the camera of each row band, (N, K, 3, 3) map -> frame;
    # None: global shutter, every row sees map_to_frame (the mid-time pose otherwise).
    rolling: RollingShutter | None = None
    row_bands: np.ndarray | None = None

    @property
    def frames(self) -> int:
        return len(self.map_to_frame)

    @property
    def pairwise(self) -> np.ndarray:
        """(N-1, 3, 3): frame t -> t+1 = map_to_frame[t+1] @ inv(map_to_frame[t])."""
        return pairwise_from_absolute(self.map_to_frame)


def pairwise_from_absolute(map_to_frame: np.ndarray) -> np.ndarray:
    M = np.asarray(map_to_frame, dtype=np.float64)
    if len(M) < 2:
        return np.zeros((0, 3, 3))
    return normalize(M[1:] @ np.linalg.inv(M[:-1]))


def centre_motion(pairwise: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Displacement of the frame centre per pair, in 1280x720-equivalent pixels, (N-1,)."""
    w, h = size
    c = np.array([[(w - 1) / 2.0, (h - 1) / 2.0]])
    moved = project(pairwise, np.broadcast_to(c, (len(pairwise), 1, 2)))[:, 0]
    return np.linalg.norm(moved - c, axis=1) * REFERENCE_WIDTH / w


# ---------------------------------------------------------------------------------------------
# smooth random signals


def smooth_signal(rng: np.random.Generator, n: int, fps: float, periods: tuple[float, float], components: int = 4) -> np.ndarray:
    """A smooth random signal of ``n`` samples in [-1, 1]: a sum of sinusoids whose periods
    (seconds) lie in ``periods``, scaled so that its largest possible excursion is 1."""
    t = np.arange(n) / fps
    freqs = 1.0 / rng.uniform(periods[0], periods[1], components)
    amps = rng.uniform(0.5, 1.0, components)
    phases = rng.uniform(0, 2 * np.pi, components)
    out = (amps[:, None] * np.sin(2 * np.pi * freqs[:, None] * t[None] + phases[:, None])).sum(0)
    return out / amps.sum()


def _rotation(pitch: float, roll: float, heading: float) -> np.ndarray:
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    ch, sh = np.cos(heading), np.sin(heading)
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    Ry = np.array([[cr, 0, sr], [0, 1, 0], [-sr, 0, cr]])
    Rz = np.array([[ch, -sh, 0], [sh, ch, 0], [0, 0, 1]])
    return Rx @ Ry @ Rz


def camera_homography(size: tuple[int, int], focal: float, X: float, Y: float, s: float, heading: float,
                      pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """map_to_frame of a camera above map point (X, Y) with ground sample ``s`` (see module doc)."""
    w, h = size
    K = np.array([[focal, 0, (w - 1) / 2.0], [0, focal, (h - 1) / 2.0], [0, 0, 1.0]])
    T = np.array([[1.0, 0, -X], [0, 1.0, -Y], [0, 0, focal * s]])
    return normalize(K @ _rotation(pitch, roll, heading) @ T)


# ---------------------------------------------------------------------------------------------
# paths of the point below the camera, in map pixels

Box = tuple[float, float, float, float]  # x0, y0, x1, y1


def _arc_sample(points: np.ndarray, distances: np.ndarray, closed: bool) -> np.ndarray:
    """Positions at the given arc lengths along a dense polyline (wrapping if ``closed``)."""
    if closed:
        points = np.vstack([points, points[:1]])
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    total = cum[-1]
    d = np.mod(distances, total) if closed else np.clip(distances, 0, total)
    return np.stack([np.interp(d, cum, points[:, 0]), np.interp(d, cum, points[:, 1])], axis=1)


def _wander_path(rng: np.random.Generator, box: Box, distances: np.ndarray) -> np.ndarray:
    """A smooth closed loop filling ``box`` (x0, y0, x1, y1), followed from a random point."""
    x0, y0, x1, y1 = box
    u = np.linspace(0, 2 * np.pi, 4096, endpoint=False)
    pts = np.zeros((len(u), 2))
    for axis in range(2):
        comp = np.cos(u + rng.uniform(0, 2 * np.pi)) if axis == 0 else np.sin(u + rng.uniform(-0.6, 0.6))
        for k, amp in ((2, rng.uniform(0, 0.2)), (3, rng.uniform(0, 0.1))):
            comp = comp + amp * np.sin(k * u + rng.uniform(0, 2 * np.pi))
        comp = comp / np.max(np.abs(comp))
        lo, hi = (x0, x1) if axis == 0 else (y0, y1)
        pts[:, axis] = (lo + hi) / 2 + (hi - lo) / 2 * comp
    if rng.random() < 0.5:
        pts = pts[::-1]
    start = rng.uniform(0, 1) * np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1))
    return _arc_sample(pts, start + distances, closed=True)


def _lawnmower_path(rng: np.random.Generator, box: Box, distances: np.ndarray, spacing: float) -> np.ndarray:
    """Back-and-forth lines along x, ``spacing`` apart, joined by half-circle turns."""
    x0, y0, x1, y1 = box
    total = float(distances[-1]) if len(distances) else 0.0
    r = spacing / 2
    inner_x0, inner_x1 = x0 + r, x1 - r
    if inner_x1 - inner_x0 < spacing:  # too narrow for turns: just lines
        inner_x0, inner_x1 = x0, x1
    # legs long enough for the flight to fly at least ~3.5 of them
    leg = float(np.clip(total / 3.5 - np.pi * r, spacing, inner_x1 - inner_x0))
    start_x = rng.uniform(inner_x0, inner_x1 - leg)
    n_lines = max(1, int(np.floor((y1 - y0) / spacing)) + 1)
    y_start = y0 + rng.uniform(0, max(0.0, (y1 - y0) - (n_lines - 1) * spacing))
    legs_needed = int(np.ceil(total / (leg + np.pi * r))) + 2
    pts: list[np.ndarray] = []
    idx, step = 0, 1
    for i in range(legs_needed):
        y = y_start + idx * spacing
        xs = np.linspace(start_x, start_x + leg, 64)
        if i % 2:
            xs = xs[::-1]
        pts.append(np.stack([xs, np.full_like(xs, y)], 1))
        if n_lines > 1:
            if not 0 <= idx + step < n_lines:
                step = -step
            nxt = idx + step
            side = 1.0 if i % 2 == 0 else -1.0
            cx = xs[-1]
            cy = y + (nxt - idx) * spacing / 2
            ang = np.linspace(-np.pi / 2, np.pi / 2, 32) * (1 if nxt > idx else -1)
            pts.append(np.stack([cx + side * r * np.cos(ang), cy + r * np.sin(ang)], 1)[1:-1])
            idx = nxt
        else:
            pass  # one line only: fly back and forth on it
    poly = np.vstack(pts)
    return _arc_sample(poly, distances, closed=False)


# ---------------------------------------------------------------------------------------------


def plan_flight(
    map_size: tuple[int, int],
    profile: str = "paper",
    frames: int = 300,
    size: tuple[int, int] = (1280, 720),
    seed: int = 0,
    fps: float = 30.0,
) -> FlightPlan:
    """Plan a flight of ``frames`` frames of ``size`` (w, h) over a map of ``map_size`` (W, H).

    The footprint stays inside the map for the whole flight: the altitude is chosen from the
    map size (``BadInput`` when the map is too small for the frame size)."""
    if profile not in PROFILES:
        raise BadInput(f"unknown profile {profile!r}: choose one of {', '.join(PROFILES)}")
    if frames < 2:
        raise BadInput(f"a flight needs at least 2 frames, got {frames}")
    if fps <= 0:
        raise BadInput(f"frame rate must be positive, got {fps}")
    prof = PROFILES[profile]
    w, h = int(size[0]), int(size[1])
    if w < 16 or h < 16:
        raise BadInput(f"frame size must be at least 16x16, got {w}x{h}")
    W, H = int(map_size[0]), int(map_size[1])
    rng = np.random.default_rng([int(seed), 7919])
    n = int(frames)
    focal = float(w)

    # Attitude: constant tilt of a few degrees plus slow sway; slow heading changes.
    tilt_dir = rng.uniform(0, 2 * np.pi)
    tilt0 = np.radians(rng.uniform(0.3, 1.0) * prof.tilt_deg)
    sway = np.radians(1.5)
    pitch = tilt0 * np.cos(tilt_dir) + sway * smooth_signal(rng, n, fps, (30, 90))
    roll = tilt0 * np.sin(tilt_dir) + sway * smooth_signal(rng, n, fps, (30, 90))
    heading0 = rng.uniform(-np.pi, np.pi) if prof.path == "wander" else rng.choice([0.0, np.pi])
    heading = heading0 + np.radians(prof.heading_deg) * smooth_signal(rng, n, fps, prof.heading_periods)
    altitude = 1.0 + prof.altitude_drift * smooth_signal(rng, n, fps, prof.altitude_periods)

    # Ground sample from the map size: the footprint's bounding circle at the highest altitude
    # and largest tilt spans FOOTPRINT_FRACTION of the map's shorter side.
    half_diag = 0.5 * np.hypot(w, h)
    max_tilt = tilt0 + 2 * sway + np.radians(prof.jitter_tilt_deg)
    radius_per_s = (half_diag * (1 + np.tan(max_tilt) * half_diag / focal) + focal * np.tan(max_tilt)) * (1 + prof.altitude_drift)
    s0 = FOOTPRINT_FRACTION * min(W, H) / 2 / radius_per_s
    if s0 < SMALL_MAP_SAMPLE:  # a small map: fly lower over more of it rather than blow it up
        s0 = min(SMALL_MAP_SAMPLE, SMALL_MAP_FRACTION * min(W, H) / 2 / radius_per_s)
    if s0 < MIN_GROUND_SAMPLE:
        need = int(np.ceil(2 * radius_per_s * MIN_GROUND_SAMPLE / SMALL_MAP_FRACTION))
        raise BadInput(f"map of {W}x{H} px is too small for {w}x{h} frames: its shorter side needs at least {need} px")
    s = s0 * altitude
    margin = radius_per_s * s0 + 2.0
    box = (margin, margin, W - 1 - margin, H - 1 - margin)

    # Speed along the ground, from the profile's range at the frame centre.
    lo, hi = prof.speed
    speed_eq = lo + (hi - lo) * (0.5 + 0.5 * smooth_signal(rng, n, fps, prof.speed_periods))
    step_map = speed_eq * w / REFERENCE_WIDTH * s
    distances = np.concatenate([[0.0], np.cumsum(step_map[:-1])])
    if prof.path == "lawnmower":
        spacing = 0.5 * h * s0 * (1 - prof.altitude_drift)
        spacing = min(spacing, max(1.0, (box[3] - box[1]) / 2)) if box[3] > box[1] else spacing
        ground = _lawnmower_path(rng, box, distances, spacing)
    else:
        ground = _wander_path(rng, box, distances)

    smooth = np.stack(
        [camera_homography((w, h), focal, ground[t, 0], ground[t, 1], s[t], heading[t], pitch[t], roll[t]) for t in range(n)]
    )
    map_to_frame = smooth.copy()
    if prof.jitter_px > 0 or prof.jitter_deg > 0:
        amp = prof.jitter_px * w / REFERENCE_WIDTH
        jx = amp * _shake(rng, n, fps)
        jy = amp * _shake(rng, n, fps)
        ja = np.radians(prof.jitter_deg) * _shake(rng, n, fps)
        cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
        for t in range(n):
            c, si = np.cos(ja[t]), np.sin(ja[t])
            J = np.array([[c, -si, cx - c * cx + si * cy + jx[t]], [si, c, cy - si * cx - c * cy + jy[t]], [0, 0, 1.0]])
            map_to_frame[t] = normalize(J @ smooth[t])
    if prof.jitter_tilt_deg > 0:  # the camera turning about its own centre: K @ R(pitch, roll) @ K^-1 on the left
        amp = np.radians(prof.jitter_tilt_deg)
        pitch_shake, roll_shake = amp * _shake(rng, n, fps), amp * _shake(rng, n, fps)
        K = np.array([[focal, 0, (w - 1) / 2.0], [0, focal, (h - 1) / 2.0], [0, 0, 1.0]])
        K_inv = np.linalg.inv(K)
        for t in range(n):
            map_to_frame[t] = normalize(K @ _rotation(pitch_shake[t], roll_shake[t], 0.0) @ K_inv @ map_to_frame[t])

    plan = FlightPlan(map_to_frame, smooth, (w, h), profile, int(seed), (W, H), float(fps))
    if prof.effects is not None:
        plan.effects = _effects(rng, plan, prof.effects)
    check_inside(plan)
    return plan


def _shake(rng: np.random.Generator, n: int, fps: float) -> np.ndarray:
    """3-8 Hz shake in [-1, 1]: a few sinusoids with drifting amplitude."""
    t = np.arange(n) / fps
    out = np.zeros(n)
    total = 0.0
    for _ in range(3):
        freq = rng.uniform(3.0, 8.0)
        amp = rng.uniform(0.5, 1.0)
        envelope = 0.75 + 0.25 * np.sin(2 * np.pi * t / rng.uniform(2, 6) + rng.uniform(0, 2 * np.pi))
        out += amp * envelope * np.sin(2 * np.pi * freq * t + rng.uniform(0, 2 * np.pi))
        total += amp
    return out / total


def _effects(rng: np.random.Generator, plan: FlightPlan, deg: Degradation) -> dict[str, np.ndarray]:
    """Per-frame exposure gain, noise sigma, motion blur vector (and, where the profile has them,
    contrast and vignetting) of a degraded flight."""
    n, fps = plan.frames, plan.fps
    w, h = plan.size
    gain = np.exp(deg.exposure * smooth_signal(rng, n, fps, (3, 12)) + 0.02 * rng.standard_normal(n))
    lo, hi = deg.noise
    noise = lo + (hi - lo) * (0.5 + 0.5 * smooth_signal(rng, n, fps, (2, 8)))
    # blur along the image motion: the motion during the exposure plus episodes of shake blur
    pw = plan.pairwise
    c = np.array([[(w - 1) / 2.0, (h - 1) / 2.0]])
    motion = np.zeros((n, 2))
    if len(pw):
        moved = project(pw, np.broadcast_to(c, (len(pw), 1, 2)))[:, 0] - c
        motion[1:] = moved
        motion[0] = moved[0]
    extra = np.clip(smooth_signal(rng, n, fps, (1, 5)), 0, None) * deg.shake_blur_px * w / REFERENCE_WIDTH
    norm = np.linalg.norm(motion, axis=1, keepdims=True)
    direction = np.where(norm > 1e-9, motion / np.maximum(norm, 1e-9), np.array([[1.0, 0.0]]))
    s_lo, s_hi = deg.shutter
    shutter = s_lo + (s_hi - s_lo) * (0.5 + 0.5 * smooth_signal(rng, n, fps, (2, 8))) if s_hi > s_lo else np.full(n, s_lo)
    blur = motion * shutter[:, None] + direction * extra[:, None]
    out = {"gain": gain, "noise_sigma": noise, "blur": blur}
    # Draws for the stronger degradations come last, so that 'hard' flights stay as they were.
    if deg.exposure_jumps > 0:
        steps = (rng.random(n) < 1.5 / fps) * rng.normal(0.0, deg.exposure_jumps, n)  # about 1.5 jumps/s
        # auto exposure corrects a jump over about half a second
        level = np.zeros(n)
        for t in range(1, n):
            level[t] = level[t - 1] * np.exp(-1.0 / (0.5 * fps)) + steps[t]
        out["gain"] = gain * np.exp(level)
    if deg.vignette[1] > 0:
        out["vignette"] = np.full(n, rng.uniform(*deg.vignette))
    if deg.contrast[0] < 1:
        c_lo, c_hi = deg.contrast
        out["contrast"] = c_lo + (c_hi - c_lo) * (0.5 + 0.5 * smooth_signal(rng, n, fps, (5, 20)))
    return out


VIBRATION_ROTATION = 0.2  # the vibration's rotation moves the frame corners by this share of its translation


NOISE_COMPONENTS = 64  # sinusoids per channel of a noise vibration


def add_rolling_shutter(plan: FlightPlan, rolling: RollingShutter) -> FlightPlan:
    """``plan`` seen by a rolling-shutter camera on a vibrating drone.

    The trajectory between frames is the cubic spline of the (normalised) entries of
    ``map_to_frame`` over time (extrapolated for the last frame's late rows); the vibration is
    an exact function of time (:func:`vibration_signal`).  ``row_bands[t, k]`` is the camera at
    band k's centre row time, ``map_to_frame[t]`` (and ``smooth_map_to_frame[t]``, without shake
    or vibration) the camera at the frame's mid time, so pairwise motions stay mid-time to mid-time."""
    from scipy.interpolate import CubicSpline

    if not rolling.any:
        return plan
    n = plan.frames
    w, h = plan.size
    frame_index = np.arange(n, dtype=np.float64)
    shaken = CubicSpline(frame_index, normalize(plan.map_to_frame).reshape(n, 9), axis=0)
    smooth = CubicSpline(frame_index, normalize(plan.smooth_map_to_frame).reshape(n, 9), axis=0)
    signal = vibration_signal(plan.size, rolling, plan.seed)

    def camera(times: np.ndarray) -> np.ndarray:
        base = shaken(times).reshape(*times.shape, 3, 3)
        return normalize(offset_matrix(plan.size, *signal(times / plan.fps)) @ base)

    bands = frame_index[:, None] + row_times(band_centres(h, rolling.bands), h, rolling.readout)[None]  # (N, K)
    mid = frame_index + float(row_times(np.array([mid_row(h)]), h, rolling.readout)[0])
    out = replace(plan, map_to_frame=camera(mid), smooth_map_to_frame=normalize(smooth(mid).reshape(n, 3, 3)),
                  rolling=rolling, row_bands=camera(bands))
    check_inside(out)
    return out


def vibration_signal(size: tuple[int, int], rolling: RollingShutter, seed: int) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``signal(seconds) -> (jx, jy, angle)``: the vibration's shift (frame px) and rotation
    (radians, about the frame centre) at each time, exactly: the first tone as it always was
    (phases from the seed's stream 6007), further tones from the same stream after it, the noise
    from a stream of its own (6011), so that adding either leaves the others unchanged."""
    w, h = size
    rng = np.random.default_rng([int(seed), 6007])
    phases = rng.uniform(0.0, 2.0 * np.pi, 3)
    tones = [(rolling.vibration_hz, rolling.vibration_px, phases)]
    tones += [(hz, px, rng.uniform(0.0, 2.0 * np.pi, 3)) for hz, px in rolling.tones]
    components: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # per channel: freqs, amplitudes, phases
    noise = rolling.noise
    if noise is not None and noise.any:
        nrng = np.random.default_rng([int(seed), 6011])
        m = NOISE_COMPONENTS
        for rms in (noise.px * w / REFERENCE_WIDTH, noise.px * w / REFERENCE_WIDTH, np.radians(noise.deg)):
            freqs = noise.low_hz + (noise.high_hz - noise.low_hz) * (np.arange(m) + nrng.uniform(0.0, 1.0, m)) / m
            # m sinusoids of amplitude a: RMS a sqrt(m / 2)
            components.append((freqs, np.full(m, rms * np.sqrt(2.0 / m)), nrng.uniform(0.0, 2.0 * np.pi, m)))

    def signal(seconds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        seconds = np.asarray(seconds, dtype=np.float64)
        out = [np.zeros(seconds.shape) for _ in range(3)]
        for i, (hz, px, ph) in enumerate(tones):
            if i and not (hz > 0 and px > 0):
                continue
            amp = px * w / REFERENCE_WIDTH
            rot = VIBRATION_ROTATION * amp / (0.5 * np.hypot(w, h))
            wave = [np.sin(2.0 * np.pi * hz * seconds + p) for p in ph]
            jx, jy, angle = amp * wave[0], amp * wave[1], rot * wave[2]
            out = [jx, jy, angle] if i == 0 else [out[0] + jx, out[1] + jy, out[2] + angle]
        for c, (freqs, amps, ph) in enumerate(components):
            out[c] = out[c] + np.einsum("m,...m->...", amps, np.sin(2.0 * np.pi * freqs * seconds[..., None] + ph))
        return out[0], out[1], out[2]

    return signal


def offset_matrix(size: tuple[int, int], jx: np.ndarray, jy: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(..., 3, 3) frame -> frame: a rotation by ``angle`` about the frame centre, then a shift (jx, jy)."""
    w, h = size
    c, s = np.cos(angle), np.sin(angle)
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    J = np.zeros(np.shape(angle) + (3, 3))
    J[..., 0, 0], J[..., 0, 1], J[..., 0, 2] = c, -s, cx - c * cx + s * cy + jx
    J[..., 1, 0], J[..., 1, 1], J[..., 1, 2] = s, c, cy - s * cx - c * cy + jy
    J[..., 2, 2] = 1.0
    return J


def footprints(plan: FlightPlan) -> np.ndarray:
    """(N, 4, 2) map positions of the frame corners, for the shaken and the smooth path."""
    c = frame_corners(*plan.size)
    both = np.concatenate([plan.map_to_frame, plan.smooth_map_to_frame])
    return project(np.linalg.inv(both), np.broadcast_to(c, (len(both), 4, 2)))


def check_inside(plan: FlightPlan) -> None:
    W, H = plan.map_size
    corners = footprints(plan)
    if not np.all(np.isfinite(corners)):
        raise BadInput("the planned flight sees beyond the horizon (internal error)")
    lo, hi = corners.min(axis=(0, 1)), corners.max(axis=(0, 1))
    if lo[0] < -0.5 or lo[1] < -0.5 or hi[0] > W - 0.5 or hi[1] > H - 0.5:
        raise BadInput(
            f"map of {W}x{H} px is too small for this flight of {plan.size[0]}x{plan.size[1]} frames "
            f"(footprint reaches {lo.round(1).tolist()}..{hi.round(1).tolist()})"
        )
