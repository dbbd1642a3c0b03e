"""``--rolling-shutter auto``'s probe: does it tell rolling from global shutters, and what does it cost?

* ``separation CLIP... [--width 320]``: `auto`'s probe on each clip's first frames as the
  tracking pass decodes them, then the readout and the cost of readout 0 against the best
  (``estimate_readout``; a global shutter under ``GLOBAL_COST_RATIO``), and its CPU time;
* ``overhead --out DIR``: global-shutter clips of 120, 600 and 1200 frames at 1280x720
  (simulated once), ``stabilize`` with ``--rolling-shutter off`` and ``auto`` in A-B-B-A order:
  the probe's stage seconds against ``off``'s total (say whether the machine was shared).

    python scripts/bench_rolling_probe.py separation /tmp/rs/*.mp4 [--width 320]
    python scripts/bench_rolling_probe.py overhead --out /tmp/rsprobe [--frames 120 600 1200]
"""

from __future__ import annotations

import argparse
import itertools
import os
import time
from pathlib import Path

from mosaic_cli.estimators.rolling import AUTO_PROBE_FRAMES, PROBE_CORNERS, PROBE_READOUTS, RollingProbe
from mosaic_cli.geometry.rolling_shutter import estimate_readout
from mosaic_cli.simulate import SimulateOptions, simulate_flight
from mosaic_cli.stabilize import StabilizeOptions, stabilize
from mosaic_cli.video import open_video, probe

PROBE_WIDTH = 320  # the default estimator's (lstm) frames, which the probe rides on


def separation(clips: list[Path], width: int = PROBE_WIDTH) -> None:
    """`auto`'s probe as stabilize, stitch and track run it (:class:`RollingProbe` on the first
    ``AUTO_PROBE_FRAMES`` frames, decoded ``width`` wide and gray: the default estimator's
    tracking pass), its readout and the cost of readout 0 against the best over ``PROBE_READOUTS``;
    CPU seconds of its tracking and of the readouts."""
    print(f"probe: {AUTO_PROBE_FRAMES} frames at {width} px, {PROBE_CORNERS} corners, readouts {PROBE_READOUTS}")
    for clip in clips:
        info = probe(clip)
        rolling_probe = RollingProbe(info)
        cpu = 0.0
        with open_video(clip, width=width, gray=True, info=info) as frames:
            for frame in itertools.islice(frames, AUTO_PROBE_FRAMES):
                clock = time.process_time()
                rolling_probe.push(frame)
                cpu += time.process_time() - clock
        rolling_probe.finish()
        motion, weights = rolling_probe.measured()
        clock = time.process_time()
        readout, costs = estimate_readout(motion, info.source_size[1], weights, PROBE_READOUTS)
        fit = time.process_time() - clock
        print(f"{clip.name:<40} readout {readout:.2f} (x{costs[0] / costs.min():.1f} at 0); CPU: tracking "
              f"{1000 * cpu / max(len(motion), 1):.1f} ms a pair, readouts {1000 * fit:.0f} ms", flush=True)


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
    sep.add_argument("--width", type=int, default=PROBE_WIDTH, help="frames decoded this wide (the estimator's; default: lstm's 320)")
    ov = sub.add_parser("overhead")
    ov.add_argument("--out", type=Path, required=True)
    ov.add_argument("--frames", type=int, nargs="+", default=[120, 600, 1200])
    args = parser.parse_args()
    if args.command == "separation":
        separation(args.clips, args.width)
    else:
        overhead(args.out, args.frames)


if __name__ == "__main__":
    main()
