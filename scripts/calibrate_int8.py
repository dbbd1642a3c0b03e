"""Add int8 activation ranges to a trained checkpoint (``mosaic train`` writes them into its
final weights; this is for weights taken from a checkpoint, or trained before it did).

    python scripts/calibrate_int8.py WEIGHTS CLIPS [--pairs 512] [--seed 0]
    python scripts/calibrate_int8.py WEIGHTS --head-only

The ranges are measured on patch pairs cut from CLIPS (the training clips) at the checkpoint's
working size, and written back into WEIGHTS' metadata (atomically; the weights are unchanged),
with the int8 LSTM's error on this machine's int8 engine (quantize.with_head_error), which spares
loading the probe.  ``--head-only``: that error alone, added to the ranges WEIGHTS already has.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from mosaic_cli.model import quantize
from mosaic_cli.model.checkpoint import load_weights, save_weights
from mosaic_cli.train.data import WindowDataset, build_frame_cache, discover_clips, sample_pairs

FRAMES_PER_CLIP = 64  # decoded per clip (spread over it): plenty for 512 pairs, quick to decode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("weights", type=Path)
    parser.add_argument("clips", type=Path, nargs="?")
    parser.add_argument("--head-only", action="store_true", help="only measure the int8 LSTM's error; keep the ranges")
    parser.add_argument("--pairs", type=int, default=512)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    model, meta = load_weights(args.weights)
    work_size = tuple(meta["work_size"])
    if args.head_only:
        if not meta.get("int8"):
            parser.error(f"{args.weights} has no int8 ranges: calibrate it with CLIPS first")
        ranges = quantize.with_head_error(model, meta["int8"])
        save_weights(args.weights, model, meta["config"], meta["variant"], extra=meta["extra"], work_size=work_size, int8=ranges)
        print(f"{args.weights}: int8 LSTM error {ranges.get('head_error')} px (tolerance {quantize.HEAD_TOLERANCE_PX})")
        return
    if args.clips is None:
        parser.error("CLIPS is needed unless --head-only")
    with tempfile.TemporaryDirectory() as cache:
        found = discover_clips(args.clips)
        budget = FRAMES_PER_CLIP * len(found) * work_size[0] * work_size[1]
        clips = build_frame_cache(found, Path(cache), work_size, 2, budget)
        windows = WindowDataset(clips, 2, 1, model.config.patch, args.seed)
        ranges = quantize.calibrate(model, sample_pairs(windows, args.pairs, seed=args.seed))
    save_weights(args.weights, model, meta["config"], meta["variant"], extra=meta["extra"], work_size=work_size, int8=ranges)
    print(f"{args.weights}: int8 ranges of {len(ranges['activations'])} activations from {args.pairs} pairs of {args.clips}")


if __name__ == "__main__":
    main()
