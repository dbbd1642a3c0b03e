"""``--rolling-shutter auto``'s probe: does it tell rolling from global shutters, and what does it cost?

* ``separation CLIP...``: the bands of each clip's first 60 frames, then the readout and the
  cost of readout 0 against the best (``estimate_readout``; a global shutter under
  ``GLOBAL_COST_RATIO``) from the first 60, 30 and 20 of them;
* ``overhead --out DIR``: global-shutter clips of 120, 600 and 1200 frames at 1280x720
  (simulated once), ``stabilize`` with ``--rolling-shutter off`` and ``auto`` in A-B-B-A order:
  the probe's stage seconds against ``off``'s total (say whether the machine was shared).

    python scripts/bench_rolling_probe.py separation /tmp/rs/*.mp4
    python scripts/bench_rolling_probe.py overhead --out /tmp/rsprobe [--frames 120 600 1200]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from mosaic_cli.estimators.rolling import AUTO_PROBE_FRAMES, measure_band_motion
from mosaic_cli.geometry.rolling_shutter import estimate_readout
from mosaic_cli.simulate import SimulateOptions, simulate_flight
from mosaic_cli.stabilize import StabilizeOptions, stabilize
from mosaic_cli.video import probe


def separation(clips: list[Path]) -> None:
    for clip in clips:
        info = probe(clip)
        motion, weights = measure_band_motion(clip, info, show_progress=False, max_frames=60)
        cells = []
        for frames in (60, 30, 20):
            readout, costs = estimate_readout(motion[:frames - 1], info.source_size[1], weights[:frames - 1])
            cells.append(f"{frames}: {readout:.2f} (x{costs[0] / costs.min():.1f} at 0)")
        print(f"{clip.name:<40} " + " | ".join(cells), flush=True)


def overhead(out: Path, lengths: list[int]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    print(f"probe: {AUTO_PROBE_FRAMES} frames")
    for frames in lengths:
        clip = out / f"gs_paper_{frames}.mp4"
        if not clip.exists():
            simulate_flight(clip, None, SimulateOptions(profile="paper", frames=frames, size=(1280, 720), seed=4), show_progress=False)
        runs = []
        for mode in ("off", "auto", "auto", "off"):
            result = stabilize(clip, clip.with_suffix(f".{mode}.mp4"), StabilizeOptions(rolling_shutter=mode), show_progress=False)
            runs.append((mode, result.seconds.get("rolling", 0.0), result.seconds["total"], os.getloadavg()[0]))
        probe_s = [r[1] for r in runs if r[0] == "auto"]
        off_s = [r[2] for r in runs if r[0] == "off"]
        auto_s = [r[2] for r in runs if r[0] == "auto"]
        share = [p / o for p, o in zip(probe_s, off_s)]
        print(f"{frames:>5} frames: probe {probe_s[0]:.2f}, {probe_s[1]:.2f} s; off total {off_s[0]:.1f}, {off_s[1]:.1f} s; "
              f"auto total {auto_s[0]:.1f}, {auto_s[1]:.1f} s; probe / off +{100 * min(share):.0f}-{100 * max(share):.0f}%; "
              f"load {min(r[3] for r in runs):.1f}-{max(r[3] for r in runs):.1f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sep = sub.add_parser("separation")
    sep.add_argument("clips", type=Path, nargs="+")
    ov = sub.add_parser("overhead")
    ov.add_argument("--out", type=Path, required=True)
    ov.add_argument("--frames", type=int, nargs="+", default=[120, 600, 1200])
    args = parser.parse_args()
    if args.command == "separation":
        separation(args.clips)
    else:
        overhead(args.out, args.frames)


if __name__ == "__main__":
    main()
