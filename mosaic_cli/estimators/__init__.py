"""Homography estimators behind one streaming interface (see :mod:`.base`).

An estimator is named on the command line as ``NAME[:OPTION=VALUE]...``, e.g. ``orb``,
``cnn:patches=5:refine=none`` or ``lstm:reset-every=300``; :func:`make_estimator` builds it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from mosaic_cli.device import check_device
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators.base import Estimator, IdentityEstimator, PairEstimate, estimate_stream  # noqa: F401
from mosaic_cli.estimators.learned_config import LEARNED, LearnedConfig
from mosaic_cli.estimators.options import Option, options_of
from mosaic_cli.estimators.orb import OrbConfig, OrbEstimator
from mosaic_cli.estimators.paper_orb import PaperOrbEstimator
from mosaic_cli.estimators.weights import default_weights
from mosaic_cli.inputs import check_weights_file

CLASSICAL = ("orb", "orb-ransac", "orb-paper", "identity")
NAMES = (*CLASSICAL, *LEARNED)
MIN_WORK_WIDTH, MAX_WORK_WIDTH = 32, 4096  # estimators work on frames this wide (px)
# The classical estimators' width unless --work-width says otherwise: track and stitch (stitch
# places its keyframes by direct registration at the features' width; the estimator only
# follows the ground between them).  stabilize uses its own (stabilize.pipeline.WORK_WIDTH).
DEFAULT_WORK_WIDTH = 320
# What track, stitch and stabilize use unless told otherwise (models/README.md has the measurements).
DEFAULT_ESTIMATOR = "lstm"

# The options each estimator takes (in a name or as command-line flags), by field name: the
# option fields of its config, and for a network the checkpoint it runs (not a config field:
# it decides which network there is to configure).
OPTIONS: dict[str, dict[str, Option]] = {
    **{name: {**options_of(LearnedConfig, name), "weights": Option("weights", Path)} for name in LEARNED},
    **{name: options_of(OrbConfig, name) for name in ("orb", "orb-ransac")},
}


def options_help() -> str:
    """The estimators' options as a sentence for ``--help``: ``Options of lstm and cnn (defaults
    in brackets): patches=1|5|9 (1), ..., reset-every=N (lstm only), ...; of orb and orb-ransac:
    refine=lk|ecc|none (lk).``"""
    orbs = ("orb", "orb-ransac")
    return (f"Options of {' and '.join(LEARNED)} (defaults in brackets): {_options_of_all(LEARNED)}; "
            f"of {' and '.join(orbs)}: {_options_of_all(orbs)}.")


def _options_of_all(family: tuple[str, ...]) -> str:
    """The options of estimators that take (nearly) the same, each once, with those only some take marked."""
    described = []
    for key in dict.fromkeys(key for estimator in family for key in OPTIONS[estimator] if not OPTIONS[estimator][key].ablation):
        takers = [estimator for estimator in family if key in OPTIONS[estimator]]
        usage = OPTIONS[takers[0]][key].usage()
        described.append(usage if len(takers) == len(family) else f"{usage} ({' and '.join(takers)} only)")
    return ", ".join(described)


def parse_spec(spec: str) -> tuple[str, dict[str, str]]:
    """``"cnn:patches=5:refine=none"`` -> ``("cnn", {"patches": "5", "refine": "none"})``."""
    name, *parts = [p.strip() for p in spec.strip().split(":")]
    options = {}
    for part in parts:
        key, sep, value = part.partition("=")
        key = key.strip().lower().replace("-", "_")
        if not sep or not key or not value.strip():
            raise BadInput(f"estimator {spec!r}: options are written NAME:OPTION=VALUE, got {part!r}")
        if key in options:
            raise BadInput(f"estimator {spec!r}: option {key!r} given twice")
        options[key] = value.strip()
    return name.lower(), options


RENAMED = {"seed": "polish_start"}  # an option's old name -> its new one (refused, naming the new one)


def typed_options(name: str, options: dict) -> dict:
    """The options given to the estimator ``name`` (from its spec and flags, None: not given),
    read as its config takes them, by field name; ``BadInput`` for one it does not take (listing
    those it does) or a value not of the option's kind."""
    allowed = OPTIONS.get(name, {})
    out = {}
    for key, value in options.items():
        if value is None:
            continue
        key = key.replace("-", "_")
        if key in RENAMED and key not in allowed:
            new = RENAMED[key]
            raise BadInput(f"-e {name}:{key.replace('_', '-')} is now -e {name}:{new.replace('_', '-')} "
                           f"({key.replace('_', '-')} named a random seed elsewhere)")
        if key not in allowed:
            offer = ", ".join(opt.usage() for opt in allowed.values()) or "none"
            raise BadInput(f"estimator {name!r} has no option {key.replace('_', '-')!r} (its options: {offer})")
        out[key] = allowed[key].read(name, value)
    return out


