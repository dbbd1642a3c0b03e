"""Issue 40: translucent, soft-edged overlays (a white diamond, a semi-transparent OSD box) at
crf 28 leave nothing in the panorama; ``--fill-holes`` closes interior holes, not the border.
Checked against the simulator's map and exact homographies."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from mosaic_cli.overlay import frame_mask
from mosaic_cli.simulate import OverlaySpec, load_ground_truth, overlay_mask_path, plan_flight, procedural_map, write_flight
from mosaic_cli.stitch.compose import fill_holes
from conftest import cli_exit

def run_cli(capsys, *args) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``mosaic ARGS`` run in this process."""
    code = cli_exit([str(a) for a in args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


SIZE, FRAMES, CRF, MAP = (640, 360), 40, 28, (1024, 1024)


@pytest.fixture(scope="module")
def flights(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("watermarks")
    ground = procedural_map(MAP, seed=3)
    cv2.imwrite(str(folder / "map.png"), cv2.cvtColor(ground, cv2.COLOR_RGB2BGR))
    plan = plan_flight(MAP, "fast", frames=FRAMES, size=SIZE, seed=3)
    out = {"map": folder / "map.png"}
    for name, spec in (("plain", None), ("burned", OverlaySpec.parse("watermark:0.6,osd"))):
        out[name] = folder / f"{name}.mp4"
        write_flight(out[name], ground, plan, crf=CRF, preset="veryfast", show_progress=False, overlays=spec)
    return out


def footprint(video: Path) -> np.ndarray:
    return cv2.imread(str(overlay_mask_path(video)), cv2.IMREAD_GRAYSCALE) == 0


def test_the_translucent_overlays_footprint_is_recorded_and_soft():
    from mosaic_cli.simulate.overlay import OverlayBurner

    burner = OverlayBurner(OverlaySpec.parse("watermark:0.5,osd:0.8"), SIZE, 30.0)
    alpha = burner.alpha()
    kinds = burner.kinds()
    assert set(kinds) == {"watermark", "osd"} and all(k.any() for k in kinds.values())
    inside = alpha[kinds["watermark"]]
    assert 0.5 <= np.median(inside[inside > 0.3]) <= 1.0  # translucent inside
    assert np.count_nonzero((inside > 0) & (inside < 0.3)) > 50  # a soft rim, not a hard edge
    assert np.array_equal(burner.drawn, kinds["watermark"] | kinds["osd"])


def test_the_mask_covers_the_whole_footprint_and_nothing_on_a_clean_flight(flights):
    masked = frame_mask(flights["burned"]).use == 0
    foot = footprint(flights["burned"])
    assert np.count_nonzero(foot & ~masked) == 0
    assert frame_mask(flights["plain"]).use is None


def panorama_error(pano: Path, transforms: Path, video: Path, ground: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) per-pixel error (max over channels) of the panorama against the map drawn
    through the reference keyframe's placement, and the covered pixels."""
    image = cv2.cvtColor(cv2.imread(str(pano), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA)
    doc = json.loads(transforms.read_text())
    gt = load_ground_truth(video)
    truth = []
    for f in doc["frames"]:
        to_canvas = np.array(f["H"]) @ gt.map_to_frame[f["index"]]
        truth.append(cv2.warpPerspective(ground, to_canvas, (image.shape[1], image.shape[0]), flags=cv2.INTER_LINEAR))
    # Against each keyframe's placement of the map, the nearest (registration drift is not the overlay's).
    err = np.min([np.abs(image[..., :3].astype(int) - t.astype(int)).max(axis=2) for t in truth], axis=0)
    return err, image[..., 3] > 0


def surroundings(video: Path, transforms: Path, canvas: tuple[int, int], grow: int = 12) -> np.ndarray:
    """(H, W) bool: the overlay footprint, grown by ``grow`` px, drawn through every keyframe."""
    foot = cv2.dilate(footprint(video).astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1,) * 2))
    out = np.zeros((canvas[1], canvas[0]), bool)
    for f in json.loads(transforms.read_text())["frames"]:
        out |= cv2.warpPerspective(foot, np.array(f["H"]), canvas, flags=cv2.INTER_NEAREST) > 0
    return out


@pytest.mark.slow
def test_no_panorama_pixel_near_the_overlays_departs_from_the_map_more_than_the_flights_own_noise(flights, tmp_path, capsys):
    ground = cv2.cvtColor(cv2.imread(str(flights["map"])), cv2.COLOR_BGR2RGB)
    errors = {}
    for name in ("plain", "burned"):
        pano, tr = tmp_path / f"{name}.png", tmp_path / f"{name}.json"
        code, _, err = run_cli(capsys, "stitch", flights[name], "-o", pano, "--transforms", tr, "-e", "orb", "-q")
        assert code == 0, err
        errors[name] = panorama_error(pano, tr, flights[name], ground)
    err, covered = errors["burned"]
    near = surroundings(flights["burned"], tmp_path / "burned.json", (err.shape[1], err.shape[0])) & covered
    plain_err, plain_covered = errors["plain"]
    # The flight's own noise: the same statistic, over the plain flight's panorama.
    noise = np.percentile(plain_err[plain_covered], 99.9)
    print(f"noise {noise:.1f}, near the overlays: p99.9 {np.percentile(err[near], 99.9):.1f} max {err[near].max()}, "
          f"over noise {np.count_nonzero(err[near] > noise)} of {np.count_nonzero(near)}")
    assert np.count_nonzero(err[near] > noise) <= 0.001 * np.count_nonzero(near)


def test_fill_holes_fills_interior_holes_and_leaves_the_border():
    rgba = np.zeros((60, 80, 4), np.uint8)
    rgba[5:55, 5:75, :3] = (90, 140, 60)
    rgba[5:55, 5:75, 3] = 255
    rgba[20:28, 30:40, 3] = 0
    rgba[20:28, 30:40, :3] = 0  # an interior hole: 80 px
    rgba[5:15, 5:9, 3] = 0  # touching the transparent outside: not interior
    filled = fill_holes(rgba, 0.05)
    assert filled == 80
    assert np.all(rgba[20:28, 30:40, 3] == 255) and np.abs(rgba[20:28, 30:40, :3].astype(int) - (90, 140, 60)).max() <= 2
    assert np.all(rgba[5:15, 5:9, 3] == 0) and np.all(rgba[:5, :, 3] == 0)
    # A hole larger than the share allowed stays.
    rgba[10:50, 10:70, 3] = 0
    assert fill_holes(rgba, 0.01) == 0


@pytest.mark.slow
def test_stitch_fill_holes_says_how_many_pixels_it_filled(flights, tmp_path, capfd):
    code, out, err = run_cli(capfd, "stitch", flights["burned"], "-o", tmp_path / "p.png", "-e", "orb", "--fill-holes")
    assert code == 0, err
    import re

    last = err.strip().splitlines()[-1]  # the console writes to stderr (stdout stays for data)
    assert re.fullmatch(r"--fill-holes: \d+ pixels of interior holes filled", last), last
