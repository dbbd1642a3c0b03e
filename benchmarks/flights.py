"""Flights: several flights stitched into one map (issue 52).  A simulated flight (``mosaic
simulate``, with its exact ground truth and DJI SRT log) is cut into two flights, each a video
with its own log beside it; ``mosaic stitch a.mp4 b.mp4 -o map.tif`` must place both as the
truth does: where they overlap by registration (within 2 px), where they do not by their logs."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import imageio_ffmpeg
import numpy as np

from benchmarks.common import make_parser, print_start, run_commands

SUITE = "flights"
CUE = re.compile(r"(\d+)\n(\d\d):(\d\d):(\d\d),(\d\d\d) --> (\d\d):(\d\d):(\d\d),(\d\d\d)\n(.*?)(?:\n\n|\Z)", re.S)


def cut_flight(video: Path, start: int, stop: int, out: Path) -> Path:
    """Frames ``start`` .. ``stop - 1`` of a simulated ``video`` as a flight of its own at ``out``
    (H.264), with its DJI log beside it when it has one (``out`` with ``.SRT``: the cues of those
    frames, their times and frame counts from zero).  Returns ``out``."""
    fps = json.loads(video.with_suffix(".gt.json").read_text())["fps"]
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-loglevel", "error", "-y", "-i", str(video), "-vf",
                    f"select='between(n,{start},{stop - 1})',setpts=N/({fps}*TB)", "-c:v", "libx264",
                    "-preset", "ultrafast", "-crf", "12", "-r", str(fps), str(out)], check=True)
    log = video.with_suffix(".SRT")
    if not log.exists():  # a flight without telemetry
        return out
    cues = []
    for match in CUE.finditer(log.read_text()):
        number = int(match.group(1)) - 1
        if start <= number < stop:
            text = re.sub(r"FrameCnt: \d+", f"FrameCnt: {number - start + 1}", match.group(10))
            cues.append((number - start, text))
    lines = []
    for k, (frame, text) in enumerate(cues):
        lines.append(f"{k + 1}\n{_clock(frame / fps)} --> {_clock((frame + 1) / fps)}\n{text}\n")
    out.with_suffix(".SRT").write_text("\n".join(lines))
    return out


def _clock(seconds: float) -> str:
    ms = int(round(seconds * 1000))
    return f"{ms // 3_600_000:02d}:{ms // 60_000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"


def placement_spread(transforms: dict, truth: dict, offsets: dict[str, int]) -> tuple[float, set[str]]:
    """The largest distance (panorama px) between where the keyframes' transforms put one map
    point and where they put it on average: 0 when every keyframe of every flight is placed as
    the truth is (up to one map -> panorama homography).  ``offsets``: each flight's first frame
    in the flight it was cut from.  Also the flights whose keyframes see that point."""
    from mosaic_cli.geometry import normalize, project

    map_to_frame = np.array(truth["map_to_frame"])
    frames = [offsets[Path(f["flight"]).name] + f["frame"] for f in transforms["frames"]]  # in the flight cut from
    to_pano = [normalize(np.array(f["H"]) @ map_to_frame[i]) for f, i in zip(transforms["frames"], frames)]
    w, h = truth["size"]
    middle = frames[len(frames) // 2]
    point = project(np.linalg.inv(map_to_frame[middle]), np.array([[w / 2.0, h / 2.0]]))  # a map point the middle keyframe sees
    # Only the keyframes that see the point: the others' homographies say nothing of it.
    landed, seen_by = [], set()
    for f, i, A in zip(transforms["frames"], frames, to_pano):
        q = project(map_to_frame[i], point)[0]
        if 0 <= q[0] < w and 0 <= q[1] < h:
            landed.append(project(A, point)[0])
            seen_by.add(Path(f["flight"]).name)
    spread = np.array(landed)
    return float(np.max(np.linalg.norm(spread - np.median(spread, axis=0), axis=1))), seen_by


def survey_in_two(root: Path, frames: int, size: str, overlap: float = 0.2, seed: int = 3) -> tuple[Path, list[Path], int]:
    """A simulated survey of ``frames`` (with its DJI log) in ``root``, cut into two flights of
    equal length of which ``overlap`` of each is flown by both: the survey, the two flights, and
    the frame of the survey the second starts at."""
    full = root / "full.mp4"
    subprocess.run(["mosaic", "simulate", "-p", "survey", "-n", str(frames), "--size", size, "-o", str(full), "-q",
                    "--telemetry", "srt", "--seed", str(seed), "--preset", "ultrafast"], check=True)
    length = round(frames / (2.0 - overlap))  # two flights of this many frames ...
    start = length - round(overlap * length)  # ... the second from here
    return full, [cut_flight(full, 0, length, root / "a.mp4"), cut_flight(full, start, frames, root / "b.mp4")], start


def two(argv: list[str]) -> int:
    """A simulated survey cut into two flights overlapping by --overlap of their frames; both
    stitched into one map: how far the keyframes of both flights put one map point apart."""
    parser = make_parser(SUITE, "two", two.__doc__)
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--overlap", type=float, default=0.2, help="share of each flight's frames flown again by the other")
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args(argv)
    print_start()
    with tempfile.TemporaryDirectory(prefix="mosaic-flights-") as tmp:
        root = Path(tmp)
        full, (a, b), b_start = survey_in_two(root, args.frames, args.size, args.overlap, args.seed)
        length = round(args.frames / (2.0 - args.overlap))
        shared = length - b_start
        js = root / "map.json"
        proc = subprocess.run(["mosaic", "stitch", str(a), str(b), "-o", str(root / "map.tif"), "--transforms", str(js)],
                              capture_output=True, text=True)
        print(proc.stdout + proc.stderr, file=sys.stderr)
        if proc.returncode:
            return proc.returncode
        spread, seen_by = placement_spread(json.loads(js.read_text()), json.loads(full.with_suffix(".gt.json").read_text()),
                                           {"a.mp4": 0, "b.mp4": b_start})
        print(f"two flights of {length} and {args.frames - length + shared} frames, {shared} flown by both: the keyframes of "
              f"{len(seen_by)} flights place one map point within {spread:.2f} px")
    return 0


def fly_apart(folder: Path, metres: float = 150.0, lat: float = 47.4, lon: float = 8.5) -> list[Path]:
    """Two simulated flights (``west``, ``east``) over two different procedural maps whose centres
    lie ``metres`` apart, each with its DJI log and its map's place (``.geo.json``) beside it:
    nothing to register between them, only their logs to place them."""
    shift = metres / (111_320.0 * np.cos(np.radians(lat)))  # degrees of longitude
    flights = []
    for name, seed, at in (("west", 2, lon), ("east", 1, lon + shift)):
        video = folder / f"{name}.mp4"
        subprocess.run(["mosaic", "simulate", "-p", "paper", "-n", "120", "--size", "320x180", "-o", str(video), "-q", "--telemetry",
                        "srt", "--seed", str(seed), "--preset", "ultrafast", "--origin", f"{lat},{at}", "--gsd", "0.05"], check=True)
        flights.append(video)
    return flights


def ground_errors(transforms: dict, folder: Path) -> dict[str, list[float]]:
    """Metres between where each keyframe's ``map_H`` puts its frame's centre and where the
    truth has it, by flight (the flights' ``.gt.json`` and ``.geo.json`` in ``folder``)."""
    from mosaic_cli.geometry import project

    errors: dict[str, list[float]] = {}
    for f in transforms["frames"]:
        name = Path(f["flight"]).stem
        truth = json.loads((folder / f"{name}.gt.json").read_text())
        geo = json.loads((folder / f"{name}.geo.json").read_text())
        w, h = truth["size"]
        centre = np.array([[(w - 1) / 2.0, (h - 1) / 2.0]])
        on_map = project(np.linalg.inv(np.array(truth["map_to_frame"][f["frame"]])), centre)
        true_ground = project(np.array(geo["map_to_crs"]), on_map)[0]
        errors.setdefault(name, []).append(float(np.linalg.norm(project(np.array(f["map_H"]), centre)[0] - true_ground)))
    return errors


def apart(argv: list[str]) -> int:
    """Two flights over ground --metres apart (nothing to register between them), stitched into
    one map: each keyframe's distance from the truth, placed by the flights' logs alone (3 m RMS)."""
    parser = make_parser(SUITE, "apart", apart.__doc__)
    parser.add_argument("--metres", type=float, default=150.0)
    args = parser.parse_args(argv)
    print_start()
    with tempfile.TemporaryDirectory(prefix="mosaic-flights-") as tmp:
        root = Path(tmp)
        west, east = fly_apart(root, args.metres)
        js = root / "map.json"
        subprocess.run(["mosaic", "stitch", str(west), str(east), "-o", str(root / "map.tif"), "--transforms", str(js), "-q"], check=True)
        maps = sorted(p.name for p in root.glob("map*.tif"))
        for name, errors in ground_errors(json.loads(js.read_text()), root).items():
            print(f"{name}: {len(errors)} keyframes, {min(errors):.2f}-{max(errors):.2f} m from the truth (median {np.median(errors):.2f} m)")
        print(f"maps written: {', '.join(maps)}")
    return 0


def workers(argv: list[str]) -> int:
    """Two flights of one simulated survey (as ``two`` cuts them) stitched into one map in one
    process and with --workers N (each flight scanned by a worker, the tiles blended by them),
    alternated --rounds times: wall seconds of the whole command."""
    args = _workers_parser("workers", workers.__doc__, frames=600).parse_args(argv)
    print_start()
    with tempfile.TemporaryDirectory(prefix="mosaic-flights-") as tmp:
        _, flights, _ = survey_in_two(Path(tmp), args.frames, args.size)
        _alternate(["mosaic", "stitch", *map(str, flights), "-o", str(Path(tmp) / "map.tif"), "-q"], args)
    return 0


def segments(argv: list[str]) -> int:
    """One long simulated survey stitched in one process and with --workers N (the video cut into
    N segments scanned at once, joined by registration), alternated --rounds times: wall seconds
    of the whole command, and each run's keyframes against the exact homographies (the corner
    error of every pair of keyframes, median and 95th percentile)."""
    from benchmarks.common import placement_errors

    args = _workers_parser("segments", segments.__doc__, frames=2400).parse_args(argv)
    print_start()
    with tempfile.TemporaryDirectory(prefix="mosaic-segments-") as tmp:
        video, js = Path(tmp) / "flight.mp4", Path(tmp) / "pano.json"
        subprocess.run(["mosaic", "simulate", "-p", "survey", "-n", str(args.frames), "--size", args.size, "-o", str(video), "-q",
                        "--seed", "3", "--preset", "ultrafast"], check=True)
        truth = np.array(json.loads(video.with_suffix(".gt.json").read_text())["map_to_frame"])
        size = tuple(int(v) for v in args.size.split("x"))

        def accuracy() -> str:
            frames = json.loads(js.read_text())["frames"]
            e = placement_errors([f["index"] for f in frames], [np.array(f["H"]) for f in frames], truth, size, 1)
            return f"keyframe pairs {np.median(e):.2f} px median, {np.percentile(e, 95):.2f} px at the 95th percentile"

        _alternate(["mosaic", "stitch", str(video), "-o", str(Path(tmp) / "pano.png"), "--transforms", str(js), "-q"], args, accuracy)
    return 0


def _workers_parser(name: str, doc: str | None, frames: int):
    parser = make_parser(SUITE, name, doc)
    parser.add_argument("--frames", type=int, default=frames)
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=2)
    return parser


def _alternate(command: list[str], args, after=None) -> None:
    """``command`` in one process and with --workers, alternated ``args.rounds`` times: each one's
    median wall seconds, its runs and its speed against one process, and what ``after()`` says of
    its last run."""
    import time

    said: dict[str, str] = {}
    walls: dict[str, list[float]] = {"one process": [], f"--workers {args.workers}": []}
    for _ in range(args.rounds):
        for name, extra in (("one process", []), (f"--workers {args.workers}", ["--workers", str(args.workers)])):
            start = time.perf_counter()
            subprocess.run([*command, *extra], check=True)
            walls[name].append(time.perf_counter() - start)
            said[name] = f"; {after()}" if after is not None else ""
    base = float(np.median(walls["one process"]))
    for name, values in walls.items():
        print(f"{name:>12}: {np.median(values):.1f} s (runs {', '.join(f'{v:.1f}' for v in values)}; "
              f"{base / np.median(values):.2f}x){said[name]}")


def main(argv: list[str]) -> int:
    return run_commands(SUITE, __doc__, {"two": two, "apart": apart, "workers": workers, "segments": segments}, argv, default=two)