def check_work_width(width: int) -> None:
    """``--work-width``: one rule for track, stitch, stabilize and bench."""
    if not MIN_WORK_WIDTH <= width <= MAX_WORK_WIDTH:
        raise BadInput(f"--work-width must be in {MIN_WORK_WIDTH}..{MAX_WORK_WIDTH}, got {width}")


def plan_estimator(name: str | None = None, work_width: int | None = None, weights: str | None = None, device: str = "auto",
                   default_width: int = DEFAULT_WORK_WIDTH, **options) -> Callable[[], Estimator]:
    """Check the estimator a user named on the command line, and return the function that builds
    it: every mistake is found here, before any work, while the build (for a network: torch's
    import, the weights, the int8 network, a second or two) can run beside other work.

    ``name`` (None: :data:`DEFAULT_ESTIMATOR`) may carry options (``cnn:patches=5``, ``lstm:weights=run/weights.safetensors``);
    keyword ``options`` (from flags, None = not given) add to them.  ``weights`` goes with a
    learned name or none (the checkpoint's head then decides lstm or cnn); with a classical name
    it is an error.  A ``weights`` option in the name wins over it, so that one benchmark can
    compare several checkpoints.

    ``work_width`` is the user's ``--work-width`` (None: not given).  A classical estimator
    works at it (else at ``default_width``), never wider than the video; a learned one works
    at the width its weights were trained at, and a different width given is refused: the
    network cannot read another size, and ignoring the flag would be a silent surprise."""
    if name is None:  # not named: the default, or with ``weights`` whichever network they hold
        name = "" if weights is not None else DEFAULT_ESTIMATOR
    base, spec_options = parse_spec(name)
    if work_width is not None:
        check_work_width(work_width)
    check_device(device)  # whether that GPU is there is found when a learned estimator moves its network there
    if weights is not None and base not in (*LEARNED, ""):
        if base in NAMES:  # running the network instead of what was named would be a silent surprise
            raise BadInput(f"--weights goes with a learned estimator (lstm or cnn) or none; -e {base} takes no weights")
        raise BadInput(f"unknown estimator {base!r}: choose one of {', '.join(NAMES)}")
    learned = weights is not None or base in LEARNED
    kind = "lstm" if learned and base not in LEARNED else base  # --weights alone: the options any learned one takes
    given = {**spec_options, **{k: v for k, v in options.items() if v is not None}}
    typed = typed_options(kind, given) if base in NAMES or learned else {}
    if learned:
        weights = typed.pop("weights", weights)
        if work_width is not None:  # before the weights are loaded: their header says their width
            _check_learned_width(base or "the network", work_width, weights)
        if weights is None:  # (then the name is lstm or cnn: see ``learned``)
            default_weights(base)  # shipped: found, or the one line that says they are not
        else:
            check_weights_file(weights)
        config = LearnedConfig(**typed)

        def build() -> Estimator:
            from mosaic_cli.estimators.learned import make_learned_estimator  # torch: imported by the build

            return make_learned_estimator(base, weights=weights, device=device, config=config)

        return build
    if base not in CLASSICAL:
        raise BadInput(f"unknown estimator {base!r}: choose one of {', '.join(NAMES)}")
    width = default_width if work_width is None else work_width
    estimator: Estimator
    if base in ("orb", "orb-ransac"):
        estimator = OrbEstimator(width, OrbConfig(method="ransac" if base == "orb-ransac" else "usac", **typed))
    elif base == "orb-paper":
        estimator = PaperOrbEstimator(width)
    else:
        estimator = IdentityEstimator(width)
    estimator.never_upscale, estimator.width_given = True, work_width is not None
    return lambda: estimator


def make_estimator(name: str | None = None, work_width: int | None = None, weights: str | None = None, device: str = "auto",
                   default_width: int = DEFAULT_WORK_WIDTH, **options) -> Estimator:
    """The estimator a user named on the command line, built (:func:`plan_estimator`)."""
    return plan_estimator(name, work_width, weights, device, default_width, **options)()


def _check_learned_width(name: str, work_width: int, weights: str | Path | None) -> None:
    """``--work-width`` with a learned estimator: only the width its weights were trained at."""
    from mosaic_cli.estimators.weights import default_weights
    from mosaic_cli.model.checkpoint import read_metadata

    trained = int(read_metadata(weights if weights is not None else default_weights(name))["work_size"][0])
    if work_width != trained:
        raise BadInput(f"--work-width {work_width}: the {name} network works at {trained} px, the width its weights were "
                       f"trained at; leave --work-width out (it sets the width of {', '.join(CLASSICAL)})")


__all__ = [
    "CLASSICAL",
    "DEFAULT_ESTIMATOR",
    "DEFAULT_WORK_WIDTH",
    "LEARNED",
    "NAMES",
    "OPTIONS",
    "check_work_width",
    "Estimator",
    "IdentityEstimator",
    "OrbConfig",
    "OrbEstimator",
    "PairEstimate",
    "PaperOrbEstimator",
    "estimate_stream",
    "make_estimator",
    "plan_estimator",
    "options_help",
    "parse_spec",
    "typed_options",
]
