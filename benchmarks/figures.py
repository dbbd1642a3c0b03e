"""Figures: the pictures of the README and the guides, each made by the commands a user runs."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from benchmarks.common import ROOT, SHARED_DATA, STILLS, make_parser, run_commands

SUITE = "figures"


# -- python -m benchmarks figures lens -------------------------------------------------------------


def labelled(image: np.ndarray, text: str) -> np.ndarray:
    """``image`` (BGR) with ``text`` in a dark band along its top."""
    out = image.copy()
    cv2.rectangle(out, (0, 0), (out.shape[1], 26), (0, 0, 0), -1)
    cv2.putText(out, text, (8, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def side_by_side(images: list[np.ndarray], height: int, gap: int = 8) -> np.ndarray:
    """The images scaled to ``height`` and joined left to right, white between them."""
    scaled = [cv2.resize(i, (round(i.shape[1] * height / i.shape[0]), height), interpolation=cv2.INTER_AREA) for i in images]
    parts: list[np.ndarray] = []
    for k, image in enumerate(scaled):
        if k:
            parts.append(np.full((height, gap, 3), 255, np.uint8))
        parts.append(image)
    return np.hstack(parts)


def on_white(path: Path) -> np.ndarray:
    """A panorama PNG (RGBA: transparent where nothing was seen) over white, BGR."""
    rgba = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if rgba is None:
        raise SystemExit(f"{path}: not found (run python -m benchmarks lens first)")
    if rgba.shape[2] == 3:
        return rgba
    alpha = rgba[..., 3:].astype(np.float32) / 255.0
    return (rgba[..., :3].astype(np.float32) * alpha + 255.0 * (1.0 - alpha)).astype(np.uint8)


def mean_of_frames(path: Path, first: int, count: int) -> np.ndarray:
    """The mean (BGR) of ``count`` consecutive frames of a video from frame ``first``."""
    capture = cv2.VideoCapture(str(path))
    capture.set(cv2.CAP_PROP_POS_FRAMES, first)
    frames = []
    for _ in range(count):
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame.astype(np.float32))
    capture.release()
    if not frames:
        raise SystemExit(f"{path}: no frames (run python -m benchmarks lens --stabilize first)")
    return np.clip(np.mean(frames, axis=0) + 0.5, 0, 255).astype(np.uint8)


def lens_command(argv: list[str] | None = None) -> int | None:
    """The lens pictures of the guides, from ``python -m benchmarks lens``'s outputs:

    * docs/lens_before_after.jpg (the stitch guide): the k1 -0.30 survey flight's panorama with
      ``--lens none`` and with the true lens file, side by side;
    * docs/lens_stabilize_before_after.jpg (the stabilize guide): one frame of the shaky fisheye
      flight stabilised with ``--lens none`` (the lens's bend left in: the roofs' straight edges
      curve) and with ``--lens auto`` (a pinhole view: straight edges straight).

        python -m benchmarks lens --out runs/lens
        python -m benchmarks lens --out runs/lens_stabilize --stabilize --frames 90 --flights pinhole,wide-0.30,fisheye
        python -m benchmarks figures lens --runs runs/lens --stabilized runs/lens_stabilize
    """
    parser = make_parser(SUITE, 'lens', lens_command.__doc__)
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "lens", help="python -m benchmarks lens's --out")
    parser.add_argument("--stabilized", type=Path, default=ROOT / "runs" / "lens_stabilize", help="python -m benchmarks lens --stabilize's --out")
    parser.add_argument("--frame", type=int, default=40, help="the stabilised frame shown")
    args = parser.parse_args(argv)

    stitch = side_by_side([labelled(on_white(args.runs / "wide-0.30_none.png"), "--lens none"),
                           labelled(on_white(args.runs / "wide-0.30_file.png"), "--lens (the lens file)")], 320)
    cv2.imwrite(str(ROOT / "docs" / "lens_before_after.jpg"), stitch, [cv2.IMWRITE_JPEG_QUALITY, 88])

    panels = [labelled(mean_of_frames(args.stabilized / f"shaky_fisheye_{option}.mp4", args.frame, 1), f"stabilize --lens {option}")
              for option in ("none", "auto")]
    cv2.imwrite(str(ROOT / "docs" / "lens_stabilize_before_after.jpg"), side_by_side(panels, 360), [cv2.IMWRITE_JPEG_QUALITY, 88])
    return 0


# -- python -m benchmarks figures rolling-shutter --------------------------------------------------

DEFAULT_MAP = STILLS / "odm_orthomosaic_previews" / "zoo.png"
ROWS, COLUMNS, SCALE = (70, 470), slice(330, 630), (2, 3)  # rows sliced; the columns kept; zoom (x, time)


def _grid_map(photo: Path | None, out: Path) -> None:
    """The map with straight lines painted on it every 96 px (a procedural map without ``photo``)."""
    from mosaic_cli.simulate import load_map

    ground = cv2.cvtColor(load_map(str(photo) if photo else None, seed=3), cv2.COLOR_RGB2BGR)
    ground = cv2.resize(ground, (2400, round(2400 * ground.shape[0] / ground.shape[1])), interpolation=cv2.INTER_CUBIC)
    h, w = ground.shape[:2]
    for k in range(48, max(h, w) - 48, 96):
        cv2.line(ground, (k, 48), (k, h - 48), (0, 220, 255), 3)
        cv2.line(ground, (48, k), (w - 48, k), (0, 220, 255), 3)
    cv2.imwrite(str(out), ground)


def _slices(video: Path, label: str) -> np.ndarray:
    capture = cv2.VideoCapture(str(video))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    parts = []
    for y in ROWS:
        cut = np.stack([f[y, COLUMNS] for f in frames])  # (time, width, 3)
        parts.append(cv2.resize(cut, (cut.shape[1] * SCALE[0], cut.shape[0] * SCALE[1]), interpolation=cv2.INTER_NEAREST))
        parts.append(np.full((6, parts[-1].shape[1], 3), 255, np.uint8))
    column = np.vstack([np.zeros((30, parts[0].shape[1], 3), np.uint8), *parts[:-1]])
    cv2.putText(column, label, (8, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return column


def rolling_shutter_command(argv: list[str] | None = None) -> int | None:
    """The before/after picture of `stabilize --rolling-shutter` (docs/rolling_shutter_before_after.jpg).

    A still cannot show wobble, so each panel is a time slice: one row of the video (near the top,
    then near the bottom of the frame) taken from every frame and stacked downwards, time running
    down.  Ground that the video holds steady draws smooth lines; a frame-to-frame jitter draws
    ragged ones.  The input is ragged everywhere; `--rolling-shutter off` (one warp per frame) takes
    out what the whole frame shares but leaves each row's own vibration; `auto` (the default) smooths both.

        python -m benchmarks figures rolling-shutter [--map PHOTO] [--out docs/rolling_shutter_before_after.jpg]

    It paints a grid of straight lines on the map (the Zoo orthophoto of ../shared/data when there,
    else a procedural map) and runs, in a temporary folder:
        mosaic simulate grid.png -p paper -n 90 --size 960x540 --seed 3 --rolling-shutter 0.9 --vibration 8,5 -o rs.mp4
        mosaic stabilize rs.mp4 off.mp4 --rolling-shutter off
        mosaic stabilize rs.mp4 auto.mp4
    """
    parser = make_parser(SUITE, 'rolling-shutter', rolling_shutter_command.__doc__)
    parser.add_argument("--map", type=Path, default=DEFAULT_MAP if DEFAULT_MAP.is_file() else None)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "rolling_shutter_before_after.jpg")
    args = parser.parse_args(argv)
    mosaic = [sys.executable, "-m", "mosaic_cli"]
    with tempfile.TemporaryDirectory() as work:
        grid, rs, off, auto = (Path(work) / name for name in ("grid.png", "rs.mp4", "off.mp4", "auto.mp4"))
        _grid_map(args.map, grid)
        subprocess.run([*mosaic, "simulate", str(grid), "-p", "paper", "-n", "90", "--size", "960x540", "--seed", "3",
                        "--rolling-shutter", "0.9", "--vibration", "8,5", "-o", str(rs), "-q"], check=True)
        subprocess.run([*mosaic, "stabilize", str(rs), str(off), "--rolling-shutter", "off", "-q"], check=True)
        subprocess.run([*mosaic, "stabilize", str(rs), str(auto), "-q"], check=True)
        columns = [_slices(rs, "input"), _slices(off, "--rolling-shutter off"), _slices(auto, "default (auto)")]
    gap = np.full((columns[0].shape[0], 8, 3), 255, np.uint8)
    figure = np.hstack([columns[0], gap, columns[1], gap, columns[2]])
    figure = cv2.resize(figure, (1200, round(1200 * figure.shape[0] / figure.shape[1])), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(args.out), figure, [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(args.out)


# -- python -m benchmarks figures stabilize --------------------------------------------------------

FIRST, COUNT, PANEL = 40, 8, (480, 270)


def _frames(path: Path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            return frames
        frames.append(frame)


def _panel(frames: list[np.ndarray], label: str) -> np.ndarray:
    mean = np.mean([f.astype(np.float32) for f in frames[FIRST : FIRST + COUNT]], axis=0).astype(np.uint8)
    panel = cv2.resize(mean, PANEL, interpolation=cv2.INTER_AREA)
    cv2.rectangle(panel, (0, 0), (PANEL[0], 26), (0, 0, 0), -1)
    cv2.putText(panel, label, (8, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
    return panel


def stabilize_command(argv: list[str] | None = None) -> int | None:
    """The README's before/after still of `mosaic stabilize` (docs/stabilize_before_after.jpg).

    A still cannot show shake, so each panel overlays (averages) the same 8 consecutive frames:
    the shaky input comes out doubled and blurred, the stabilised output sharp.

        python -m benchmarks figures stabilize [--out docs/stabilize_before_after.jpg]

    It runs, in a temporary folder:
        mosaic simulate -p shaky -n 90 --size 960x540 --seed 3 -o shaky.mp4
        mosaic stabilize shaky.mp4 stable.mp4
    """
    parser = make_parser(SUITE, 'stabilize', stabilize_command.__doc__)
    parser.add_argument("--out", type=Path, default=Path("docs/stabilize_before_after.jpg"))
    args = parser.parse_args(argv)
    mosaic = [sys.executable, "-m", "mosaic_cli"]
    with tempfile.TemporaryDirectory() as work:
        shaky, stable = Path(work) / "shaky.mp4", Path(work) / "stable.mp4"
        subprocess.run([*mosaic, "simulate", "-p", "shaky", "-n", "90", "--size", "960x540", "--seed", "3", "-o", str(shaky), "-q"], check=True)
        subprocess.run([*mosaic, "stabilize", str(shaky), str(stable), "-q"], check=True)
        before = _panel(_frames(shaky), f"input: {COUNT} frames overlaid")
        after = _panel(_frames(stable), "mosaic stabilize: the same frames")
    gap = np.full((PANEL[1], 6, 3), 255, np.uint8)
    cv2.imwrite(str(args.out), np.hstack([before, gap, after]), [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(args.out)


# -- python -m benchmarks figures stitch, stitch-photos ---------------------------------------------

# The stitch guide's figure shows its source region, so it flies over a CC0 photo (ODM's Caliterra
# set; this one is not among the training images).
FIGURE_MAP = SHARED_DATA / "aerial_sequences" / "odm_caliterra" / "IMG_9355.jpg"
DEFAULT_WORKDIR = ROOT / ".dev" / "bench_stitch"  # python -m benchmarks stitch's, where the flight may be cached


def stitch_command(argv: list[str] | None = None) -> int | None:
    """The stitch guide's picture: a survey flight's panorama (docs/stitch_pano.jpg) beside the ground it
    shows, cut from the image flown over (docs/stitch_source.jpg).

        python -m benchmarks figures stitch [--frames 900 --seeds 1 --figure-map IMAGE --figure-width 1400]

    The flight is a ``mosaic simulate -p survey`` lawnmower at 1280x720 over a CC0 photo (ODM's
    Caliterra set; one not among the training images), cached in --workdir (that of
    ``python -m benchmarks stitch``), stitched with ``-e orb``.
    """
    parser = make_parser(SUITE, "stitch", stitch_command.__doc__)
    parser.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR)
    parser.add_argument("--frames", type=int, default=900, help="frames of the survey flight")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1], help="the flight's seed (the first)")
    parser.add_argument("--figure-width", type=int, default=1400)
    parser.add_argument("--figure-map", type=Path, default=FIGURE_MAP, help="the image the flight flies over")
    args = parser.parse_args(argv)
    from benchmarks.stitch import survey_flight
    from mosaic_cli.estimators import make_estimator
    from mosaic_cli.geometry import frame_corners, project
    from mosaic_cli.simulate import load_ground_truth, load_map
    from mosaic_cli.stitch import stitch

    args.workdir.mkdir(parents=True, exist_ok=True)
    video = survey_flight(args.workdir, args.frames, (1280, 720), args.seeds[0], args.figure_map)
    gt = load_ground_truth(video.with_suffix(".gt.json"))
    out = args.workdir / "figure.png"
    result = stitch(video, out, make_estimator("orb"), transforms=out.with_suffix(".json"), show_progress=False)
    docs = ROOT / "docs"
    docs.mkdir(exist_ok=True)
    pano = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    # Transparent areas shown white, as on a page.
    alpha = pano[..., 3:4].astype(np.float32) / 255.0
    flat = (pano[..., :3] * alpha + 255 * (1 - alpha)).astype(np.uint8)
    _save_jpeg(docs / "stitch_pano.jpg", flat, args.figure_width)
    # The same ground cut from the orthophoto: the map region under the used frames.
    ground = load_map(args.figure_map if args.figure_map.exists() else None, seed=args.seeds[0])
    corners = np.concatenate([project(np.linalg.inv(gt.map_to_frame[i]), frame_corners(*gt.size)) for i, _ in result.transforms])
    (x0, y0), (x1, y1) = np.floor(corners.min(axis=0)).astype(int), np.ceil(corners.max(axis=0)).astype(int)
    crop = ground[max(0, y0): y1, max(0, x0): x1]
    _save_jpeg(docs / "stitch_source.jpg", cv2.cvtColor(crop, cv2.COLOR_RGB2BGR), args.figure_width)
    print(f"figure: docs/stitch_pano.jpg ({result.canvas_size[0]}x{result.canvas_size[1]} panorama of {result.frames} frames, "
          f"{len(result.transforms)} keyframes), docs/stitch_source.jpg (orthophoto region {x1 - x0}x{y1 - y0}); "
          f"reproduce: python -m benchmarks figures stitch --frames {args.frames} --seeds {args.seeds[0]} --figure-map {args.figure_map}")
    return 0


def stitch_photos_command(argv: list[str] | None = None) -> int | None:
    """The README's first picture (docs/stitch_photos.jpg): a real survey, ODM's Caliterra photos
    (CC0), stitched by the command a user runs, transparent areas shown white.

        python -m benchmarks figures stitch-photos [--figure-width 1400]
    """
    parser = make_parser(SUITE, "stitch-photos", stitch_photos_command.__doc__)
    parser.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR)
    parser.add_argument("--figure-width", type=int, default=1400)
    args = parser.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    folder = SHARED_DATA / "aerial_sequences" / "odm_caliterra"
    out = args.workdir / "caliterra.png"
    subprocess.run([sys.executable, "-m", "mosaic_cli", "stitch", str(folder), "-o", str(out), "-q"], check=True)
    pano = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    alpha = pano[..., 3:4].astype(np.float32) / 255.0
    flat = (pano[..., :3] * alpha + 255 * (1 - alpha)).astype(np.uint8)
    _save_jpeg(ROOT / "docs" / "stitch_photos.jpg", flat, args.figure_width)
    print(f"figure: docs/stitch_photos.jpg ({pano.shape[1]}x{pano.shape[0]} panorama of the {len(list(folder.glob('*.jpg')))} "
          f"photos of {folder.name}); reproduce: python -m benchmarks figures stitch-photos --figure-width {args.figure_width}")
    return 0


def _save_jpeg(path: Path, bgr: np.ndarray, width: int) -> None:
    if bgr.shape[1] > width:
        bgr = cv2.resize(bgr, (width, round(bgr.shape[0] * width / bgr.shape[1])), interpolation=cv2.INTER_AREA)
    for quality in (88, 80, 70, 60):
        ok, data = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if ok and len(data) < 900_000:
            break
    path.write_bytes(data.tobytes())


COMMANDS = {
    "lens": lens_command,
    "rolling-shutter": rolling_shutter_command,
    "stabilize": stabilize_command,
    "stitch": stitch_command,
    "stitch-photos": stitch_photos_command,
}


def main(argv: list[str]) -> int:
    return run_commands(SUITE, __doc__, COMMANDS, argv)
