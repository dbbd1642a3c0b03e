"""Maps: large canvases in bounded memory (issue 52).  ``compose``: the compose stage alone,
drawing a grid of overlapping keyframes onto canvases of --mpx megapixels (tile by tile, into the
staged GeoTIFF, then a PNG), one child process each: peak RSS and seconds per megapixel, which
should both stay flat as the canvas grows.  ``stitch``: the whole ``mosaic stitch`` of simulated
12 MP photo folders (benchmarks/survey.py) whose maps reach about --mpx megapixels.  ``costs``:
what moving one keyframe costs (its spill written, read back from the page cache and from the disk,
and fetched by a Dask worker over loopback): the transfer term of docs/guide/costs.md.
``writers``: a staged map of --mpx megapixels of noise written as a COG and as a PNG, and how
long each run goes on after SIGTERM at half its write (it should stop at once)."""

from __future__ import annotations

import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from benchmarks.common import make_parser, print_start, run_commands, stage_seconds
from benchmarks.memory import run_child
from benchmarks.survey import write_survey

SUITE = "maps"
IMAGE = (2048, 1536)  # each keyframe of the compose benchmark, a 3 MP photo's size
STEP = 0.5  # the grid's step, a share of the image: each keyframe overlaps its neighbours by half


def compose_scaling(argv: list[str]) -> int:
    """The compose stage on canvases of --mpx megapixels (keyframes of 2048x1536 on a grid, each
    overlapping its neighbours by half, cut from a procedural texture with uneven exposure), one
    child process each: peak RSS, compose seconds per megapixel, the PNG's write seconds."""
    parser = make_parser(SUITE, "compose", compose_scaling.__doc__)
    parser.add_argument("--mpx", default="10,40,160,400", help="canvas sizes, megapixels, comma-separated")
    parser.add_argument("--keep", type=Path, help="keep the keyframes and the panoramas here")
    args = parser.parse_args(argv)
    print_start()
    print(f"{'Mpx':>5} {'canvas':>12} {'keyframes':>9} {'peak MiB':>9} {'compose s':>9} {'s/Mpx':>6} {'s/kf Mpx':>8} {'png s':>6} {'png MB':>7}")
    rows = []
    for mpx in (float(m) for m in args.mpx.split(",")):
        with tempfile.TemporaryDirectory(prefix="mosaic-maps-", dir=args.keep) as tmp:
            root = Path(tmp)
            canvas, count = _write_keyframes(root, mpx)
            out = root / "pano.png"
            peak, _, err = run_child([sys.executable, "-m", "benchmarks", "maps", "compose-child", str(root), str(out)], keep_stderr=True)
            report = json.loads(err.strip().splitlines()[-1])
            area, drawn = canvas[0] * canvas[1] / 1e6, count * IMAGE[0] * IMAGE[1] / 1e6
            rows.append((area, peak, report["compose_s"] / area, report["compose_s"] / drawn))
            print(f"{area:>5.0f} {canvas[0]:>6}x{canvas[1]:<5} {count:>9} {peak:>9.0f} {report['compose_s']:>9.1f} "
                  f"{report['compose_s'] / area:>6.3f} {report['compose_s'] / drawn:>8.3f} {report['write_s']:>6.1f} "
                  f"{out.stat().st_size / 1e6:>7.0f}", flush=True)
    peaks, rates, fed = [r[1] for r in rows], [r[2] for r in rows], [r[3] for r in rows]
    # A small canvas is mostly edge, where fewer keyframes overlap: seconds per canvas Mpx grow
    # with the overlap's depth, seconds per keyframe Mpx drawn (s/kf Mpx) do not.
    print(f"peak RSS max/min {max(peaks) / min(peaks):.2f}x (goal 1.3x, and at most 2048 MiB); "
          f"s/Mpx max/min {max(rates) / min(rates):.2f}x, s/kf Mpx {max(fed) / min(fed):.2f}x (goal 1.5x)")
    return 0


