"""Stretches of a flight where the frames carry no motion cue: what the sequence model is for.

Every 12-30 frames (``every``), 1-3 consecutive frames (``length``) are spoilt by one of:

==========  =======================================================================
glare       washed out: the sun in the lens, the frame almost white, a faint residue
blur        a gust's motion blur, 40-80 px long (1280x720-equivalent) in any direction
dark        nearly black: auto exposure caught out, a tunnel of shade
flat        featureless: fog, a white roof, calm water (contrast down to a few percent)
drop        a frame the camera dropped: the next pair spans two frame intervals
duplicate   a frame written twice by the encoder: no motion between the two copies
==========  =======================================================================

The pixel kinds (glare, blur, dark, flat) leave the geometry alone; ``drop`` and ``duplicate``
change it, and the ground truth follows (``pairwise`` is exact for them too).  The frames
touched are recorded in the ground truth (``"bursts": [{"frame": t, "kind": k}, ...]``), so that
``mosaic bench`` scores the pairs that touch them apart (:func:`burst_pairs`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mosaic_cli.errors import BadInput

PIXEL_KINDS = ("glare", "blur", "dark", "flat")
GEOMETRY_KINDS = ("drop", "duplicate")
KINDS = PIXEL_KINDS + GEOMETRY_KINDS
CODES = {kind: k + 1 for k, kind in enumerate(PIXEL_KINDS)}  # per-frame effect codes; 0 = none
# Each pixel kind's strength: the ground's residue under glare, the blur's length in 1280-wide px,
# the brightness kept in the dark, the contrast kept on featureless ground.
LEVELS = {"glare": (0.03, 0.12), "blur": (40.0, 80.0), "dark": (0.02, 0.06), "flat": (0.02, 0.06)}


@dataclass(frozen=True)
class BurstSpec:
    """Which bursts a flight has, how often and how long (``mosaic simulate --bursts``)."""

    kinds: tuple[str, ...] = ()
    every: tuple[int, int] = (12, 30)  # frames from one burst's start to the next
    length: tuple[int, int] = (1, 3)  # frames spoilt by one pixel burst (drops and duplicates: 1)

    def __post_init__(self) -> None:
        unknown = [k for k in self.kinds if k not in KINDS]
        if unknown:
            raise BadInput(f"--bursts: unknown kind {unknown[0]!r}: choose from {', '.join(KINDS)} or all")
        if not 2 <= self.every[0] <= self.every[1]:
            raise ValueError(f"burst spacing must be 2 <= low <= high, got {self.every}")
        if not 1 <= self.length[0] <= self.length[1] < self.every[0]:
            raise ValueError(f"burst length must be 1 <= low <= high < spacing, got {self.length}")

    @property
    def any(self) -> bool:
        return bool(self.kinds)

    @classmethod
    def parse(cls, text: str | None) -> BurstSpec:
        """``None`` or "none" -> no bursts; "all" -> every kind; else a comma-separated list."""
        if text is None or text.strip().lower() in ("", "none"):
            return cls()
        words = [w.strip().lower() for w in text.split(",") if w.strip()]
        if words == ["all"]:
            return cls(KINDS)
        return cls(tuple(dict.fromkeys(words)))


@dataclass(frozen=True)
class Burst:
    frame: int  # index in the written video
    kind: str


def plan_bursts(frames: int, spec: BurstSpec, seed: int) -> list[Burst]:
    """The bursts of a flight of ``frames`` frames (video indices after drops), drawn from
    ``seed`` alone.  The first and last few frames stay clean, so every burst has frames on
    both sides to carry the motion from."""
    if not spec.any:
        return []
    rng = np.random.default_rng([int(seed), 31337])
    out: list[Burst] = []
    t = int(rng.integers(spec.every[0], spec.every[1] + 1))
    while t < frames - spec.length[1] - 2:
        kind = str(rng.choice(spec.kinds))
        length = 1 if kind in GEOMETRY_KINDS else int(rng.integers(spec.length[0], spec.length[1] + 1))
        out += [Burst(t + k, kind) for k in range(length)]
        t += int(rng.integers(spec.every[0], spec.every[1] + 1))
    return out


def frames_to_plan(frames: int, spec: BurstSpec) -> int:
    """How many frames to fly so that ``frames`` remain once the drops are taken out (at most
    one drop per burst)."""
    if "drop" not in spec.kinds:
        return frames
    return frames + frames // spec.every[0] + 1


def apply_bursts(plan, bursts: list[Burst], frames: int, seed: int):
    """A copy of ``plan`` (a :class:`~mosaic_cli.simulate.trajectory.FlightPlan` of at least
    ``frames`` + the drops frames) with ``bursts`` applied and cut to ``frames`` frames.

    ``drop`` at video frame t: the flown frame between video frames t-1 and t is taken out.
    ``duplicate`` at t: frame t shows exactly what frame t-1 shows.  Pixel kinds: per-frame
    codes and parameters in ``plan.effects`` ("burst", "burst_level", "burst_angle") that
    :func:`~mosaic_cli.simulate.render.apply_effects` renders."""
    rng = np.random.default_rng([int(seed), 4243])
    keep = np.ones(plan.frames, bool)
    drops = sorted(b.frame for b in bursts if b.kind == "drop")
    for k, t in enumerate(drops):  # video frame t is flown frame t + (drops before it)
        keep[t + k] = False
    index = np.flatnonzero(keep)[:frames]
    if len(index) < frames:
        raise ValueError(f"plan of {plan.frames} frames is too short for {frames} frames and {len(drops)} drops")
    M, smooth = plan.map_to_frame[index].copy(), plan.smooth_map_to_frame[index].copy()
    bands = None if plan.row_bands is None else plan.row_bands[index].copy()
    effects = {k: np.asarray(v)[index].copy() for k, v in plan.effects.items()}
    code, level, angle = np.zeros(frames, np.int64), np.zeros(frames), np.zeros(frames)
    for b in bursts:
        t = b.frame
        if b.kind == "duplicate":
            M[t], smooth[t] = M[t - 1], smooth[t - 1]
            if bands is not None:
                bands[t] = bands[t - 1]
            for v in effects.values():  # the same pixels: the same effects too
                v[t] = v[t - 1]
        elif b.kind in CODES:
            code[t] = CODES[b.kind]
            # one draw per kind, in PIXEL_KINDS order, whatever the kind: the flights made so far stay as they were
            level[t] = {kind: rng.uniform(*LEVELS[kind]) for kind in PIXEL_KINDS}[b.kind]
            angle[t] = rng.uniform(0.0, np.pi)
    if code.any():
        effects.update({"burst": code, "burst_level": level, "burst_angle": angle})
    return replace(plan, map_to_frame=M, smooth_map_to_frame=smooth, effects=effects, row_bands=bands)


def burst_pairs(bursts: list[dict] | list[Burst], pairs: int) -> np.ndarray:
    """(pairs,) bool: the frame pairs (t, t+1) that touch a burst: both pairs around a spoilt
    frame, the pair that spans a drop, the pair that repeats a frame."""
    touched = np.zeros(pairs, bool)
    for b in bursts:
        t, kind = (b.frame, b.kind) if isinstance(b, Burst) else (int(b["frame"]), str(b["kind"]))
        around = (t - 1,) if kind in GEOMETRY_KINDS else (t - 1, t)
        for p in around:
            if 0 <= p < pairs:
                touched[p] = True
    return touched


__all__ = ["KINDS", "CODES", "LEVELS", "BurstSpec", "Burst", "plan_bursts", "frames_to_plan", "apply_bursts", "burst_pairs"]
