"""Homography estimators behind one streaming interface (see :mod:`.base`)."""

from __future__ import annotations

from mosaic_cli.errors import BadInput
from mosaic_cli.estimators.base import Estimator, IdentityEstimator, PairEstimate, estimate_stream  # noqa: F401
from mosaic_cli.estimators.orb import OrbConfig, OrbEstimator

CLASSICAL = ("orb", "identity")


def make_estimator(name: str, work_width: int = 320, weights: str | None = None, device: str = "auto") -> Estimator:
    """Build the estimator a user named on the command line."""
    name = name.lower()
    if work_width < 32:
        raise BadInput(f"--work-width must be at least 32, got {work_width}")
    if weights is not None or name in ("lstm", "cnn"):
        from mosaic_cli.estimators.learned import make_learned_estimator

        return make_learned_estimator(name, weights=weights, device=device)
    if name == "orb":
        return OrbEstimator(work_width)
    if name == "orb-ransac":
        return OrbEstimator(work_width, OrbConfig(method="ransac"))
    if name == "identity":
        return IdentityEstimator(work_width)
    raise BadInput(f"unknown estimator {name!r}: choose one of orb, orb-ransac, identity, lstm, cnn")
