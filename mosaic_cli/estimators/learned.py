"""The paper's learned estimator at test time: a trained :class:`HomographyNet` run over a video.

    frame -> gray, working size (320 px wide), [-1, 1]
          -> every ``chunk`` frame pairs: (with prior=velocity, frame t+1 pre-aligned by the last
             confirmed motion P), the patch pairs cut (the centre 128x128, as the
             paper, or several places), backbone on the whole chunk in one batch (on a CPU in int8
             when the weights carry calibrated ranges, see mosaic_cli.model.quantize; else fp32
             channels-last)
          -> LSTM stepped pair by pair with (h, c) carried through the whole video
          -> offsets -> DLT -> homography of the working frame, frame t -> t+1 (P @ it with a prior)
          -> several patches: consensus (per-corner median of where the frame corners go)
          -> polish, per pair, seeded by the network (default "lk": Shi-Tomasi corners of frame t
             tracked into frame t+1 by pyramidal Lucas-Kanade on band-passed frames, starting
             where the network puts them, robust refit; see :mod:`.refine`)
          -> where that cheap polish fails, a wide one (a deep pyramid, large windows) looks for
             the basin and the cheap one places the pair from there
          -> confirmed when the polish agreed and the registered detail correlates (ZNCC); else
             the classical fallback (ORB + its polish) tries the pair; a pair only the wide
             polish could place is contested by ORB (the better band-passed correlation wins)
          -> confidence (ZNCC of the registered patches x agreement between patches x how much
             of the polish agreed), or ORB's when the fallback made the pair
          -> a pair no path confirms, one of whose frames is spoilt (glare, a gust's blur, near
             black, featureless) -> the motion carried across the frames, with a low confidence
             (``carry``: the network's estimate, which for the LSTM reads its carried state, or
             the last confirmed motion)
          -> invalid, a frame without texture, or detail that does not correlate once registered
             (unrelated ground), with no fallback estimate -> identity with confidence 0; else
             re-expressed at full resolution exactly
    ``path_counts`` says which path made each pair: learned, fallback, carried or failed.
    A chunk's frames are described and its pairs polished, checked and tried by the fallback on a
    pool of threads (``--threads``, default one a core; OpenCV lets go of the GIL); the carry and
    the prior then follow pair by pair, in order: the same estimates on any number.
    On a GPU (or with ``polish-with=torch``) the chunk's cheap LK polish, its refit and the
    correlation check first run batched on the device (:mod:`.batched`, OpenCV's arithmetic);
    only the pairs it does not settle go to the pool, checked as above.

Beside it: its options (:mod:`.learned_config`), the correlation checks (:mod:`.correlation`),
where the shipped weights are (:mod:`.weights`) and the polish (:mod:`.refine`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from mosaic_cli.device import pair_threads, resolve_device, use_cpu_threads
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import LEARNED, batched
from mosaic_cli.estimators.base import Estimator, PairEstimate
from mosaic_cli.estimators.correlation import band_agreement, detail_level, detail_zncc, fine_detail
from mosaic_cli.estimators.learned_config import PATCH_LAYOUTS, PRECISIONS, LearnedConfig
from mosaic_cli.estimators.orb import OrbEstimator
from mosaic_cli.estimators.refine import (
    Polish,
    PolishConfig,
    align_pixels,
    band_pass,
    erode_mask,
    points_to_track,
    track_points,
)
from mosaic_cli.estimators.weights import default_weights
from mosaic_cli.geometry import frame_corners, is_valid
from mosaic_cli.geometry.tensor import four_point_to_homography, project
from mosaic_cli.model.checkpoint import load_weights
from mosaic_cli.model.network import HomographyNet
from mosaic_cli.model.patches import offsets_to_homography
from mosaic_cli.model.quantize import quantized_features, quantized_head

PATHS = ("learned", "fallback", "carried", "failed")  # which path produced a pair, counted in ``path_counts``


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


def patch_positions(work_size: tuple[int, int], patch: int, layout: int) -> np.ndarray:
    """Top-left (x, y) of the patches (M, 2): the centre (paper: x=96, y=26 at 320x180), the
    centre and the four corners, or a 3x3 grid spread over the frame."""
    w, h = work_size
    span_x, span_y = w - patch, h - patch
    cx, cy = span_x // 2, span_y // 2
    if layout == 1:
        pts = [(cx, cy)]
    elif layout == 5:
        pts = [(cx, cy), (0, 0), (span_x, 0), (span_x, span_y), (0, span_y)]
    elif layout == 9:
        pts = [(x, y) for y in (0, cy, span_y) for x in (0, cx, span_x)]
    else:
        raise BadInput(f"patches must be one of {', '.join(map(str, PATCH_LAYOUTS))}, got {layout}")
    return np.array(pts, dtype=np.int64)


class LearnedEstimator(Estimator):
    """Streaming inference with a trained net; ``feed`` returns estimates a chunk at a time.

    ``threads``: the threads that finish a chunk's pairs (None: ``--threads``, else every core; see
    :func:`mosaic_cli.device.pair_threads`), read at each ``reset``.  What a pair's own frames
    say of it (describing the frames, the polish and its wide retry, the correlation check, the
    fallback's registration: :meth:`_check`) runs on a pool of that many threads, OpenCV's calls
    letting go of the GIL; what follows from the pairs before it (the carried motion, the prior,
    the counts: :meth:`_decide`) runs after, pair by pair, in order.  Every result is
    the same, to the bit, whatever the number; with one, each pair is finished in turn on the
    calling thread, with no pool."""

    def __init__(self, model: HomographyNet, meta: dict, device: str = "auto", config: LearnedConfig | None = None,
                 threads: int | None = None):
        self.meta = meta
        self.threads = threads
        self._workers = 1  # the pool's threads for this video (reset)
        self._pool: ThreadPoolExecutor | None = None
        self._pool_size = 0
        self.work_size_trained = tuple(int(v) for v in meta.get("work_size", (320, 180)))
        super().__init__(self.work_size_trained[0])
        self.config = config or LearnedConfig()
        self.device = resolve_device(device)
        self.model = model.to(self.device).eval()
        self.precision = "fp32"
        self._features = self.model.features
        if self.device.type == "cpu":
            self.model = self.model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stubs lack Module.to(memory_format=)
            if self.config.precision != "fp32":
                int8 = quantized_features(self.model, meta.get("int8"))
                if int8 is not None:
                    self._features, self.precision = int8, "int8"
                    self.model = quantized_head(self.model, meta.get("int8")) or self.model
        if self.config.precision == "int8" and self.precision != "int8":
            raise BadInput("int8 needs a CPU with an int8 engine and weights with calibrated ranges "
                           "(mosaic train writes them; mosaic train CLIPS --calibrate WEIGHTS adds them to existing weights)")
        self.patch = model.config.patch
        self.name = meta.get("variant", model.config.head)
        self._prior_warp = self.config.prior == "velocity" and self.config.seed == "network"
        # The chunk's LK polish and check batched on the device (polish-with; see _finish_batched).
        on = self.config.polish_with
        self._batched = self.config.refine == "lk" and (on == "torch" or (on == "auto" and self.device.type == "cuda"))
        self._fallback = OrbEstimator(self.work_width) if self.config.fallback == "orb" else None
        self._pending: list[WorkFrame] = []
        self._ahead: tuple | None = None  # see _run_ahead
        self._state: tuple[torch.Tensor, ...] | None = None  # the LSTM's (h, c) between chunks
        self._pairs_done = 0
        self._motion = np.eye(3)
        self._detail_levels: list[float] = []
        self._confirmed_once = False
        self._carried_run = 0
        self.path_counts = dict.fromkeys(PATHS, 0)

    def reset(self, full_size: tuple[int, int]) -> None:
        super().reset(full_size)
        w, h = self.work_size
        if min(w, h) < self.patch:
            raise BadInput(
                f"frames of {full_size[0]}x{full_size[1]} are {w}x{h} at the working width, smaller than the "
                f"{self.patch}x{self.patch} patch the network reads"
            )
        self.positions = patch_positions(self.work_size, self.patch, self.config.patches)
        self._positions_t = torch.as_tensor(self.positions, device=self.device)
        self._corners = frame_corners(w, h)
        downscaled = full_size[0] >= self.config.polish_band_min_downscale * w
        self._band = self.config.polish_band if downscaled else None
        # Overlays (set_mask): no polish corner whose LK window would reach them.
        self._corner_mask = None if self.work_mask is None else erode_mask(self.work_mask, self.config.polish.window // 2 + 1)
        self._pending = []
        self._ahead = None  # the chunk checked on the pool while the next one's network runs (lookahead)
        self._state = None
        self._pairs_done = 0
        self._motion = np.eye(3)  # the last confirmed pair's motion (working px): the prior
        self._detail_levels = []  # band-passed detail of the recent unspoilt frames (see _describe)
        self._confirmed_once = False  # a pair was placed by the frames: there is a motion to carry
        self._carried_run = 0  # pairs carried in a row
        self.path_counts = dict.fromkeys(PATHS, 0)
        self._zncc_use: np.ndarray | None = None  # the usable-pixel image (work size) of _valid_pixels, made at the first pair
        self._batch_masks_t: tuple | None = None  # _batch_masks' tensors, made at the first batched chunk
        self._workers = self.threads if self.threads is not None else pair_threads()
        if self._workers < 1:
            raise ValueError(f"threads must be at least 1, got {self._workers}")
        if self._fallback is not None:
            self._fallback.set_mask(self.mask)  # the fallback's ORB keypoints and polish skip overlays too
            self._fallback.reset(full_size)

    def warm_up(self) -> None:
        """Run the network once on a chunk of blank pairs at the trained working size, so that
        its first real chunk does not pay for CUDA's kernels and cuDNN's plans (1.2-1.3 s on an
        H200: docs/measurements/gpu.md) or a CPU's first int8 calls.  Called by the build, which
        the commands run beside other work (the overlay detection, a live stream's opening).
        Leaves nothing behind: the LSTM's state and the pair count are as they were."""
        w, h = self.work_size_trained
        if min(w, h) < self.patch:
            return
        kept_state = (self._state, self._pairs_done)
        kept_positions = (self.positions, self._positions_t) if hasattr(self, "positions") else None  # (after a reset)
        try:
            self.positions = patch_positions((w, h), self.patch, self.config.patches)
            self._positions_t = torch.as_tensor(self.positions, device=self.device)
            blank = [np.full((h, w), 128, np.uint8)] * self.config.chunk
            self._state = None
            self._predict(blank, blank)
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
        finally:
            self._state, self._pairs_done = kept_state
            if kept_positions is not None:
                self.positions, self._positions_t = kept_positions

    # Streaming ----------------------------------------------------------------------------

    def feed(self, frame: np.ndarray) -> list[PairEstimate]:
        if self.full_size is None:
            raise RuntimeError("call reset(full_size) before feeding frames")
        self._pending.append(WorkFrame(self.prepared(frame)))
        if len(self._pending) - 1 >= self.config.chunk:
            return self._run_chunk()
        return []

    def finish(self) -> list[PairEstimate]:
        out = self._run_chunk() if len(self._pending) >= 2 else []
        return out + self._decide_ahead() if self._ahead is not None else out

    def _run_chunk(self) -> list[PairEstimate]:
        frames = self._pending
        self._pending = [frames[-1]]  # the last frame starts the next chunk's first pair
        pool = self._pair_pool()
        if pool is not None and self._looks_ahead(pool):
            return self._run_ahead(frames, pool)
        assert self._ahead is None, "a chunk looked ahead and the next did not"  # (the settings are a video's)
        described = self._describe_all(frames, pool)  # on the pool: while the network runs
        pairs = list(zip(frames[:-1], frames[1:]))
        if self.config.seed == "velocity":  # each pair starts from the one before: no batch, in turn
            described()
            return [self._finish_pair(prev, cur, self._motion, True, 1.0) for prev, cur in pairs]
        seeds, offsets_ok, agreement = self._seeds(frames)
        described()
        if self._batched:
            return self._finish_batched(pairs, seeds, offsets_ok, agreement, pool)
        if pool is None:  # one thread: each pair finished in turn
            return [self._finish_pair(prev, cur, seeds[k], offsets_ok[k], agreement[k]) for k, (prev, cur) in enumerate(pairs)]
        self._valid_pixels()  # made once, before the threads read it
        checks = pool.map(lambda k: self._check(pairs[k][0], pairs[k][1], seeds[k], bool(offsets_ok[k])), range(len(pairs)))
        # map yields in the pairs' order: each decided once those before it are
        return self._decide_all(pairs, seeds, offsets_ok, agreement, checks)

    def frames_held(self, lookahead: bool = False) -> int:
        """A chunk less one (its pairs are told once the chunk is full), and with ``lookahead``
        and a pool a chunk more (told when the next one is full: :meth:`_run_ahead`)."""
        workers = self.threads if self.threads is not None else pair_threads()
        ahead = lookahead and workers > 1 and self._can_look_ahead()
        return self.config.chunk - 1 + (self.config.chunk if ahead else 0)

    def _can_look_ahead(self) -> bool:
        """Whether a chunk's network reads nothing the decisions of the chunk before leave (no
        motion prior, no velocity seed), and its checks run on the pool (the batched polish waits
        on the device's one copy back anyway)."""
        return self.config.seed == "network" and not self._prior_warp and not self._batched

    def _looks_ahead(self, pool: ThreadPoolExecutor | None) -> bool:
        """Whether this chunk's network runs while the chunk before is checked (``lookahead``)."""
        return self.lookahead and pool is not None and self._can_look_ahead()

    def _run_ahead(self, frames: list[WorkFrame], pool: ThreadPoolExecutor) -> list[PairEstimate]:
        """:meth:`_run_chunk` a chunk late: this chunk's network runs on this thread while the
        pool checks the chunk before, whose pairs are then decided and returned; this chunk's
        checks start on the pool (decided at the next chunk, or at :meth:`finish`).  The same
        estimates, in the same order, as without the lookahead."""
        described = self._describe_all(frames, pool)
        pairs = list(zip(frames[:-1], frames[1:]))
        seeds, offsets_ok, agreement = self._seeds(frames)
        described()
        out = self._decide_ahead()
        self._valid_pixels()  # made once, before the threads read it
        futures = [pool.submit(self._check, prev, cur, seeds[k], bool(offsets_ok[k])) for k, (prev, cur) in enumerate(pairs)]
        self._ahead = (pairs, seeds, offsets_ok, agreement, futures)
        return out

    def _decide_ahead(self) -> list[PairEstimate]:
        """The pairs of the chunk whose checks run ahead, decided in order (none: [])."""
        if self._ahead is None:
            return []
        pairs, seeds, offsets_ok, agreement, futures = self._ahead
        self._ahead = None
        return self._decide_all(pairs, seeds, offsets_ok, agreement, (f.result() for f in futures))

    def _decide_all(self, pairs: list[tuple[WorkFrame, WorkFrame]], seeds: np.ndarray, offsets_ok: np.ndarray,
                    agreement: np.ndarray, checks) -> list[PairEstimate]:
        """The chunk's pairs decided in order from their checks (an iterable in the pairs' order)."""
        return [self._decide(prev, cur, seeds[k], agreement[k], check) for k, ((prev, cur), check) in enumerate(zip(pairs, checks))]

    def _finish_batched(self, pairs: list[tuple[WorkFrame, WorkFrame]], seeds: np.ndarray, offsets_ok: np.ndarray,
                        agreement: np.ndarray, pool: ThreadPoolExecutor | None) -> list[PairEstimate]:
        """The chunk's pairs with the polish and check batched on the device (:meth:`_batch_checks`);
        the pairs it does not settle are checked by :meth:`_check` as without it, on the pool."""
        settled = self._batch_checks(pairs, seeds, offsets_ok)
        todo = [k for k, check in enumerate(settled) if check is None]
        if pool is None:
            checked = {k: self._check(pairs[k][0], pairs[k][1], seeds[k], bool(offsets_ok[k])) for k in todo}
        else:
            self._valid_pixels()  # made once, before the threads read it
            checked = dict(zip(todo, pool.map(lambda k: self._check(pairs[k][0], pairs[k][1], seeds[k], bool(offsets_ok[k])), todo)))
        checks = [check if check is not None else checked[k] for k, check in enumerate(settled)]
        return self._decide_all(pairs, seeds, offsets_ok, agreement, checks)

    def _batch_checks(self, pairs: list[tuple[WorkFrame, WorkFrame]], seeds: np.ndarray,
                      offsets_ok: np.ndarray) -> list[PairCheck | None]:
        """The checks of the pairs the batched polish settles (:mod:`.batched`): the cheap LK polish
        of every plausible pair of textured frames, its refit and the correlation of the detail it
        registers, in one batch on the device and one copy back; a pair settles when the refit
        holds (enough inliers, close to the seed, plausible: :func:`.batched.settled`) and
        its detail correlates, as :meth:`_check` settles it without the wide polish or the
        fallback.  None for the others."""
        c = self.config
        checks: list[PairCheck | None] = [None] * len(pairs)
        todo = [k for k, (prev, cur) in enumerate(pairs) if prev.textured and cur.textured and bool(offsets_ok[k])
                and is_valid(seeds[k], self.work_size, max_area_ratio=c.max_area_ratio)]
        if not todo:
            return checks
        dev = self.device
        firsts, seconds = [pairs[k][0] for k in todo], [pairs[k][1] for k in todo]
        tracked = [f.points for f in firsts]  # a textured frame has its corners (refine=lk)
        counts = [0 if p is None else len(p) for p in tracked]
        points = np.zeros((len(todo), max(counts), 2), np.float32)
        for i, p in enumerate(tracked):
            points[i, : counts[i]] = p

        def stack(images: list) -> torch.Tensor:
            return torch.from_numpy(np.stack(images)).to(dev, non_blocking=True)

        allowed, usable, mask = self._batch_masks()
        result = batched.polish(stack([f.aligned for f in firsts]), stack([f.aligned for f in seconds]),
                                torch.from_numpy(seeds[todo]).to(dev), torch.from_numpy(points).to(dev),
                                torch.as_tensor(counts, device=dev), c.polish, allowed)
        zncc = batched.detail_zncc(batched.fine_detail(stack([f.gray for f in firsts])), batched.fine_detail(stack([f.gray for f in seconds])),
                                   result.H, self._positions_t, self.patch, usable, mask)
        back = torch.cat([result.H.flatten(1), result.found[:, None].double(), result.inliers[:, None].double(), zncc[:, None]], 1).cpu().numpy()
        for i, k in enumerate(todo):
            H, found, inliers, score = back[i, :9].reshape(3, 3), back[i, 9] > 0, back[i, 10], float(back[i, 11])
            if not found or (c.min_zncc is not None and score < c.min_zncc):
                continue
            checks[k] = PairCheck(True, Polish(H, True, float(inliers) / counts[i]), score, True, None)
        return checks

    def _batch_masks(self) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor | None]:
        """On the device, once a video: the pixels a cheap polish's track may touch (the mask eroded
        by its window's half; None: all), the usable pixels of the correlation check, the mask."""
        if self._batch_masks_t is None:
            use = torch.from_numpy(self._valid_pixels()).to(self.device)
            if self.work_mask is None:
                self._batch_masks_t = (None, use, None)
            else:
                eroded = erode_mask(self.work_mask, self.config.polish.window // 2 + 1)
                self._batch_masks_t = (torch.from_numpy(eroded).to(self.device), use, torch.from_numpy(self.work_mask).to(self.device))
        return self._batch_masks_t

    def _seeds(self, frames: list[WorkFrame]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each pair's starting estimate (n, 3, 3), whether the network's offsets were finite, and
        how much its patches agreed: the network's (after the motion prior), or the identity."""
        n = len(frames) - 1
        firsts, seconds = [f.gray for f in frames[:-1]], [f.gray for f in frames[1:]]
        if self.config.seed == "identity":
            return np.repeat(np.eye(3)[None], n, 0), np.ones(n, bool), np.ones(n)
        if self._prior_warp:
            # The motion prior P (the last confirmed motion when the chunk starts): the network reads
            # frame t+1 pre-aligned by P and regresses the rest R, so frame t -> t+1 is P @ R.
            prior = self._motion
            seconds = [cv2.warpPerspective(g, prior, self.work_size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                           borderMode=cv2.BORDER_REPLICATE) for g in seconds]
            residual, offsets_ok, agreement = self._network(firsts, seconds)
            return prior[None] @ residual, offsets_ok, agreement
        return self._network(firsts, seconds)

    def close(self) -> None:
        """Stop the pool's threads: idle workers would otherwise outlive the run (a live run's
        estimator, built beside the stream with the garbage collector frozen, is never collected)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool, self._pool_size = None, 0

    def _pair_pool(self) -> ThreadPoolExecutor | None:
        """The pool of this video's threads; None for one thread."""
        if self._workers <= 1:
            return None
        if self._pool is None or self._pool_size != self._workers:
            if self._pool is not None:
                self._pool.shutdown(wait=False)
            self._pool = ThreadPoolExecutor(self._workers, thread_name_prefix="mosaic-pairs")
            self._pool_size = self._workers
        return self._pool

    def _describe_all(self, frames: list[WorkFrame], pool: ThreadPoolExecutor | None) -> Callable[[], None]:
        """Describe the frames not yet described (:meth:`_describe`): now, in turn, without a pool;
        with one, their own part on the pool (:meth:`_texture`), and the call returned waits for it
        and tells the spoilt frames in the flight's order (:meth:`_spoil`)."""
        todo = [f for f in frames if f.textured is None]
        if pool is None:
            for f in todo:
                self._describe(f)
            return lambda: None
        futures: list[Future] = [pool.submit(self._texture, f) for f in todo]

        def described() -> None:
            for f, future in zip(todo, futures):
                future.result()
                self._spoil(f)

        return described

    def _network(self, firsts: list[np.ndarray], seconds: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The network's homographies (n, 3, 3) for the n pairs (firsts[k], seconds[k]), whether
        its offsets were finite, and how much its patches agreed."""
        H_patches, offsets_ok = self._predict(firsts, seconds)
        H_net, agreement = self._consensus(H_patches)
        return H_net, offsets_ok, agreement

    def _finish_pair(self, prev: WorkFrame, cur: WorkFrame, seed: np.ndarray, offsets_ok: bool, agreement: float) -> PairEstimate:
        """Polish the seed, confirm it by the correlation of the registered detail, and where the
        learned path cannot confirm the pair, let the classical fallback try it."""
        return self._decide(prev, cur, seed, agreement, self._check(prev, cur, seed, offsets_ok))

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
                frame.features = self._fallback._describe(frame.gray)
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

    def _describe(self, frame: WorkFrame) -> None:
        """Whether the frame has texture to register (black, blown-out, flat or badly blurred
        frames do not) and, for the polish, its band-passed image and corners; whether it is spoilt."""
        if frame.textured is not None:
            return
        self._texture(frame)
        self._spoil(frame)

    def _texture(self, frame: WorkFrame) -> None:
        """The part of :meth:`_describe` that reads the frame alone (run on the pool's threads):
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

    def _spoil(self, frame: WorkFrame) -> None:
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
        # Only textured frames are polished, and _describe gave those their aligned image (and corners, lk).
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

    @torch.inference_mode()
    def _predict(self, firsts: list[np.ndarray], seconds: list[np.ndarray]):
        """Working-frame homographies (n, M, 3, 3) of every patch for the n pairs (firsts[k], seconds[k])."""
        n, M, P = len(firsts), len(self.positions), self.patch
        # Cut the patches before anything else: only they are converted and sent to the device.
        cut = np.stack([[frame[y : y + P, x : x + P] for x, y in self.positions] for frame in (*firsts, *seconds)])
        crops = torch.from_numpy(cut).to(self.device, non_blocking=True).float() * (2.0 / 255.0) - 1.0  # (2n, M, P, P)
        pairs = torch.stack([crops[:n], crops[n:]], dim=2).flatten(0, 1)  # (n*M, 2, P, P) in [-1, 1]
        if self.device.type == "cpu" and self.precision == "fp32":
            pairs = pairs.contiguous(memory_format=torch.channels_last)
        feats = self._features(pairs).unflatten(0, (n, M)).transpose(0, 1)  # (M, n, F)
        offsets = self._step(feats)  # (M, n, 4, 2)
        return self._homographies(offsets)

    def _homographies(self, offsets: torch.Tensor) -> tuple[torch.Tensor, np.ndarray]:
        """Offsets (M, n, 4, 2) -> working-frame homographies (n, M, 3, 3) and whether each pair's
        offsets were finite (n,)."""
        ok = torch.isfinite(offsets).flatten(2).all(-1).all(0).cpu().numpy()
        offsets = torch.nan_to_num(offsets.double(), nan=0.0, posinf=0.0, neginf=0.0)
        H = offsets_to_homography(offsets, self._positions_t[:, None, :], self.patch)  # (M, n, 3, 3)
        return H.transpose(0, 1), ok

    def _step(self, feats: torch.Tensor) -> torch.Tensor:
        """Regress the chunk's offsets, carrying (and if asked, periodically resetting) the LSTM state."""
        offsets, self._state = self._step_from(feats, self._state, self._pairs_done)
        self._pairs_done += feats.shape[1]
        return offsets

    def _step_from(self, feats: torch.Tensor, state: tuple[torch.Tensor, ...] | None,
                   done: int) -> tuple[torch.Tensor, tuple[torch.Tensor, ...] | None]:
        """The offsets of the pairs ``feats`` (M, n, F) from ``state`` after ``done`` pairs of the
        video, and the state after them: restarted where ``reset-every`` asks."""
        every = self.config.reset_every if self.model.head == "lstm" else None
        if not every:
            return self.model.step(feats, state)
        parts, start = [], 0
        while start < feats.shape[1]:
            if done % every == 0:
                state = None
            size = min(every - done % every, feats.shape[1] - start)
            part = slice(start, start + size)
            offsets, state = self.model.step(feats[:, part], state)
            parts.append(offsets)
            start += size
            done += size
        return torch.cat(parts, dim=1), state

    def _consensus(self, H_patches: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """One homography per pair from M patch estimates: the DLT of the per-corner median of
        where they send the frame corners; agreement = 1 / (1 + (spread / agreement_px)^2), the
        spread being the median over patches of their mean corner distance to the consensus."""
        n, M = H_patches.shape[:2]
        if M == 1:
            return H_patches[:, 0].cpu().numpy(), np.ones(n)
        corners = torch.as_tensor(self._corners, dtype=H_patches.dtype, device=H_patches.device)
        moved = project(H_patches, corners)  # (n, M, 4, 2)
        median = moved.median(dim=1).values  # (n, 4, 2)
        H = four_point_to_homography(corners.expand(n, 4, 2), median - corners)
        spread = (moved - median[:, None]).norm(dim=-1).mean(-1).median(dim=1).values
        agreement = 1.0 / (1.0 + (spread / self.config.agreement_px) ** 2)
        return H.cpu().numpy(), agreement.cpu().numpy()

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

    def _estimate(self, prev, cur):  # pragma: no cover - feed/finish are overridden
        raise NotImplementedError


SPOILT_HISTORY = 15  # frames the detail reference is the median of
SPOILT_HISTORY_MIN = 2  # frames needed before any is called spoilt


def make_learned_estimator(
    name: str, weights: str | Path | None = None, device: str = "auto", config: LearnedConfig | None = None
) -> LearnedEstimator:
    """The estimator for ``--estimator lstm|cnn`` (shipped weights) or ``--weights FILE`` (the
    checkpoint's own preset, head and variant; ``name`` then only has to agree with its head)."""
    name = (name or "").lower()
    if weights is None:
        if name not in LEARNED:
            raise BadInput(f"unknown learned estimator {name!r}: choose lstm or cnn, or pass --weights FILE")
        weights = default_weights(name)
    on = resolve_device(device)  # bad --device fails before loading anything
    model, meta = load_weights(weights, device="cpu")
    if name in LEARNED and name != model.config.head:
        raise BadInput(f"--estimator {name}, but {weights} holds a {model.config.head} network ({meta['variant']})")
    if on.type == "cpu":  # a command's estimator: --threads, or one (training sets its own)
        use_cpu_threads()
    estimator = LearnedEstimator(model, meta, device=device, config=config)
    estimator.warm_up()  # here, in the build: beside the work the command runs meanwhile
    return estimator


__all__ = [
    "PRECISIONS",
    "LearnedConfig",
    "LearnedEstimator",
    "default_weights",
    "make_learned_estimator",
    "patch_positions",
]