def _write_keyframes(root: Path, mpx: float) -> tuple[tuple[int, int], int]:
    """Keyframes spilled to ``root`` (``.npy``, as a stitch holds them) and ``plan.json`` (each
    one's canvas homography): a square-ish grid whose bounding box is about ``mpx`` megapixels."""
    w, h = IMAGE
    cols = max(1, round((math.sqrt(mpx * 1e6 * w / h) - w) / (STEP * w)) + 1)
    rows = max(1, round((mpx * 1e6 / ((w + (cols - 1) * STEP * w)) - h) / (STEP * h)) + 1)
    canvas = (int(w + (cols - 1) * STEP * w) + 8, int(h + (rows - 1) * STEP * h) + 8)
    rng = np.random.default_rng(0)
    base = _texture(2 * w, 2 * h)
    plan = []
    for r in range(rows):
        for c in range(cols):
            x, y = rng.integers(0, w), rng.integers(0, h)
            image = np.clip(base[y:y + h, x:x + w] * rng.uniform(0.85, 1.15), 0, 255).astype(np.uint8)
            path = root / f"k{r:03d}_{c:03d}.npy"
            np.save(path, image, allow_pickle=False)
            angle = math.radians(rng.uniform(-3, 3))
            cos, sin = math.cos(angle), math.sin(angle)
            H = [[cos, -sin, 4 + c * STEP * w], [sin, cos, 4 + r * STEP * h], [0.0, 0.0, 1.0]]
            plan.append({"path": str(path), "H": H})
    (root / "plan.json").write_text(json.dumps({"canvas": canvas, "keyframes": plan}))
    return canvas, len(plan)


