"""Where a mosaic command's time goes, every thread of it: the command run under yappi (wall
clock), the functions that spent the most time in themselves, and each thread's total.

    python -m benchmarks profile --out prof.txt -- stabilize flight.mp4 steady.mp4 --device cuda
    python -m benchmarks profile --top 40 -- track flight.mp4 -o flight.json

cProfile sees the main thread only; mosaic decodes, warps, encodes and finishes pairs on threads
of their own (docs/architecture.md), so the time of a stage on another thread would be missed.
Wall clock: a thread waiting on a queue, a pipe or the GIL is charged for the wait, which is what
tells a stage that works from one that waits.  yappi's own cost is about 1.5-3x on Python-heavy
code: compare the shares, not the seconds, with an unprofiled run.
"""

from __future__ import annotations

import argparse
import io
import time
from pathlib import Path

from benchmarks.common import make_parser

SUITE = "profile"


def main(argv: list[str] | None = None) -> int | None:
    ap = make_parser(SUITE, None, __doc__)
    ap.add_argument("--out", type=Path, help="write the report here (default: standard output)")
    ap.add_argument("--top", type=int, default=30, help="functions listed (by time spent in themselves)")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="-- then mosaic's own arguments")
    args = ap.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        ap.error("give the mosaic command after --")
    import yappi

    from mosaic_cli.cli import main as mosaic  # not the console entry, whose quick exit skips this report

    yappi.set_clock_type("wall")
    status: object = 0
    start = time.perf_counter()
    yappi.start(builtins=True, profile_threads=True)  # C calls (OpenCV, torch, PyAV) listed on their own
    try:
        mosaic(command)
    except SystemExit as exc:
        status = exc.code
    finally:
        yappi.stop()
    wall = time.perf_counter() - start
    report = io.StringIO()
    report.write(f"mosaic {' '.join(command)}\nexit status {status}, {wall:.2f} s of wall time (under yappi)\n\n")
    threads = yappi.get_thread_stats()
    threads.sort("ttot")
    report.write("threads (wall seconds each was scheduled, waits included):\n")
    for t in threads:
        report.write(f"  {t.name:<28} id {t.id:<4} {t.ttot:9.3f} s\n")
    stats = yappi.get_func_stats()
    stats.sort("tsub")
    report.write(f"\nthe {args.top} functions with the most time in themselves (tsub; ttot: with their callees):\n")
    for f in list(stats)[: args.top]:
        where = f"{Path(f.module).name}:{f.lineno}" if f.module else "?"
        report.write(f"  {f.tsub:9.3f} s  ttot {f.ttot:9.3f} s  calls {f.ncall:<8} {f.name}  ({where})\n")
    text = report.getvalue()
    if args.out:
        args.out.write_text(text)
    else:
        print(text)
    return int(status) if isinstance(status, int) else 1
