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

Its parts, one concept a module: scheduling the pairs (chunks, threads, look-ahead:
:mod:`.learned_schedule`), running the network (:mod:`.learned_network`), the per-pair checks
(the trust/fallback decision: :mod:`.learned_checks`, batched on the device:
:mod:`.learned_batch_checks`).  Beside it: its options (:mod:`.learned_config`), the correlation
checks (:mod:`.correlation`), where the shipped weights are (:mod:`.weights`) and the polish
(:mod:`.refine`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from mosaic_cli.device import pair_threads, resolve_device, use_cpu_threads
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators.base import PairEstimate
from mosaic_cli.estimators.learned_checks import PATHS, WorkFrame
from mosaic_cli.estimators.learned_config import LEARNED, PRECISIONS, LearnedConfig
from mosaic_cli.estimators.learned_network import patch_positions
from mosaic_cli.estimators.learned_schedule import PairSchedule
from mosaic_cli.estimators.orb import OrbEstimator
from mosaic_cli.estimators.refine import erode_mask
from mosaic_cli.estimators.weights import default_weights
from mosaic_cli.geometry import frame_corners
from mosaic_cli.model.checkpoint import load_weights
from mosaic_cli.model.network import HomographyNet
from mosaic_cli.model.quantize import quantized_features, quantized_head


class LearnedEstimator(PairSchedule):
    """Streaming inference with a trained net; ``feed`` returns estimates a chunk at a time.

    ``threads``: the threads that finish a chunk's pairs (None: ``--threads``, else every core; see
    :func:`mosaic_cli.device.pair_threads`), read at each ``reset``.  What a pair's own frames
    say of it (describing the frames, the polish and its wide retry, the correlation check, the
    fallback's registration: :meth:`_check`) runs on a pool of that many threads, OpenCV's calls
    letting go of the GIL; what follows from the pairs before it (the carried motion, the prior,
    the counts: :meth:`_decide`) runs after, pair by pair, in order.  Every result is
    the same, to the bit, whatever the number; with one, each pair is finished in turn on the
    calling thread, with no pool.

    This class holds the state (set here, in ``__init__`` and ``reset``) and the streaming
    interface; the work is its bases': :class:`.PairSchedule` (chunks, the pool, the look-ahead)
    runs :class:`.NetworkRun` (the network) and :class:`.BatchedPairChecks` /
    :class:`.PairChecks` (each pair's checks and decision)."""

    def __init__(self, model: HomographyNet, meta: dict, device: str = "auto", config: LearnedConfig | None = None,
                 threads: int | None = None):
        self.meta = meta
        self.threads = threads
        self._workers = 1  # the pool's threads for this video (reset)
        self._pool = None
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
        self._prior_warp = self.config.prior == "velocity" and self.config.polish_start == "network"
        # The chunk's LK polish and check batched on the device (polish-with; see _finish_batched).
        on = self.config.polish_with
        self._batched = self.config.refine == "lk" and (on == "torch" or (on == "auto" and self.device.type == "cuda"))
        self._fallback = OrbEstimator(self.work_width) if self.config.fallback == "orb" else None
        self._pending = []
        self._ahead = None  # see _run_ahead
        self._state = None  # the LSTM's (h, c) between chunks
        self._pairs_done = 0
        self._motion = np.eye(3)
        self._detail_levels = []
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
        self._detail_levels = []  # band-passed detail of the recent unspoilt frames (see _judge_spoilt)
        self._confirmed_once = False  # a pair was placed by the frames: there is a motion to carry
        self._carried_run = 0  # pairs carried in a row
        self.path_counts = dict.fromkeys(PATHS, 0)
        self._zncc_use = None  # the usable-pixel image (work size) of _valid_pixels, made at the first pair
        self._batch_masks_t = None  # _batch_masks' tensors, made at the first batched chunk
        self._workers = self.threads if self.threads is not None else pair_threads()
        if self._workers < 1:
            raise ValueError(f"threads must be at least 1, got {self._workers}")
        if self._fallback is not None:
            self._fallback.set_mask(self.mask)  # the fallback's ORB keypoints and polish skip overlays too
            self._fallback.reset(full_size)

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

    def _estimate(self, prev, cur):  # pragma: no cover - feed/finish are overridden
        raise NotImplementedError


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
