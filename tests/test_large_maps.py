"""Maps as large as the flight (issue 52): the panorama composed tile by tile into a staged
GeoTIFF on disk and every format written from it (stitch/raster.py), checked by independent
readers: OpenCV for PNG, JPEG and TIFF, GDAL (rasterio) for the TIFF's bands and alpha; the
canvas at the footage's own resolution by default, and any shrink said in one line."""

from __future__ import annotations

import os
import sys

import cv2
import numpy as np
import pytest

from benchmarks.maps import WRITE_UNDER_SIGNALS, write_noise_map
from mosaic_cli.errors import BadInput
from mosaic_cli.stitch.canvas import CanvasOptions, parse_distance, plan_canvas
from mosaic_cli.stitch.compose import ComposeOptions, PlacedImage, compose
from mosaic_cli.stitch.raster import staged_panorama, write_image
from tests.conftest import assert_one_line_error, run_cli, textured_image


@pytest.fixture(scope="module")
def ground() -> np.ndarray:
    return textured_image(900, 600, seed=5)


def _panorama(width: int, height: int) -> np.ndarray:
    """An RGBA panorama with texture, a transparent corner and colour everywhere else."""
    rng = np.random.default_rng(4)
    rgba = np.zeros((height, width, 4), np.uint8)
    rgba[..., :3] = cv2.resize(rng.integers(0, 256, (height // 8 + 1, width // 8 + 1, 3), dtype=np.uint8), (width, height),
                               interpolation=cv2.INTER_NEAREST)
    rgba[..., 3] = 255
    rgba[: height // 3, : width // 4] = 0  # ground nobody saw: transparent, black underneath
    return rgba


def test_every_format_holds_the_pixels_written_tile_by_tile(tmp_path):
    import rasterio
    from rasterio.enums import ColorInterp

    truth = _panorama(1300, 700)
    outputs = {"png": tmp_path / "p.png", "jpeg": tmp_path / "p.jpg", "tiff": tmp_path / "p.tif"}
    for fmt in ("png", "jpeg", "tiff"):  # the TIFF last: it is the staged file itself, renamed
        with staged_panorama(outputs[fmt], (1300, 700), keep=fmt == "tiff") as staged:
            for y in range(0, 700, 256):  # tiles, in no special order of rows
                for x in range(0, 1300, 384)[::-1]:
                    staged.write(x, y, truth[y:y + 256, x:x + 384])
            write_image(outputs[fmt], staged, fmt)
    bgra = cv2.imread(str(outputs["png"]), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(cv2.cvtColor(bgra, cv2.COLOR_BGRA2RGBA), truth)
    bgra = cv2.imread(str(outputs["tiff"]), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(cv2.cvtColor(bgra, cv2.COLOR_BGRA2RGBA), truth)
    with rasterio.open(outputs["tiff"]) as ds:  # alpha declared as alpha, tiled, compressed
        assert ds.count == 4 and ds.colorinterp[3] == ColorInterp.alpha and ds.profile["tiled"] and ds.compression is not None
    rgb = cv2.cvtColor(cv2.imread(str(outputs["jpeg"]), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2RGB).astype(int)
    # lossy, but no worse than OpenCV's JPEG of the same quality, and black where nothing was seen
    _, encoded = cv2.imencode(".jpg", cv2.cvtColor(truth[..., :3], cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 92])
    opencv = cv2.cvtColor(cv2.imdecode(encoded, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB).astype(int)
    assert np.abs(rgb - truth[..., :3]).mean() < np.abs(opencv - truth[..., :3]).mean() + 1
    assert rgb[: 700 // 3 - 8, : 1300 // 4 - 8].max() < 12
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.jpg", "p.png", "p.tif"]  # no staging file left


def test_compose_into_the_staged_file_gives_the_in_memory_panorama(ground, tmp_path):
    """Small tiles, a cache too small to hold one keyframe (every tile reads the spilled pixels
    again), written through GDAL: the panorama of one tile over the whole canvas, in memory."""
    rng = np.random.default_rng(2)
    views = []
    for k in range(8):
        H = np.array([[1.0, 0.03, 30 + 170 * (k % 4) + rng.uniform(-8, 8)], [-0.03, 1.0, 25 + 190 * (k // 4)], [2e-5, 0, 1]])
        view = cv2.warpPerspective(ground, np.linalg.inv(H), (260, 220))
        views.append((np.clip(view * (0.85 + 0.3 * rng.random()), 0, 255).astype(np.uint8), H))
    canvas = (780, 460)
    whole = compose([PlacedImage(v.copy(), H) for v, H in views], canvas, ComposeOptions(tile=10**6))
    out = tmp_path / "pano.png"
    with staged_panorama(out, canvas) as staged:
        assert compose([PlacedImage(v.copy(), H) for v, H in views], canvas, ComposeOptions(tile=64, cache_megabytes=1e-6), sink=staged) is None
        write_image(out, staged, "png")
    tiled = cv2.cvtColor(cv2.imread(str(out), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA).astype(int)
    assert np.array_equal(tiled[..., 3], whole[..., 3]) and (whole[..., 3] == 255).mean() > 0.6
    diff = np.abs(tiled[..., :3] - whole[..., :3].astype(int))
    assert diff.mean() < 0.05 and diff.max() <= 2


def test_a_panorama_too_large_for_jpeg_is_one_line_and_leaves_nothing(tmp_path):
    out = tmp_path / "big.jpg"
    with staged_panorama(out, (65_501, 16)) as staged, pytest.raises(BadInput, match="JPEG holds at most 65500 pixels a side"):
        write_image(out, staged, "jpeg")
    assert list(tmp_path.iterdir()) == []


def test_the_canvas_keeps_every_pixel_unless_asked_and_says_what_shrank_it():
    frame = (400, 300)
    placements = [np.array([[1.0, 0, 350.0 * k], [0, 1, 0], [0, 0, 1]]) for k in range(30)]  # 10,550 px wide
    native = plan_canvas(placements, list(range(30)), frame, CanvasOptions())
    assert native.scale == 1.0 and native.size == native.native_size and native.size[0] >= 10_550 and native.shrunk_by is None
    capped = plan_canvas(placements, list(range(30)), frame, CanvasOptions(max_size=5000))
    assert max(capped.size) == 5000 and capped.shrunk_by == "--max-size 5000"
    # Placements in ground pixels of 2 cm: --gsd 5cm draws 2/5 of the pixels a side; 1cm cannot add any.
    coarser = plan_canvas(placements, list(range(30)), frame, CanvasOptions(gsd=0.05), gsd=0.02)
    assert coarser.scale == pytest.approx(0.4) and coarser.shrunk_by == "--gsd 5cm"
    assert plan_canvas(placements, list(range(30)), frame, CanvasOptions(gsd=0.01), gsd=0.02).scale == 1.0
    jpeg = plan_canvas(placements, list(range(30)), frame, CanvasOptions(max_size=6000), limit="JPEG's limit")
    assert jpeg.shrunk_by == "JPEG's limit"


@pytest.mark.parametrize("text,metres", [("5cm", 0.05), ("0.05m", 0.05), ("50mm", 0.05), ("0.3", 0.3), ("2 cm", 0.02)])
def test_gsd_reads_a_ground_distance(text, metres):
    assert parse_distance(text) == pytest.approx(metres)


@pytest.mark.parametrize("text", ["fast", "-5cm", "0", "nan m"])
def test_a_gsd_that_is_no_distance_is_refused(text):
    with pytest.raises(BadInput, match="--gsd"):
        parse_distance(text)


def test_gsd_without_telemetry_is_one_line_before_any_work(capsys, tmp_path, plain_160x90):
    code, err = run_cli(capsys, "stitch", plain_160x90, "-o", tmp_path / "p.png", "--gsd", "5cm", "-q", "--estimator", "orb")
    assert_one_line_error(code, err, "--gsd needs telemetry")
    assert list(tmp_path.iterdir()) == []


def test_without_gdal_the_panorama_is_held_in_memory_and_written_by_opencv(tmp_path, monkeypatch):
    """The lent GPU machine has no rasterio: a plain panorama is still written, the same pixels."""
    monkeypatch.setitem(sys.modules, "rasterio", None)
    truth = _panorama(300, 200)
    out = tmp_path / "p.png"
    with staged_panorama(out, (300, 200)) as staged:
        assert staged.path is None  # nothing staged on disk
        staged.write(0, 0, truth[:, :128])
        staged.write(128, 0, truth[:, 128:])
        write_image(out, staged, "png")
    assert np.array_equal(cv2.cvtColor(cv2.imread(str(out), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA), truth)


@pytest.fixture(scope="module")
def large_staged_map(tmp_path_factory) -> tuple:
    """A staged map of 8000 x 8000 px of noise: GDAL takes seconds to copy it on a 2-core machine."""
    path, side = tmp_path_factory.mktemp("large") / "staged.tif", 8000
    write_noise_map(path, side)
    return path, side


@pytest.mark.slow
@pytest.mark.alone
@pytest.mark.parametrize("fmt, name", [("cog", "map.tif"), ("png", "map.png")])
def test_a_signal_while_a_large_map_is_written_stops_it_at_once_and_leaves_nothing(large_staged_map, tmp_path, fmt, name):
    """GDAL copies a map in C calls of minutes at survey sizes, and Python runs a signal's
    handler only between the main thread's bytecodes: SIGTERM at a third and at two thirds of
    the write must still end the run within a second, in one line, with nothing under the
    output's folder (neither the output, nor its temporary file, nor GDAL's own beside it)."""
    import signal
    import subprocess
    import time

    staged, side = large_staged_map
    command = [sys.executable, "-c", WRITE_UNDER_SIGNALS, fmt, str(staged)]
    started = time.monotonic()
    whole = subprocess.run([*command, str(tmp_path / name), str(side)], capture_output=True, text=True, timeout=300)
    write_time = time.monotonic() - started
    assert whole.returncode == 0 and (tmp_path / name).stat().st_size > 1 << 20, whole.stderr
    for k, share in enumerate((1 / 3, 2 / 3)):
        out = tmp_path / f"out{k}"
        out.mkdir()
        run = subprocess.Popen([*command, str(out / name), str(side)], stderr=subprocess.PIPE, text=True, start_new_session=True)
        try:
            time.sleep(share * write_time)
            assert run.poll() is None, "the write ended before the signal"
            os.killpg(run.pid, signal.SIGTERM)
            signalled = time.monotonic()
            err = run.communicate(timeout=300)[1]
            took = time.monotonic() - signalled
        finally:
            if run.poll() is None:
                os.killpg(run.pid, signal.SIGKILL)
        assert run.returncode == 143 and err.strip() == "mosaic: error: terminated", err
        assert took < 1.0, f"the run went on {took:.1f} s after SIGTERM at {share:.0%} of a {write_time:.1f} s write"
        assert list(out.iterdir()) == []


def _file_size_limit(limit: int):
    """A child's files held to ``limit`` bytes, as a full disk would stop them (its writes fail
    with EFBIG instead of the process being killed by SIGXFSZ)."""
    import resource
    import signal

    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return apply


def test_a_stitch_that_cannot_keep_its_keyframes_on_disk_says_where_in_one_line(survey_320x180, tmp_path):
    """The keyframes' pixels wait in TMPDIR between the scan and the compositing: a write there
    that fails (a full disk) is one line naming the folder and TMPDIR, not numpy's byte count."""
    import subprocess

    out = tmp_path / "out"
    out.mkdir()
    run = subprocess.run([sys.executable, "-m", "mosaic_cli", "stitch", str(survey_320x180), "-o", str(out / "pano.png"), "-q"],
                         capture_output=True, text=True, preexec_fn=_file_size_limit(100_000), timeout=300,
                         env={**os.environ, "TMPDIR": str(tmp_path)})
    assert run.returncode == 1
    assert_one_line_error(run.returncode, run.stderr, str(tmp_path), "could not keep a keyframe's pixels", "TMPDIR", status=1)
    assert list(out.iterdir()) == [] and not list(tmp_path.glob("mosaic-stitch-*"))


@pytest.mark.parametrize("fmt, name", [("cog", "map.tif"), ("png", "map.png")])
def test_a_map_gdal_cannot_finish_writing_is_a_line_naming_it_and_leaves_nothing(tmp_path, fmt, name):
    """GDAL failing in the middle of a map (its files held to 1 MB, as a full disk stops them):
    a ProcessingError naming the user's output, not GDAL's own exception class; no file left
    (GDAL's overviews staged beside the COG included).  (libtiff prints lines of its own to
    stderr first, which mosaic cannot hold back.)"""
    import subprocess

    staged = tmp_path / "staged.tif"
    write_noise_map(staged, 1500)  # 9 MB of noise
    out = tmp_path / "out"
    out.mkdir()
    run = subprocess.run([sys.executable, "-c", WRITE_UNDER_SIGNALS, fmt, str(staged), str(out / name), "1500"],
                         capture_output=True, text=True, preexec_fn=_file_size_limit(1_000_000), timeout=300)
    assert run.returncode == 1, run.stderr
    assert run.stderr.strip().splitlines()[-1].startswith(f"mosaic: error: {out / name}: could not write the "), run.stderr
    assert list(out.iterdir()) == []
