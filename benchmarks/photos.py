"""Photos: geotagged photo folders (benchmarks/survey.py: lawnmower surveys over a procedural
map, EXIF GPS 2.5 m off, DJI yaw 2 degrees off) stitched into a map with ``mosaic stitch FOLDER
-o map.tif``, as the folder grows: seconds per photo, pairs matched per photo, peak memory, and
the map's accuracy against the survey's exact truth."""

from __future__ import annotations

import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import make_parser, print_start, run_commands
from benchmarks.memory import run_child
from benchmarks.survey import score_survey, write_survey

SUITE = "photos"


def scaling(argv: list[str]) -> int:
    """Folders of --counts photos of --size, one row per folder: the time per photo should stay flat
    (the GPS names each photo's few neighbours; no search grows with the folder's square)."""
    parser = make_parser(SUITE, "scaling", scaling.__doc__)
    parser.add_argument("--counts", default="50,150,500", help="photos per folder, comma-separated")
    parser.add_argument("--size", default="640x480", help="photo size WxH")
    parser.add_argument("--gsd", type=float, default=0.25, help="metres per photo pixel")
    parser.add_argument("--map-gsd", type=float, default=0.25, help="metres per pixel of the map flown over")
    parser.add_argument("--keep", type=Path, help="keep the folders and maps here")
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    print_start()
    print(f"{'photos':>6} {'MP':>5} {'s/photo':>8} {'pairs/photo':>11} {'peak MiB':>9} {'placed':>7} {'pair px max':>11} "
          f"{'map m median':>12} {'fix m median':>12} {'scale':>6} {'north deg':>9}")
    for count in (int(c) for c in args.counts.split(",")):
        with tempfile.TemporaryDirectory(prefix="mosaic-photos-", dir=args.keep) as tmp:
            root = Path(tmp)
            survey = _survey(root / "photos", count, (w, h), args.gsd, args.map_gsd)
            n = len(survey.names)
            js = root / "t.json"
            start = time.perf_counter()
            peak, _, err = run_child_with_stderr(["mosaic", "stitch", str(survey.folder), "-o", str(root / "map.tif"),
                                                  "--transforms", str(js)])
            wall = time.perf_counter() - start
            pairs = _pairs(err)
            transforms = json.loads(js.read_text())
            placed, raw, scale, north, pair_px = score_survey(survey, transforms)
            print(f"{n:>6} {w * h / 1e6:>5.1f} {wall / n:>8.2f} {pairs / n:>11.1f} {peak:>9.0f} {len(transforms['frames']):>7} "
                  f"{max(pair_px):>11.2f} {np.median(placed):>12.2f} {np.median(raw):>12.2f} {np.median(scale):>6.4f} "
                  f"{np.median(north):>9.2f}", flush=True)
    return 0


def stages(argv: list[str]) -> int:
    """One folder of --count photos stitched in this process, its RSS sampled every 0.1 s: the
    peak of each stage (scan, register, georeference, compose, write), the process's own."""
    import functools
    import threading

    import mosaic_cli.stitch.pipeline as pipeline
    import mosaic_cli.stitch.scan as stitch_scan
    from mosaic_cli.geo.georef import GeorefOptions
    from mosaic_cli.stitch import StitchOptions

    parser = make_parser(SUITE, "stages", stages.__doc__)
    parser.add_argument("--count", type=int, default=500, help="photos in the folder")
    parser.add_argument("--size", default="4000x3000", help="photo size WxH")
    parser.add_argument("--gsd", type=float, default=0.04, help="metres per photo pixel")
    parser.add_argument("--map-gsd", type=float, default=0.1, help="metres per pixel of the map flown over")
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))

    def rss() -> float:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024.0

    peak = [0.0]

    def sample() -> None:
        while True:
            peak[0] = max(peak[0], rss())
            time.sleep(0.1)

    def timed(name, f):
        @functools.wraps(f)
        def stage(*a, **k):
            peak[0], start = rss(), time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                print(f"{name:>14} {time.perf_counter() - start:8.1f} s, peak {max(peak[0], rss()):6.0f} MiB", flush=True)
        return stage

    print_start()
    with tempfile.TemporaryDirectory(prefix="mosaic-photos-") as tmp:
        root = Path(tmp)
        survey = _survey(root / "photos", args.count, (w, h), args.gsd, args.map_gsd)
        threading.Thread(target=sample, daemon=True).start()
        for module, name in ((stitch_scan, "_scan"), (pipeline, "_register"), (pipeline, "_georeference"), (pipeline, "compose"),
                             (pipeline, "write_outputs")):
            setattr(module, name, timed(name.strip("_"), getattr(module, name)))
        start = time.perf_counter()
        result = pipeline.stitch(survey.folder, root / "map.tif", options=StitchOptions(georef=GeorefOptions()),
                                 transforms=root / "t.json", show_progress=False)
        *_, pair_px = score_survey(survey, json.loads((root / "t.json").read_text()))
        print(f"{len(survey.names)} photos of {w}x{h} into {result.canvas_size[0]}x{result.canvas_size[1]} in "
              f"{time.perf_counter() - start:.0f} s, worst pair {max(pair_px):.2f} px")
    return 0


def _survey(folder: Path, count: int, size: tuple[int, int], gsd: float, map_gsd: float):
    """The folder of about ``count`` photos both commands stitch: lines about 1.5x as long as they
    are apart, photos 42% of a footprint apart along a line (its top edge points along it) and 56%
    across, seeded by the count."""
    w, h = size
    per_row = math.ceil(math.sqrt(count * 1.5))
    return write_survey(folder, rows=math.ceil(count / per_row), per_row=per_row, size=size, gsd=gsd, along=0.42 * h * gsd,
                        across=0.56 * w * gsd, map_gsd=map_gsd, seed=count)


def run_child_with_stderr(cmd: list[str]) -> tuple[float, float, str]:
    """(peak RSS in MiB, wall seconds, stderr) of one child process."""
    return run_child(cmd, keep_stderr=True)


def _pairs(stderr: str) -> int:
    """The pairs the stitch says it matched (``N photo pairs matched, ...``)."""
    for line in stderr.splitlines():
        if "photo pairs matched" in line:
            return int(line.strip().split()[0])
    raise SystemExit("the stitch did not say how many photo pairs it matched")


def main(argv: list[str]) -> int:
    return run_commands(SUITE, __doc__, {"scaling": scaling, "stages": stages}, argv, default=scaling)
