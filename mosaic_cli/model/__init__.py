"""The paper's learned homography estimator, model side: network (:mod:`.network`), tensor DLT
and warps (:mod:`.dlt`), loss terms (:mod:`.losses`), per-variant objective (:mod:`.objective`),
checkpoint format (:mod:`.checkpoint`) and int8 CPU inference (:mod:`.quantize`).  Every homography maps frame t -> frame t+1."""

from mosaic_cli.model.checkpoint import load_weights, read_metadata, save_weights
from mosaic_cli.model.network import HEADS, PRESETS, HomographyNet, NetConfig, count_parameters, macs_per_pair
from mosaic_cli.model.objective import TERMS, VARIANTS, LossWeights, Objective

__all__ = [
    "HEADS",
    "PRESETS",
    "HomographyNet",
    "NetConfig",
    "count_parameters",
    "macs_per_pair",
    "TERMS",
    "VARIANTS",
    "LossWeights",
    "Objective",
    "save_weights",
    "load_weights",
    "read_metadata",
]
