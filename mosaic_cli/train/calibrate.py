"""``mosaic train CLIPS --calibrate WEIGHTS``: int8 activation ranges added to existing weights
instead of training.  ``mosaic train`` writes the ranges into its final weights; this is for
weights taken from a checkpoint, or trained before it did.

The ranges are measured as the end of a training run measures them (:func:`.loop.calibrate_int8`:
patch pairs of the training clips at the weights' working size) and written back into the
weights' metadata, atomically; the weights themselves are unchanged.  With them goes the int8
LSTM's error on this machine's int8 engine (:func:`mosaic_cli.model.quantize.with_head_error`),
which spares the estimator probing it when it loads.  ``head_only``: that error alone, added to
the ranges the weights already have (no clips needed).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from mosaic_cli.errors import BadInput
from mosaic_cli.model import quantize
from mosaic_cli.model.checkpoint import load_weights, save_weights
from mosaic_cli.train.data import WindowDataset, build_frame_cache, discover_clips
from mosaic_cli.train.loop import calibrate_int8

FRAMES_PER_CLIP = 64  # decoded per clip (spread over it): plenty for the calibration's pairs, quick to decode


def calibrate_weights(weights: Path, clips: Path | None, seed: int = 0, head_only: bool = False) -> dict:
    """Measure int8 ranges for ``weights`` on ``clips`` (or, ``head_only``, only the int8 LSTM's
    error, added to the ranges it has) and write them into ``weights``; the ranges written."""
    if quantize.engine() is None:
        raise BadInput("--calibrate: this PyTorch build has no int8 engine, so int8 ranges cannot be measured here")
    model, meta = load_weights(weights)
    work_size = tuple(meta["work_size"])
    if head_only:
        if not meta.get("int8"):
            raise BadInput(f"{weights} has no int8 ranges: calibrate it with CLIPS first (--head-only keeps the ranges it has)")
        ranges = quantize.with_head_error(model, meta["int8"])
    else:
        if clips is None:
            raise BadInput("--calibrate needs CLIPS, the clips to measure the ranges on (or --head-only)")
        found = discover_clips(clips)
        with tempfile.TemporaryDirectory(prefix="mosaic-calibrate-") as cache:
            budget = FRAMES_PER_CLIP * len(found) * work_size[0] * work_size[1]
            cached = build_frame_cache(found, Path(cache), (work_size[0], work_size[1]), 2, budget)
            windows = WindowDataset(cached, 2, 1, model.config.patch, seed)
            ranges = calibrate_int8(model, windows, seed)
    assert ranges is not None  # the engine was checked above
    save_weights(weights, model, meta["config"], meta["variant"], extra=meta["extra"], work_size=(work_size[0], work_size[1]), int8=ranges)
    return ranges
