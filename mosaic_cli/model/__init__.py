"""The paper's learned homography estimator, model side: network (:mod:`.network`), patches
and their warps (:mod:`.patches`; the tensor DLT is :mod:`mosaic_cli.geometry.tensor`), checkpoint format (:mod:`.checkpoint`) and int8 CPU inference
(:mod:`.quantize`).  Training (loss terms, per-variant objective) lives in :mod:`mosaic_cli.train`.
Every homography maps frame t -> frame t+1."""

from mosaic_cli.model.checkpoint import load_weights, read_metadata, save_weights
from mosaic_cli.model.network import HEADS, PRESETS, VARIANTS, HomographyNet, NetConfig, count_parameters, macs_per_pair

__all__ = [
    "HEADS",
    "PRESETS",
    "HomographyNet",
    "NetConfig",
    "count_parameters",
    "macs_per_pair",
    "VARIANTS",
    "save_weights",
    "load_weights",
    "read_metadata",
]
