"""The learned estimator's per-pair checks: whether a pair's estimate is trusted, and by which path.

Each frame is described once (:meth:`PairChecks._read_frame`: texture, the corners and band-passed
image the polish reads, whether it is spoilt: glare, a gust's blur, near black, featureless).
Each pair is then checked on its own frames (:meth:`PairChecks._check`: the network's estimate
plausible, the polish and its wide retry, the correlation of the registered detail, ORB's
registration where the learned path cannot confirm the pair or only its wide polish placed it)
and decided in order (:meth:`PairChecks._decide`: learned, fallback, carried or failed, with its
confidence), the carried motion being what the pairs before it left.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from mosaic_cli.estimators.base import Estimator, PairEstimate
from mosaic_cli.estimators.correlation import band_agreement, detail_level, detail_zncc, fine_detail
from mosaic_cli.estimators.learned_config import LearnedConfig
from mosaic_cli.estimators.orb import OrbEstimator
from mosaic_cli.estimators.refine import Polish, PolishConfig, align_pixels, band_pass, points_to_track, track_points
from mosaic_cli.geometry import is_valid

PATHS = ("learned", "fallback", "carried", "failed")  # which path produced a pair, counted in ``path_counts``

SPOILT_HISTORY = 15  # frames the detail reference is the median of
SPOILT_HISTORY_MIN = 2  # frames needed before any is called spoilt


@dataclass
class WorkFrame:
    """A frame at the working resolution and what the polish needs of it, computed once (a frame
    is the second of one pair and the first of the next, possibly in the next chunk)."""

    gray: np.ndarray
    textured: bool | None = None
    points: np.ndarray | None = None  # Shi-Tomasi corners to track (LK polish)
    aligned: np.ndarray | None = None  # the image the polish aligns (band-passed gray)
    detail: np.ndarray | None = None  # fine detail (gray minus its 5x5 mean), for the ZNCC check
    features: tuple | None = None  # ORB keypoints and descriptors, when the fallback needed them
    level: float | None = None  # band-passed detail (correlation.detail_level), when a spoilt frame is looked for
    spoilt: bool | None = None  # no motion cue: glare, heavy blur, near black, featureless (see LearnedConfig.carry)
    # ``detail`` and ``features`` are made when a pair first needs them; two pairs share the frame,
    # and on the pool their threads may ask at once: the lock has one make it.
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)


@dataclass(frozen=True)
class PairCheck:
    """What a pair's own frames say of it, whatever the pairs before (so pairs are checked on the
    pool in any order): the network's estimate is plausible, the polish, the correlation of the
    registered detail, and the fallback's registration when it is to take the pair."""

    plausible: bool
    polished: Polish | None  # None: not polished (an implausible estimate, a frame without texture)
    zncc: float
    related: bool  # the registered detail correlates (or no minimum is asked)
    fallback: tuple[np.ndarray, float] | None  # the fallback's (H, confidence) when it wins the pair


