#!/usr/bin/env python
"""The learned estimator on every core (issue 39, item 1): one video's frames decoded once, then
estimated with 1..N threads (``--threads``: the pool that checks each pair), with and without a
file's lookahead (the next chunk's network beside this chunk's checks), rounds in turn; the
median wall time of each, and whether every run gave the one-thread estimates to the bit.

    python scripts/bench_threads.py FLIGHT.mp4 [--threads 1,2] [--rounds 3] [-e lstm]

Estimation only (the decode, the overlay detection and writing the track are left out: see
``mosaic track``'s final line for those); say how loaded the machine was beside the figures.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mosaic_cli import device  # noqa: E402
from mosaic_cli.estimators import estimate_stream, make_estimator  # noqa: E402
from mosaic_cli.video import open_video  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("video", type=Path)
    parser.add_argument("--threads", default="1,2", help="pool sizes, comma-separated")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("-e", "--estimator", default="lstm")
    args = parser.parse_args()
    device.ask_cpu_threads(None)  # the network on one torch thread, as the commands run it
    estimator = make_estimator(args.estimator, device="cpu")
    with open_video(args.video, width=estimator.input_width, gray=True) as stream:
        frames, size = list(stream), stream.info.source_size
    runs = [(lookahead, int(t)) for lookahead in (False, True) for t in args.threads.split(",")]
    seconds: dict[tuple[bool, int], list[float]] = {run: [] for run in runs}
    reference, identical = None, True
    for _ in range(args.rounds):
        for lookahead, threads in runs:
            estimator.threads = threads
            start = time.perf_counter()
            H = np.array([e.H for e in estimate_stream(estimator, frames, size, lookahead=lookahead)])
            seconds[(lookahead, threads)].append(time.perf_counter() - start)
            reference = H if reference is None else reference
            identical &= bool(np.array_equal(H, reference))
    base = statistics.median(seconds[(False, 1)])
    print(f"{len(frames)} frames of {size[0]}x{size[1]}, -e {args.estimator}, {args.rounds} rounds")
    for (lookahead, threads), times in seconds.items():
        median = statistics.median(times)
        print(f"  threads {threads:>2}  lookahead {'on ' if lookahead else 'off'}  {median:6.2f} s  ({len(frames) / median:5.0f} fr/s, "
              f"{base / median:.2f}x one thread)  runs {', '.join(f'{t:.2f}' for t in times)}")
    print(f"every run gave the one-thread estimates to the bit: {identical}")
    return 0 if identical else 1


if __name__ == "__main__":
    raise SystemExit(main())
