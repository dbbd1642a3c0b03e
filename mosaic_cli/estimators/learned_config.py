"""The learned estimator's options (``-e lstm:OPTION=VALUE``, the flags that set them) and the
internal knobs beside them, with their defaults and checks: what :class:`.learned.LearnedEstimator`
is told to do, apart from how it does it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, get_args

from mosaic_cli.errors import BadInput
from mosaic_cli.estimators.options import check_choices, option
from mosaic_cli.estimators.refine import CornerConfig, PolishConfig, Polisher

LEARNED = ("lstm", "cnn")  # the learned estimators: the network heads (model.network.HEADS) by name

# The values of the options that take one of a few: the annotations of LearnedConfig's fields,
# which the command line reads its choices from (mosaic_cli.estimators.options).
PatchLayout = Literal[1, 5, 9]
Precision = Literal["auto", "int8", "fp32"]
Retry = Literal["wide", "none"]
PolishStart = Literal["network", "identity", "velocity"]
Prior = Literal["velocity", "none"]
Fallback = Literal["orb", "none"]
Carry = Literal["network", "velocity", "none"]
PolishWith = Literal["auto", "opencv", "torch"]
PATCH_LAYOUTS: tuple[PatchLayout, ...] = get_args(PatchLayout)
PRECISIONS: tuple[Precision, ...] = get_args(Precision)


@dataclass
class LearnedConfig:
    """The learned estimator's options (``-e lstm:OPTION=VALUE``: the fields declared with
    ``option``) and internal knobs.  The measurements behind each default are in
    models/README.md ("Why these defaults")."""

    patches: PatchLayout = option(1)  # 1: the centre patch (paper); 5: centre + 4 corners; 9: a 3x3 grid
    chunk: int = option(16)  # frame pairs per backbone batch (larger on a GPU)
    reset_every: int | None = option(None, only=("lstm",))  # LSTM: restart from a zero state every K pairs (None: never)
    # The network's arithmetic: "auto" is int8 on a CPU when the weights carry calibrated ranges
    # (the convolutions and the LSTM's weights; offsets stay within hundredths of a working px of
    # fp32's), fp32 otherwise and on GPUs.
    precision: Precision = option("auto")
    agreement_px: float = 2.0  # corner spread between patches (working px) at which confidence halves
    max_area_ratio: float = 2.0  # larger frame-to-frame area changes are failures
    refine: Polisher | None = option("lk")  # "lk", "ecc" or None: the polish seeded by the network (see refine.py)
    # The network's estimate is usually within a working px or two, but on fast, degraded flights
    # over ground unlike its training sites it can be 5-15 px off: a cheap polish first (1 pyramid
    # level), and where it fails a deep pyramid with large windows and a long leash, which finds
    # the basin on blurred, noisy frames; its result then seeds the cheap polish again, whose
    # small windows and tight refit place it precisely.
    polish: PolishConfig = field(default_factory=lambda: PolishConfig(window=11, levels=1, max_shift=3.0))
    polish_wide: PolishConfig | None = field(
        default_factory=lambda: PolishConfig(window=31, levels=4, max_shift=20.0, threshold=1.5))
    # Where a chunk's pairs are polished and checked: "opencv" one pair at a time on the pool of
    # threads; "torch" the whole chunk at once on the estimator's device (the LK polish, its
    # refit and the correlation check: mosaic_cli.estimators.batched), the pairs it does not
    # settle (no refit, too few inliers, a divergence, detail that does not correlate) then
    # finished by OpenCV as with "opencv"; "auto": torch on a GPU, OpenCV on a CPU.  Only the
    # LK polish (refine=lk) is batched, and not with polish-start=velocity (each pair starts the next).
    polish_with: PolishWith = option("auto", ablation=True)
    retry: Retry = option("wide", ablation=True)  # "none": no wide polish where the cheap one fails (what the seed alone reaches)
    # The polish aligns band-passed frames (difference of Gaussians of these sigmas, working px):
    # the finest detail of an encoded video moves with the codec's quantised motion vectors, and
    # exposure drifts from frame to frame; both bias LK tracks in ways that add up along a chain.
    # None: plain frames.
    polish_band: tuple[float, float] | None = (1.5, 6.0)
    # ...but only for video at least this many times wider than the working frame: frames that
    # already are at the working size keep their finest detail, which is then real.
    polish_band_min_downscale: float = 2.0
    corners: CornerConfig = field(default_factory=lambda: CornerConfig(max_points=200))
    unpolished_weight: float = 0.5  # confidence factor of an estimate the polish could not confirm
    # Registered detail that correlates less than this is unrelated ground (a cut, a swapped
    # camera): the pair is reported as failed (identity, confidence 0), as ORB does, so that
    # stitch and stabilize treat it as one.  Registered noisy frames score far above it, a cut
    # to unrelated ground far below.
    min_zncc: float | None = 0.1  # None: never
    # What the polish starts from: "network" (the product), or for the ablations the identity or
    # the previous pair's motion (constant velocity), with everything else unchanged.  (Named
    # ``seed`` until issue 50: every command's --seed is a random seed.)
    polish_start: PolishStart = option("network", ablation=True)
    # A motion prior: "velocity" pre-aligns frame t+1 by the last confirmed motion (as the chunk
    # starts) before the network reads it, so that the network regresses only what changed;
    # "none" reads the raw pair, as the paper does.  A network trained on fast flights needs no
    # prior, and a prior a chunk old misleads it (models/README.md): "none" by default.
    prior: Prior = option("none", ablation=True)
    # When the learned path cannot confirm a pair (the polish fails or its detail does not
    # correlate), the classical estimator (ORB + its own polish) tries that pair: "orb" or "none".
    fallback: Fallback = option("orb", ablation=True)
    # A pair that no path confirms, one of whose frames is spoilt (glare, a gust's blur, near
    # black, featureless: its band-passed detail below ``spoilt_ratio`` of the flight's recent
    # frames), is placed by the motion carried across the frames rather than reported failed:
    # "network" (the network's estimate for the pair: for the LSTM, what its state carried over
    # from the frames before makes of it), "velocity" (the last confirmed motion), "none"
    # (failed).  Its confidence is ``carry_confidence``: placed, but confirmed by nothing.  A cut
    # to unrelated ground keeps its detail, so it stays a failure.
    carry: Carry = option("velocity", ablation=True)
    carry_confidence: float = 0.05
    # ...for at most this many pairs in a row, and only once a pair was confirmed: a video that
    # goes dark for seconds, or starts dark, has no motion that can honestly be carried so far.
    carry_limit: int = option(8, ablation=True)
    spoilt_ratio: float = option(0.8, ablation=True)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """The options a user sets (``--patches``, ``-e lstm:reset-every=K`` ...), named as written."""
        if self.chunk < 1:
            raise BadInput(f"chunk must be at least 1 frame pair, got {self.chunk}")
        check_choices(self)  # patches, refine, precision, retry, polish-start, prior, fallback, carry
        if self.reset_every is not None and self.reset_every < 1:
            raise BadInput(f"reset-every must be at least 1 frame pair, got {self.reset_every}")
        if self.carry_limit < 1:
            raise BadInput(f"carry-limit must be at least 1 pair, got {self.carry_limit}")
        if not 0 < self.carry_confidence < 1:
            raise BadInput(f"carry-confidence must be in (0, 1), got {self.carry_confidence}")
        if not 0 <= self.spoilt_ratio < 1:
            raise BadInput(f"spoilt-ratio must be in [0, 1), got {self.spoilt_ratio}")
