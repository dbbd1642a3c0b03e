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
        per_row = math.ceil(math.sqrt(count * 1.5))
        rows = math.ceil(count / per_row)
        with tempfile.TemporaryDirectory(prefix="mosaic-photos-", dir=args.keep) as tmp:
            root = Path(tmp)
            footprint_along, footprint_across = h * args.gsd, w * args.gsd  # the top edge points along the line
            survey = write_survey(root / "photos", rows=rows, per_row=per_row, size=(w, h), gsd=args.gsd,
                                  along=0.42 * footprint_along, across=0.56 * footprint_across, map_gsd=args.map_gsd, seed=count)
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
    return run_commands(SUITE, __doc__, {"scaling": scaling}, argv, default=scaling)
