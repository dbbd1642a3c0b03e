"""``python -m benchmarks SUITE [ARGS...]``: one suite's benchmark or tool; ``python -m benchmarks``
lists them, ``python -m benchmarks SUITE --help`` tells a suite's commands and arguments."""

from __future__ import annotations

import importlib
import sys

# suite: (module of this package, what it measures or makes).  A suite's module is imported only
# when it runs, so that one suite's imports (torch, PyAV, scipy) do not slow another's start.
SUITES = {
    "speed": ("speed", "the commands against ffmpeg's decode, a transcode and vid.stab; `floors`: the least time each could take"),
    "stitch": ("stitch", "stitch's placement accuracy, throughput, memory, revisits and photo folders; `drift-solver`"),
    "stabilize": ("stabilize", "stabilize against vid.stab; `perspective`: the motion models; `frames`: frames in = frames out"),
    "live": ("live", "live track, stitch and stabilize over loopback TCP: lag, latency, jitter, start-up, memory"),
    "flights": ("flights", "several flights into one map: overlapping flights against the truth, flights apart placed by their logs"),
    "maps": ("maps", "large canvases: the compose stage's peak memory and time per megapixel from 10 to 400 Mpx; whole photo-folder stitches"),
    "photos": ("photos", "geotagged photo folders into a map as the folder grows: time and pairs per photo, memory, accuracy"),
    "georef": ("georef", "georeferencing accuracy of stitch --telemetry on simulated flights with exact truth"),
    "memory": ("memory", "peak memory of track and stabilize as the clip grows"),
    "estimators": ("estimators", "the network's cost, threads, the ORB baselines, the model card's tables and failure analyses"),
    "lens": ("lens", "wide-angle and fisheye flights stitched or stabilised with --lens none, the true lens and auto"),
    "rolling-shutter": ("rolling_shutter", "--rolling-shutter of stabilize (against vid.stab) and of `stitch`; auto's `probe`"),
    "decode": ("decode", "decoding and probing speed of mosaic's video reader"),
    "overlay": ("overlay", "burned-in overlays: accuracy with and without detection, the detector's cost; `mask`: its tightness"),
    "gpu": ("gpu", "everything a session with a lent GPU does, in one call (scripts/gpu_session.sh runs it)"),
    "figures": ("figures", "the pictures of the README and the guides"),
    "compare": ("compare_outputs", "track, stitch and stabilize outputs of the working tree against a git revision's"),
    "profile": ("profile_command", "where a mosaic command's time goes, every thread of it (yappi)"),
    "help-snapshot": ("help_snapshot", "the --help of mosaic and every command, to diff a refactor against"),
}


def usage() -> str:
    width = max(map(len, SUITES))
    lines = [f"  {name:<{width}}  {about}" for name, (_, about) in SUITES.items()]
    return ("usage: python -m benchmarks SUITE [ARGS...]   (from the repository's root)\n\n"
            "suites:\n" + "\n".join(lines) + "\n\npython -m benchmarks SUITE --help: a suite's commands and arguments")


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0
    if argv[0] not in SUITES:
        print(f"python -m benchmarks: no suite {argv[0]!r}\n\n{usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(f"benchmarks.{SUITES[argv[0]][0]}")
    return module.main(argv[1:]) or 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