def _texture(width: int, height: int) -> np.ndarray:
    rng = np.random.default_rng(1)
    image = np.zeros((height, width, 3), np.float32)
    for cell, weight in ((512, 0.9), (96, 0.7), (16, 0.5), (3, 0.3)):
        coarse = rng.random((height // cell + 2, width // cell + 2, 3), dtype=np.float32)
        image += weight * cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    return (image - image.min()) / (image.max() - image.min()) * 255.0


def compose_child(argv: list[str]) -> int:
    """(run by ``compose``) compose ROOT's plan into OUT; the seconds as JSON on stderr's last line."""
    from mosaic_cli.stitch.compose import ComposeOptions, PlacedImage, compose
    from mosaic_cli.stitch.raster import staged_panorama, write_image
    from mosaic_cli.stitch.spill import SpilledImage

    root, out = Path(argv[0]), Path(argv[1])
    workers = int(argv[2]) if len(argv) > 2 else None
    plan = json.loads((root / "plan.json").read_text())
    canvas = tuple(plan["canvas"])
    placed = []
    class Kept(SpilledImage):
        """The benchmark's keyframe file: read as a stitch's spilled pixels, kept for the next run."""

        def drop(self) -> None:
            pass

    for item in plan["keyframes"]:
        spilled = Kept.__new__(Kept)  # the file exists: no need to write it again
        spilled.path, spilled.shape, spilled.size, spilled.dtype = Path(item["path"]), (IMAGE[1], IMAGE[0], 3), IMAGE[0] * IMAGE[1] * 3, np.uint8
        placed.append(PlacedImage(spilled, np.array(item["H"])))
    from mosaic_cli.stitch.cluster import ClusterOptions, connect, tile_runner

    begun = time.perf_counter()
    with connect(ClusterOptions(workers), root) as client:
        start = time.perf_counter()  # (the cluster's start is not compose's)
        with staged_panorama(out, canvas) as staged:  # type: ignore[arg-type]
            runner = tile_runner(client) if client is not None else None
            compose(placed, canvas, ComposeOptions(), sink=staged, runner=runner)  # type: ignore[arg-type]
            composed = time.perf_counter()
            write_image(out, staged, "png")
        done = time.perf_counter()
    print(json.dumps({"compose_s": composed - start, "write_s": done - composed, "cluster_start_s": start - begun,
                      "wall_s": time.perf_counter() - begun}), file=sys.stderr)
    return 0


def workers(argv: list[str]) -> int:
    """The compose stage of one canvas (--mpx) in one process and on --workers local Dask
    workers, alternated --rounds times: compose seconds, the cluster's start, the whole run."""
    parser = make_parser(SUITE, "workers", workers.__doc__)
    parser.add_argument("--mpx", type=float, default=40.0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args(argv)
    print_start()
    with tempfile.TemporaryDirectory(prefix="mosaic-maps-") as tmp:
        root = Path(tmp)
        canvas, count = _write_keyframes(root, args.mpx)
        print(f"canvas {canvas[0]}x{canvas[1]} ({canvas[0] * canvas[1] / 1e6:.0f} Mpx), {count} keyframes")
        times: dict[str, list[dict]] = {"one process": [], f"{args.workers} workers": []}
        for _ in range(args.rounds):
            for name, extra in (("one process", []), (f"{args.workers} workers", [str(args.workers)])):
                out = root / "pano.png"
                peak, _, err = run_child([sys.executable, "-m", "benchmarks", "maps", "compose-child", str(root), str(out), *extra],
                                         keep_stderr=True)
                times[name].append({**json.loads(err.strip().splitlines()[-1]), "peak": peak})
        base = float(np.median([t["compose_s"] for t in times["one process"]]))
        for name, runs in times.items():
            compose_s = float(np.median([t["compose_s"] for t in runs]))
            print(f"{name:>12}: compose {compose_s:.1f} s ({base / compose_s:.2f}x), cluster start "
                  f"{np.median([t['cluster_start_s'] for t in runs]):.1f} s, whole run {np.median([t['wall_s'] for t in runs]):.1f} s, "
                  f"peak (this process) {max(t['peak'] for t in runs):.0f} MiB")
    return 0


def stitch_scaling(argv: list[str]) -> int:
    """The whole ``mosaic stitch FOLDER -o map.tif`` of simulated geotagged 12 MP photo folders
    whose maps reach about --mpx megapixels at the photos' own resolution: peak RSS, the compose
    stage's seconds per megapixel, the canvas."""
    parser = make_parser(SUITE, "stitch", stitch_scaling.__doc__)
    parser.add_argument("--mpx", default="10,40", help="map sizes, megapixels, comma-separated")
    parser.add_argument("--size", default="4000x3000", help="photo size WxH")
    parser.add_argument("--keep", type=Path, help="keep the folders and maps here")
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    gsd = 0.05
    print_start()
    print(f"{'Mpx':>5} {'photos':>6} {'canvas':>12} {'peak MiB':>9} {'wall s':>7} {'compose s':>9} {'s/Mpx':>6}")
    for mpx in (float(m) for m in args.mpx.split(",")):
        along, across = 0.55 * h * gsd, 0.6 * w * gsd  # new ground per photo: 0.33 of a photo
        per_row = max(2, round(math.sqrt(mpx * 1e6 / (0.33 * w * h))))
        rows = max(1, round(mpx * 1e6 / (0.33 * w * h) / per_row))
        with tempfile.TemporaryDirectory(prefix="mosaic-maps-", dir=args.keep) as tmp:
            root = Path(tmp)
            survey = write_survey(root / "photos", rows=rows, per_row=per_row, size=(w, h), gsd=gsd, along=along, across=across,
                                  map_gsd=2.5 * gsd, seed=int(mpx))
            js = root / "t.json"
            peak, wall, err = run_child(["mosaic", "stitch", str(survey.folder), "-o", str(root / "map.tif"), "--transforms", str(js)],
                                        keep_stderr=True)
            canvas = json.loads(js.read_text())["canvas_size"]
            area = canvas[0] * canvas[1] / 1e6
            compose_s = stage_seconds(err).get("compose", float("nan"))
            print(f"{area:>5.0f} {len(survey.names):>6} {canvas[0]:>6}x{canvas[1]:<5} {peak:>9.0f} {wall:>7.0f} {compose_s:>9.1f} "
                  f"{compose_s / area:>6.3f}", flush=True)
    return 0


def costs(argv: list[str]) -> int:
    """Milliseconds to move one keyframe of --size: its spill written (as a stitch holds it), read
    back from the page cache and from the disk (the file's cached pages dropped first), and
    fetched by a worker of a local Dask cluster over loopback; medians of --count keyframes."""
    from mosaic_cli.stitch.spill import SpilledImage

    parser = make_parser(SUITE, "costs", costs.__doc__)
    parser.add_argument("--size", default="2048x1536", help="keyframe size WxH (RGB)")
    parser.add_argument("--count", type=int, default=20)
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    print_start()
    image = _texture(w, h).astype(np.uint8)
    timings: dict[str, list[float]] = {"written": [], "read from the page cache": [], "read from the disk": []}
    with tempfile.TemporaryDirectory(prefix="mosaic-maps-", dir=Path.cwd()) as tmp:
        spilled = []
        for _ in range(args.count):
            started = time.perf_counter()
            spilled.append(SpilledImage(image, tmp))
            timings["written"].append(time.perf_counter() - started)
        for item in spilled:
            started = time.perf_counter()
            item.load()
            timings["read from the page cache"].append(time.perf_counter() - started)
            with open(item.path, "rb") as file:
                os.fsync(file.fileno())
                os.posix_fadvise(file.fileno(), 0, 0, os.POSIX_FADV_DONTNEED)
            started = time.perf_counter()
            item.load()
            timings["read from the disk"].append(time.perf_counter() - started)
        timings.update(_fetched_by_a_worker(spilled))
    megabytes = image.nbytes / 1e6
    print(f"one keyframe of {w}x{h} RGB: {megabytes:.1f} MB; milliseconds, median (min-max) of {args.count}")
    for name, seconds in timings.items():
        ms = 1000 * np.array(seconds)
        print(f"{name:>32}: {np.median(ms):7.1f} ({ms.min():.1f}-{ms.max():.1f}) ms, {megabytes / np.median(seconds) / 1e3:.2f} GB/s")
    return 0


def _fetched_by_a_worker(spilled: list) -> dict[str, list[float]]:
    """Each spilled keyframe loaded by a worker of a local cluster and its pixels sent back over loopback."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        print("(no cluster extra: the worker's fetch is not measured)")
        return {}
    seconds = []
    with LocalCluster(n_workers=1, threads_per_worker=1, host="127.0.0.1", dashboard_address=None) as cluster, Client(cluster) as client:
        client.submit(np.zeros, 1).result()  # the worker is up
        for item in spilled:
            started = time.perf_counter()
            client.submit(item.load, pure=False).result()
            seconds.append(time.perf_counter() - started)
    return {"loaded by a worker, sent back": seconds}


# The writer of a map under the command line's handling of signals and errors (cli.main's): a
# signal unwinds the run, which says so in one line and exits 128 + the signal; mosaic's own
# errors are one line and exit 1.  Arguments: the format ("cog" or "png"), the staged map, the
# output, the map's side in pixels.
WRITE_UNDER_SIGNALS = """
import sys
from pathlib import Path

from mosaic_cli import cli
from mosaic_cli.errors import MosaicError

fmt, staged, out, side = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4])
with cli._stop_by_unwinding_on_signals():
    try:
        if fmt == "cog":
            from mosaic_cli.geo.output import write_cog

            write_cog(out, staged, (side, side))
        else:
            from mosaic_cli.stitch.raster import StagedPanorama, write_image

            panorama = StagedPanorama.__new__(StagedPanorama)
            panorama.path, panorama.size = staged, (side, side)
            panorama.close = lambda: None
            write_image(out, panorama, fmt)
    except KeyboardInterrupt:
        cli._fail_stopped()
    except MosaicError as exc:
        sys.exit(f"mosaic: error: {exc}")
"""


def write_noise_map(path: Path, side: int) -> None:
    """A georeferenced RGBA GeoTIFF of ``side`` x ``side`` px of noise (which GDAL copies slowly),
    staged as compose stages a panorama."""
    import rasterio
    from rasterio.transform import Affine

    from mosaic_cli.stitch.raster import StagedPanorama

    tile = np.random.default_rng(0).integers(0, 256, (2000, 2000, 4), dtype=np.uint8)
    tile[..., 3] = 255
    with rasterio.Env(GDAL_PAM_ENABLED="NO"):
        staged = StagedPanorama(path, (side, side), crs="EPSG:32633", transform=Affine(0.05, 0, 500000, 0, -0.05, 5000000))
        for y in range(0, side, 2000):
            for x in range(0, side, 2000):
                staged.write(x, y, tile[:side - y, :side - x])
        staged.close()


def writers(argv: list[str]) -> int:
    """Seconds to write a staged map of --mpx megapixels of noise as a COG and as a PNG (each in a
    child process under the command line's handling of signals), and how long a run goes on
    after SIGTERM at half that time; medians of --rounds."""
    import signal
    import subprocess

    parser = make_parser(SUITE, "writers", writers.__doc__)
    parser.add_argument("--mpx", type=float, default=144.0)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    side = int(round(math.sqrt(args.mpx * 1e6)))
    print_start()
    with tempfile.TemporaryDirectory(prefix="mosaic-maps-", dir=Path.cwd()) as tmp:
        staged = Path(tmp) / "staged.tif"
        write_noise_map(staged, side)
        print(f"a staged map of {side}x{side} px of noise ({side * side / 1e6:.0f} Mpx); seconds, median (min-max) of {args.rounds}")
        for fmt, name in (("cog", "map.tif"), ("png", "map.png")):
            command = [sys.executable, "-c", WRITE_UNDER_SIGNALS, fmt, str(staged), str(Path(tmp) / name), str(side)]
            whole, after = [], []
            for _ in range(args.rounds):
                started = time.perf_counter()
                subprocess.run(command, check=True)
                whole.append(time.perf_counter() - started)
                run = subprocess.Popen(command, stderr=subprocess.DEVNULL)
                time.sleep(whole[-1] / 2)
                run.send_signal(signal.SIGTERM)
                signalled = time.perf_counter()
                run.wait()
                after.append(time.perf_counter() - signalled)
            print(f"{fmt:>4}: written in {np.median(whole):6.2f} ({min(whole):.2f}-{max(whole):.2f}) s; "
                  f"SIGTERM at half of it: ended {np.median(after):.2f} ({min(after):.2f}-{max(after):.2f}) s later")
    return 0


def main(argv: list[str]) -> int:
    return run_commands(SUITE, __doc__, {"compose": compose_scaling, "compose-child": compose_child, "stitch": stitch_scaling, "workers": workers,
                                          "costs": costs, "writers": writers}, argv,
                        default=compose_scaling)
