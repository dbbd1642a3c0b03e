"""``--rolling-shutter auto``'s probe: does it tell rolling from global shutters, and what does it cost?

* ``separation CLIP... [--width 320]``: `auto`'s probe on each clip's first frames as the
  tracking pass decodes them, then the readout and the cost of readout 0 against the best
  (``estimate_readout``; a global shutter under ``GLOBAL_COST_RATIO``), and its CPU time;
* ``overhead --out DIR``: global-shutter clips of 120, 600 and 1200 frames at 1280x720
  (simulated once), ``stabilize`` with ``--rolling-shutter off`` and ``auto`` in A-B-B-A order
  (``--rounds`` times, after one warm-up run): the probe's own seconds and CPU seconds (its
  thread's), each whole run's CPU seconds (the process's threads and its ffmpeg children) and
  wall seconds (say whether the machine was shared: CPU seconds suffer less from it).

    python scripts/bench_rolling_probe.py separation /tmp/rs/*.mp4 [--width 320]
    python scripts/bench_rolling_probe.py overhead --out /tmp/rsprobe [--frames 120 600 1200] [--rounds 2]
"""

from __future__ import annotations

import argparse
import itertools
import os
import resource
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
        motion, weights = rolling_probe.measured().arrays()
        clock = time.process_time()
        readout, costs = estimate_readout(motion, info.source_size[1], weights, PROBE_READOUTS)
        fit = time.process_time() - clock
        print(f"{clip.name:<40} readout {readout:.2f} (x{costs[0] / costs.min():.1f} at 0); CPU: tracking "
              f"{1000 * cpu / max(len(motion), 1):.1f} ms a pair, readouts {1000 * fit:.0f} ms", flush=True)


def cpu_seconds() -> float:
    """CPU seconds of this process (all its threads) and of its children that have ended (ffmpeg)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def overhead(out: Path, lengths: list[int], rounds: int = 1) -> None:
    out.mkdir(parents=True, exist_ok=True)
    print(f"probe: {AUTO_PROBE_FRAMES} frames")
    for frames in lengths:
        clip = out / f"gs_paper_{frames}.mp4"
        if not clip.exists():
            simulate_flight(clip, None, SimulateOptions(profile="paper", frames=frames, size=(1280, 720), seed=4), show_progress=False)
        stabilize(clip, clip.with_suffix(".warm.mp4"), StabilizeOptions(rolling_shutter="off"), show_progress=False)  # imports, caches
        runs = []
        for mode in ("off", "auto", "auto", "off") * rounds:
            clock = cpu_seconds()
            result = stabilize(clip, clip.with_suffix(f".{mode}.mp4"), StabilizeOptions(rolling_shutter=mode), show_progress=False)
            s = result.seconds
            runs.append((mode, s.get("rolling", 0.0), s.get("rolling_cpu", 0.0), s["total"], cpu_seconds() - clock, os.getloadavg()[0]))
        off = [r for r in runs if r[0] == "off"]
        auto = [r for r in runs if r[0] == "auto"]

        def spread(values: list[float], digits: int = 2) -> str:
            return f"{min(values):.{digits}f}-{max(values):.{digits}f}"

        mean = lambda rows, i: sum(r[i] for r in rows) / len(rows)  # noqa: E731
        print(f"{frames:>5} frames: probe {spread([r[1] for r in auto])} s wall, {spread([r[2] for r in auto])} s CPU; "
              f"whole run CPU off {spread([r[4] for r in off])}, auto {spread([r[4] for r in auto])} s "
              f"(means: auto - off {mean(auto, 4) - mean(off, 4):+.2f} s, probe CPU / off CPU {100 * mean(auto, 2) / mean(off, 4):.1f}%); "
              f"wall off {spread([r[3] for r in off])}, auto {spread([r[3] for r in auto])} s "
              f"(means {100 * (mean(auto, 3) / mean(off, 3) - 1):+.1f}%); load {spread([r[5] for r in runs], 1)}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sep = sub.add_parser("separation")
    sep.add_argument("clips", type=Path, nargs="+")
    sep.add_argument("--width", type=int, default=PROBE_WIDTH, help="frames decoded this wide (the estimator's; default: lstm's 320)")
    ov = sub.add_parser("overhead")
    ov.add_argument("--out", type=Path, required=True)
    ov.add_argument("--frames", type=int, nargs="+", default=[120, 600, 1200])
    ov.add_argument("--rounds", type=int, default=1, help="off, auto, auto, off this many times")
    args = parser.parse_args()
    if args.command == "separation":
        separation(args.clips, args.width)
    else:
        overhead(args.out, args.frames, args.rounds)


if __name__ == "__main__":
    main()
