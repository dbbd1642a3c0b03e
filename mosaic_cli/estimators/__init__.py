"""Homography estimators behind one streaming interface (see :mod:`.base`).

An estimator is named on the command line as ``NAME[:OPTION=VALUE]...``, e.g. ``orb``,
``cnn:patches=5:refine=none`` or ``lstm:reset-every=300``; :func:`make_estimator` builds it.
"""

from __future__ import annotations

import re
from pathlib import Path

from mosaic_cli.errors import BadInput
from mosaic_cli.estimators.base import Estimator, IdentityEstimator, PairEstimate, estimate_stream  # noqa: F401
from mosaic_cli.estimators.orb import OrbConfig, OrbEstimator
from mosaic_cli.estimators.paper_orb import PaperOrbEstimator

CLASSICAL = ("orb", "orb-ransac", "orb-paper", "identity")
LEARNED = ("lstm", "cnn")  # the learned estimators: the network heads (model.network.HEADS) by name
NAMES = (*CLASSICAL, *LEARNED)
MIN_WORK_WIDTH, MAX_WORK_WIDTH = 32, 4096  # estimators work on frames this wide (px)
# What track, stitch and stabilize use unless told otherwise (models/README.md has the measurements).
DEFAULT_ESTIMATOR = "lstm"

# The options each estimator takes (in a name or as command-line flags) and how to read them.
OPTIONS: dict[str, dict[str, type]] = {
    "lstm": {"patches": int, "chunk": int, "reset_every": int, "refine": str, "precision": str, "weights": Path,
             "seed": str, "prior": str, "fallback": str, "retry": str, "carry": str},
    "cnn": {"patches": int, "chunk": int, "refine": str, "precision": str, "weights": Path,
            "seed": str, "prior": str, "fallback": str, "retry": str, "carry": str},
    "orb": {"refine": str},
    "orb-ransac": {"refine": str},
}


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


def _typed(name: str, options: dict) -> dict:
    allowed = OPTIONS.get(name, {})
    out = {}
    for key, value in options.items():
        if value is None:
            continue
        key = key.replace("-", "_")
        if key not in allowed:
            offer = ", ".join(k.replace("_", "-") for k in allowed) or "none"
            raise BadInput(f"estimator {name!r} has no option {key.replace('_', '-')!r} (its options: {offer})")
        kind = allowed[key]
        if kind is int:
            try:
                value = int(value)
            except (TypeError, ValueError):
                raise BadInput(f"estimator {name!r}: {key.replace('_', '-')} must be a whole number, got {value!r}") from None
        elif kind is Path:
            value = str(value)  # a file name keeps its case
        else:
            value = str(value).lower()
            if key == "refine" and value == "none":
                value = None
        out[key] = value
    return out


def check_work_width(width: int) -> None:
    """``--work-width``: one rule for track, stitch, stabilize and bench."""
    if not MIN_WORK_WIDTH <= width <= MAX_WORK_WIDTH:
        raise BadInput(f"--work-width must be in {MIN_WORK_WIDTH}..{MAX_WORK_WIDTH}, got {width}")


def check_device(device: str | None) -> None:
    """``--device``: auto, cpu, cuda or cuda:N (whether that GPU exists is found when a learned
    estimator moves its network there)."""
    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", (device or "auto").lower()):
        raise BadInput(f"--device must be auto, cpu or cuda, got {device!r}")


def make_estimator(name: str | None = None, work_width: int = 320, weights: str | None = None, device: str = "auto",
                   **options) -> Estimator:
    """Build the estimator a user named on the command line.

    ``name`` (None: :data:`DEFAULT_ESTIMATOR`) may carry options (``cnn:patches=5``, ``lstm:weights=run/weights.safetensors``);
    keyword ``options`` (from flags, None = not given) add to them.  ``weights`` goes with a
    learned name or none (the checkpoint's head then decides lstm or cnn); with a classical name
    it is an error.  A ``weights`` option in the name wins over it, so that one benchmark can
    compare several checkpoints."""
    if name is None:  # not named: the default, or with ``weights`` whichever network they hold
        name = "" if weights is not None else DEFAULT_ESTIMATOR
    base, spec_options = parse_spec(name)
    check_work_width(work_width)
    check_device(device)
    if weights is not None and base not in (*LEARNED, ""):
        if base in NAMES:  # running the network instead of what was named would be a silent surprise
            raise BadInput(f"--weights goes with a learned estimator (lstm or cnn) or none; -e {base} takes no weights")
        raise BadInput(f"unknown estimator {base!r}: choose one of {', '.join(NAMES)}")
    learned = weights is not None or base in LEARNED
    kind = "lstm" if learned and base not in LEARNED else base  # --weights alone: the options any learned one takes
    given = {**spec_options, **{k: v for k, v in options.items() if v is not None}}
    typed = _typed(kind, given) if base in NAMES or learned else {}
    if learned:
        from mosaic_cli.estimators.learned import LearnedConfig, make_learned_estimator

        weights = typed.pop("weights", weights)
        return make_learned_estimator(base, weights=weights, device=device, config=LearnedConfig(**typed))
    if base in ("orb", "orb-ransac"):
        return OrbEstimator(work_width, OrbConfig(method="ransac" if base == "orb-ransac" else "usac", **typed))
    if base == "orb-paper":
        return PaperOrbEstimator(work_width)
    if base == "identity":
        return IdentityEstimator(work_width)
    raise BadInput(f"unknown estimator {base!r}: choose one of {', '.join(NAMES)}")


__all__ = [
    "CLASSICAL",
    "DEFAULT_ESTIMATOR",
    "LEARNED",
    "NAMES",
    "check_device",
    "check_work_width",
    "Estimator",
    "IdentityEstimator",
    "OrbConfig",
    "OrbEstimator",
    "PairEstimate",
    "PaperOrbEstimator",
    "estimate_stream",
    "make_estimator",
    "parse_spec",
]