class PairChecks(Estimator):
    """The per-pair half of :class:`~mosaic_cli.estimators.learned.LearnedEstimator`: what a
    pair's own frames say of it (:meth:`_check`, run on the pool's threads in any order) and the
    estimate that follows from that and the pairs before it (:meth:`_decide`, in order)."""

    # Set by LearnedEstimator (__init__, reset).
    config: LearnedConfig
    positions: np.ndarray  # the patches' top-left corners (M, 2)
    patch: int
    _fallback: OrbEstimator | None
    _band: tuple | None  # the polish's band-pass, None: the gray frame itself
    _corner_mask: np.ndarray | None
    _motion: np.ndarray  # the last confirmed pair's motion (working px)
    _detail_levels: list[float]
    _confirmed_once: bool
    _carried_run: int
    path_counts: dict[str, int]
    _zncc_use: np.ndarray | None

    def _check(self, prev: WorkFrame, cur: WorkFrame, seed: np.ndarray, offsets_ok: bool) -> PairCheck:
        """What the pair's own frames say of it (see :class:`PairCheck`): nothing here reads or
        changes what the pairs before it left (run on the pool's threads)."""
        # The network's estimate is plausible (finite, not a fold or a blow-up) whatever the frames;
        # only on textured frames can the polish and the checks confirm it.  A carried pair may
        # take a plausible estimate (carry=network): a sequence model's, on a frame without
        # texture, is what its state carried over.
        plausible = bool(offsets_ok) and bool(is_valid(seed, self.work_size, max_area_ratio=self.config.max_area_ratio))
        valid = bool(plausible and prev.textured and cur.textured)
        polished, settled = self._polish(prev, cur, seed) if valid else (None, False)
        zncc = self._zncc(prev, cur, polished.H) if polished is not None else 0.0
        related = self.config.min_zncc is None or zncc >= self.config.min_zncc
        confirmed = polished is not None and related and (polished.refined or self.config.refine is None)
        fallback = None
        if (not confirmed or not settled) and self._fallback is not None and prev.textured and cur.textured:
            H_orb, orb_confidence = self._fallback.register(prev.gray, cur.gray, self._orb_features(prev), self._orb_features(cur))
            orb_ok = H_orb is not None and np.all(np.isfinite(H_orb))
            # Only the wide polish placed the pair: where its large windows were fooled, ORB's
            # features may do better; the registration whose band-passed frames agree more wins.
            # (confirmed: polished is set)
            if orb_ok and (not confirmed or (polished is not None and self._agreement(prev, cur, H_orb) > self._agreement(prev, cur, polished.H))):
                fallback = (H_orb, orb_confidence)
        return PairCheck(plausible, polished, zncc, related, fallback)

    def _decide(self, prev: WorkFrame, cur: WorkFrame, seed: np.ndarray, agreement: float, check: PairCheck) -> PairEstimate:
        """The pair's estimate from its check and what the pairs before it left (the carried
        motion): pairs are decided one at a time, in order."""
        if check.fallback is not None:
            return self._result(*check.fallback, "fallback")
        polished = check.polished
        if polished is None or not check.related:
            if self._can_carry() and (prev.spoilt or cur.spoilt):
                return self._carried(seed, check.plausible)
            return self._result(None, 0.0, "failed")
        confidence = max(0.0, check.zncc) * float(agreement) * self._polish_weight(polished)
        return self._result(polished.H, confidence, "learned")

    def _orb_features(self, frame: WorkFrame) -> tuple:
        """The frame's ORB features for the fallback, described once (the first pair to ask)."""
        assert self._fallback is not None
        with frame.lock:
            if frame.features is None:
                frame.features = self._fallback.features_of(frame.gray)
            return frame.features

    def _carried(self, seed: np.ndarray, plausible: bool) -> PairEstimate:
        carried = seed if self.config.carry == "network" and plausible else self._motion
        return self._result(carried, self.config.carry_confidence, "carried")

    def _can_carry(self) -> bool:
        """Whether a pair no path confirms may take the carried motion (see LearnedConfig.carry)."""
        c = self.config
        return c.carry != "none" and self._confirmed_once and self._carried_run < c.carry_limit

    def _result(self, H_work: np.ndarray | None, confidence: float, path: str) -> PairEstimate:
        self.path_counts[path] += 1
        if path == "carried":
            self._carried_run += 1
        elif path != "failed":  # the frames placed a pair again: a new run may be carried
            self._carried_run = 0
        if H_work is None:
            return replace(PairEstimate.failed(), path=path)
        if confidence > 0:
            self._confirmed_once = self._confirmed_once or path != "carried"
            self._motion = H_work
        estimate = self._to_full(H_work, confidence)
        return replace(estimate, path=path if estimate.confidence > 0 or path == "failed" else "failed")

    def _read_frame(self, frame: WorkFrame) -> None:
        """Whether the frame has texture to register (black, blown-out, flat or badly blurred
        frames do not) and, for the polish, its band-passed image and corners; whether it is spoilt."""
        if frame.textured is not None:
            return
        self._texture(frame)
        self._judge_spoilt(frame)

    def _texture(self, frame: WorkFrame) -> None:
        """The part of :meth:`_read_frame` that reads the frame alone (run on the pool's threads):
        its texture, corners and band-passed image, and its detail level if it is textured."""
        c = self.config
        if c.refine == "lk":
            frame.points = points_to_track(frame.gray, c.corners, self._corner_mask)
            frame.textured = len(frame.points) > 0
        else:
            frame.textured = bool(cv2.cornerMinEigenVal(frame.gray, c.corners.block_size).max() >= c.corners.min_response)
        if c.refine is not None and frame.textured:
            frame.aligned = band_pass(frame.gray, *self._band) if self._band else frame.gray
        if c.carry != "none" and frame.textured:  # only the carried motion asks whether a frame is spoilt
            frame.level = detail_level(frame.gray)

    def _judge_spoilt(self, frame: WorkFrame) -> None:
        """Whether the frame is spoilt, against the frames before it: frames are told in order."""
        if self.config.carry != "none":  # a frame without texture has no level, and is spoilt
            frame.spoilt = frame.level is None or self._spoilt(frame.level)

    def _spoilt(self, level: float) -> bool:
        """Whether a frame of this band-passed detail carries no motion cue: far less detail than
        the median of the flight's recent unspoilt frames (which then takes it in)."""
        recent = self._detail_levels
        spoilt = len(recent) >= SPOILT_HISTORY_MIN and level < self.config.spoilt_ratio * float(np.median(recent))
        if not spoilt:
            recent.append(level)
            del recent[:-SPOILT_HISTORY]
        return spoilt

    def _polish(self, prev: WorkFrame, cur: WorkFrame, H: np.ndarray) -> tuple[Polish, bool]:
        """The polished estimate, and whether the cheap polish settled it (from the seed, or from
        where the wide polish found the basin): the wide polish alone is less sure."""
        c = self.config
        if c.refine is None:
            return Polish(H, False, 1.0), True
        result = self._polish_once(prev, cur, H, c.polish)
        if result.refined or c.polish_wide is None or c.retry == "none":
            return result, True
        wide = self._polish_once(prev, cur, H, c.polish_wide)
        if not wide.refined:
            return wide, True
        fine = self._polish_once(prev, cur, wide.H, c.polish)
        return (fine, True) if fine.refined else (wide, False)

    def _polish_once(self, prev: WorkFrame, cur: WorkFrame, H: np.ndarray, config: PolishConfig) -> Polish:
        # Only textured frames are polished, and _read_frame gave those their aligned image (and corners, lk).
        assert prev.aligned is not None and cur.aligned is not None
        if self.config.refine == "lk":
            assert prev.points is not None
            return track_points(prev.aligned, cur.aligned, H, prev.points, config, self.work_mask)
        return align_pixels(prev.aligned, cur.aligned, H, config, self.work_mask)

    def _polish_weight(self, p: Polish) -> float:
        """The polish's say in the confidence: its score when it confirmed the network's estimate,
        a fixed discount when it could not; 1 without a polish."""
        if self.config.refine is None:
            return 1.0
        w = self.config.unpolished_weight
        return w + (1.0 - w) * p.score if p.refined else w

    def _zncc(self, prev: WorkFrame, cur: WorkFrame, H: np.ndarray) -> float:
        """The correlation of the pair's fine detail registered by ``H`` (:func:`.correlation.detail_zncc`),
        each frame's detail made once."""
        return detail_zncc(self._detail(prev), self._detail(cur), H, self.positions, self.patch, self._valid_pixels(), self.work_mask)

    def _detail(self, frame: WorkFrame) -> np.ndarray:
        """The frame's fine detail, made once (the first pair to ask)."""
        with frame.lock:
            if frame.detail is None:
                frame.detail = fine_detail(frame.gray)
            return frame.detail

    def _valid_pixels(self) -> np.ndarray:
        """1 where a pixel of a working frame may be used (the mask allows it), 0 elsewhere;
        made once per video."""
        use = self._zncc_use
        if use is None:
            use = self._zncc_use = (np.ones(self.work_size[::-1], np.float32) if self.work_mask is None
                                    else (self.work_mask > 0).astype(np.float32))
        return use

    def _agreement(self, prev: WorkFrame, cur: WorkFrame, H: np.ndarray) -> float:
        """The correlation of the pair's band-passed frames registered by ``H`` (:func:`.correlation.band_agreement`):
        to choose between two registrations of one pair."""
        assert prev.aligned is not None and cur.aligned is not None  # asked only of polished (textured) pairs
        return band_agreement(prev.aligned, cur.aligned, H, self._valid_pixels(), self.work_mask)
