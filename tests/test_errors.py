"""Every way a user can get ``mosaic track`` wrong: one line on stderr, exit 2 (bad input) or 1,
no traceback unless --debug, and no output file (nor temporary file) left behind."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import assert_one_line_error, cli_exit, ffmpeg, run_cli, write_clip
from mosaic_cli.cli import main


@pytest.fixture
def workdir(tmp_path):
    """A folder for inputs and a separate, initially empty, folder for outputs."""
    (tmp_path / "in").mkdir()
    (tmp_path / "out").mkdir()
    return tmp_path


def outputs(workdir):
    return sorted(p.name for p in (workdir / "out").iterdir())


def good_clip(path, n=20):
    ffmpeg("-f", "lavfi", "-i", "testsrc2=size=320x180:rate=30", "-frames:v", str(n), "-c:v", "libx264",
           "-pix_fmt", "yuv420p", "-movflags", "+faststart", str(path))
    return path


def make_bad_input(kind, folder):
    path = folder / f"{kind}.mp4"
    if kind == "missing":
        return path, "no such file"
    if kind == "empty":
        path.write_bytes(b"")
        return path, "empty"
    if kind == "text":
        path.write_text("this is not a video\n" * 50)
        return path, "not a video"
    if kind == "random bytes":
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 50_000, dtype=np.uint8).tobytes())
        return path, "not a video"
    if kind == "audio only":
        path = folder / "audio.m4a"
        ffmpeg("-f", "lavfi", "-i", "sine=duration=1", str(path))
        return path, "not a video"
    if kind in ("truncated", "truncated header"):
        data = good_clip(folder / "whole.mp4", n=60).read_bytes()
        path.write_bytes(data[: len(data) // 2] if kind == "truncated" else data[:3000])
        return path, "truncated" if kind == "truncated" else "not a video"
    if kind == "truncated mkv":
        whole = folder / "whole.mkv"
        ffmpeg("-i", str(good_clip(folder / "whole.mp4", n=60)), "-c", "copy", str(whole))
        path = folder / "cut.mkv"
        path.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
        return path, "truncated"
    if kind == "folder without images":
        path = folder / "frames"
        path.mkdir()
        (path / "readme.txt").write_text("x")
        return path, "no images"
    if kind == "folder of broken images":
        path = folder / "frames"
        path.mkdir()
        (path / "f_1.png").write_text("not really a png")
        (path / "f_2.png").write_text("not really a png")
        return path, "not an image"
    raise AssertionError(kind)


@pytest.mark.slow
@pytest.mark.parametrize("kind", [
    "missing", "empty", "text", "random bytes", "audio only", "truncated", "truncated header", "truncated mkv",
    "folder without images", "folder of broken images",
])
def test_bad_video_is_one_line_exit_2_no_output(capsys, workdir, kind):
    video, message = make_bad_input(kind, workdir / "in")
    out = workdir / "out" / "t.json"
    # A truncated video is refused under --strict (without it the run goes on with a warning:
    # tests/test_truncated.py).
    strict = ["--strict"] if kind in ("truncated", "truncated mkv") else []
    code, err = run_cli(capsys, "track", video, "-o", out, "-q", *strict)
    assert_one_line_error(code, err, message, video.name)
    assert outputs(workdir) == []


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return good_clip(tmp_path_factory.mktemp("ok") / "ok.mp4")


@pytest.mark.parametrize("args, message", [
    (["--work-width", "8"], "work-width"),
    (["--work-width", "100000"], "work-width"),
    (["--estimator", "sift"], "unknown estimator"),
    (["--max-frames", "1"], "max-frames"),
])
def test_bad_option_values(capsys, workdir, clip, args, message):
    code, err = run_cli(capsys, "track", clip, "-o", workdir / "out" / "t.json", "-q", *args)
    assert_one_line_error(code, err, message)
    assert outputs(workdir) == []


@pytest.mark.parametrize("args, fragments", [
    (["track", "{clip}", "-o", "{out}", "--work-width", "wide"], ["--work-width", "mosaic track --help"]),
    (["track"], ["missing argument", "mosaic track --help"]),
    (["track", "{clip}", "-o", "{out}", "--no-such-option"], ["--no-such-option"]),
    (["no-such-command"], ["no-such-command", "mosaic --help"]),
    (["simulate", "-o", "{out}", "--seed", "-1"], ["--seed"]),
    (["stabilize", "{clip}", "{out}.mp4", "-e", "orb", "--radius", "0"], ["--radius"]),
])
def test_usage_errors_are_one_line_too(capsys, workdir, clip, args, fragments):
    """Click's own errors (a value of the wrong type, a missing argument, an unknown option or
    command) keep the one-line form, and say where the help is."""
    out = workdir / "out" / "t.json"
    code, err = run_cli(capsys, *(a.format(clip=clip, out=out) for a in args))
    assert_one_line_error(code, err, *fragments)
    assert outputs(workdir) == []


def test_output_on_a_file_system_that_takes_no_files(capsys, clip):
    """/proc passes the permission check (as root) but cannot hold a file: refused before any work."""
    if not os.path.isdir("/proc/self"):
        pytest.skip("no /proc here")
    code, err = run_cli(capsys, "track", clip, "-o", "/proc/t.json", "-q")
    assert_one_line_error(code, err, "/proc", "not writable")


@pytest.mark.slow
@pytest.mark.parametrize("args, fragments", [
    (["simulate", "-o", "{out}/odd.mp4", "-n", "3", "--size", "321x181"], ["even", "321x181"]),
    (["eval", "{pred}", "--gt", "{folder}"], ["a folder", "ground-truth"]),
    (["track", "{clip}", "-o", "{out}/t.json", "--weights", "{folder}"], ["a folder", "weights"]),
    (["track", "{clip}", "-o", "{out}/t.json", "-e", "orb", "--device", "tpu"], ["--device", "tpu"]),
    (["bench", "--video", "{clip}", "-e", "identity", "--json", "{out}/report.txt"], ["--json", ".json"]),
    (["train", "{folder}", "-o", "{out}/run", "--steps", "1"], ["no usable clips", "not a video"]),
])
def test_more_bad_input_across_commands(capsys, workdir, clip, args, fragments):
    """Each names what is wrong in one line, and writes nothing: a simulated flight whose video
    would be padded away from its ground truth, a folder where a file belongs, a device that
    does not exist for any estimator, a report without its extension, clips that are all unusable."""
    folder = workdir / "in" / "folder"
    folder.mkdir()
    (folder / "notes.mp4").write_text("not a video\n" * 10)
    pred = workdir / "in" / "track.npy"
    np.save(pred, np.repeat(np.eye(3)[None], 4, axis=0))
    code, err = run_cli(capsys, *(a.format(clip=clip, out=workdir / "out", folder=folder, pred=pred) for a in args))
    assert_one_line_error(code, err, *fragments)
    assert outputs(workdir) == []


@pytest.mark.slow
@pytest.mark.parametrize("signum, status, message", [
    (signal.SIGINT, 130, "interrupted"),
    (signal.SIGTERM, 143, "terminated"),
])
@pytest.mark.parametrize("min_bytes", [0, 1], ids=["as the encoder starts", "while encoding"])
def test_a_signal_midway_is_one_line_and_leaves_no_file(workdir, signum, status, message, min_bytes):
    """Ctrl-C (to the whole process group, as a terminal sends it) or SIGTERM while the output is
    being written: one line, 128 + the signal, and neither the output nor its temporary file,
    whether it lands as the encoder starts (the temporary file just made) or later."""
    out = workdir / "out" / "f.mp4"
    run = subprocess.Popen([sys.executable, "-m", "mosaic_cli", "simulate", "-o", str(out), "-n", "3000", "--size", "320x180",
                            "--preset", "ultrafast", "-q"], stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while not any(p.name.endswith(".part.mp4") and p.stat().st_size >= min_bytes for p in (workdir / "out").iterdir()):
            assert run.poll() is None and time.monotonic() < deadline, "the run ended before writing began"
            time.sleep(0.05)
        os.killpg(run.pid, signum)
        err = run.communicate(timeout=60)[1]
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
    assert run.returncode == status, err
    assert err.strip() == f"mosaic: error: {message}"
    assert outputs(workdir) == []


@pytest.mark.parametrize("target, message", [
    ("missing/t.json", "does not exist"),
    ("a_file/t.json", "a_file"),
    ("subdir", "directory"),
    ("t.txt", ".json or .npy"),
])
def test_unwritable_output(capsys, workdir, clip, target, message):
    (workdir / "out" / "a_file").write_text("")
    (workdir / "out" / "subdir").mkdir()
    before = outputs(workdir)
    code, err = run_cli(capsys, "track", clip, "-o", workdir / "out" / target, "-q")
    assert_one_line_error(code, err, message)
    assert outputs(workdir) == before


def test_failure_midway_leaves_no_file_and_debug_shows_the_traceback(capsys, workdir, clip, monkeypatch):
    from mosaic_cli.estimators.orb import OrbEstimator

    def broken(self, prev, cur):
        raise RuntimeError("estimator exploded")

    monkeypatch.setattr(OrbEstimator, "_estimate", broken)
    out = workdir / "out" / "t.json"
    code, err = run_cli(capsys, "track", clip, "-o", out, "-e", "orb", "-q")
    assert_one_line_error(code, err, "estimator exploded", "--debug", status=1)
    assert outputs(workdir) == []
    with pytest.raises(RuntimeError, match="exploded"):
        main(["--debug", "track", str(clip), "-o", str(out), "-e", "orb", "-q"])
    assert outputs(workdir) == []


@pytest.mark.slow
def test_console_script_prints_no_traceback(workdir):
    """The installed entry point, in a fresh process, as a user runs it."""
    missing = workdir / "in" / "nothing.mp4"
    run = subprocess.run([sys.executable, "-m", "mosaic_cli", "track", str(missing), "-o", str(workdir / "out" / "t.json")],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2
    assert run.stderr.strip() == f"mosaic: error: {missing}: no such file or folder"
    run = subprocess.run([sys.executable, "-m", "mosaic_cli", "--debug", "track", str(missing), "-o", str(workdir / "out" / "t.json")],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode != 0 and "Traceback" in run.stderr


# ---------------------------------------------------------------- degenerate but valid


@pytest.mark.slow
def test_one_frame_video_gives_an_empty_track(capsys, workdir):
    video = good_clip(workdir / "in" / "one.mp4", n=1)
    out = workdir / "out" / "t.json"
    code, _ = run_cli(capsys, "track", video, "-o", out, "-q")
    data = json.loads(out.read_text())
    assert code == 0 and data["frames"] == 1 and data["pairwise"] == [] and data["confidence"] == []


@pytest.mark.slow
def test_all_black_video_gives_identity_with_zero_confidence(capsys, workdir):
    video = write_clip(workdir / "in" / "black.mp4", [np.zeros((180, 320, 3), np.uint8)] * 10)
    out = workdir / "out" / "t.json"
    code, _ = run_cli(capsys, "track", video, "-o", out, "-q")
    data = json.loads(out.read_text())
    assert code == 0 and data["frames"] == 10
    assert np.array_equal(np.array(data["pairwise"]), np.broadcast_to(np.eye(3), (9, 3, 3)))
    assert data["confidence"] == [0.0] * 9


@pytest.mark.parametrize("command", ["track", "stitch", "stabilize"])
@pytest.mark.parametrize("width", ["16", "100000"])
def test_work_width_has_one_rule_for_every_command(capsys, tiny_clip, tmp_path, command, width):
    """--work-width is bounded the same way wherever an estimator is built (stabilize once
    upsampled every frame to 100000 px)."""
    out = {"track": ["-o", tmp_path / "t.json"], "stitch": ["-o", tmp_path / "p.png"], "stabilize": [tmp_path / "s.mp4"]}[command]
    code, err = run_cli(capsys, command, tiny_clip, *out, "-e", "orb", "--work-width", width, "-q")
    assert_one_line_error(code, err, "--work-width must be in 32..4096")
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("suffix,fragments", [(".jpg", ("b.jpg", "damaged image", "truncated")), (".png", ("b.png", "damaged image")),
                                              (".tif", ("b.tif", "not an image"))])
def test_a_photo_cut_short_is_refused_in_one_line(capfd, tmp_path, suffix, fragments):
    """A copy cut short (two thirds of its bytes): OpenCV decodes such a JPEG with its missing rows
    grey and says so only through libjpeg's line on stderr, so the photo went into the panorama;
    a PNG or TIFF left libpng's or libtiff's lines beside mosaic's.  Each is now one line naming
    the photo (Pillow reads its bytes before OpenCV decodes it); stderr is captured at the file
    descriptor, where those C libraries write."""
    import cv2

    rng = np.random.default_rng(5)
    ground = cv2.GaussianBlur(rng.integers(0, 255, (480, 900, 3), dtype=np.uint8), (0, 0), 3)
    folder = tmp_path / "photos"
    folder.mkdir()
    for k, name in enumerate("abc"):
        path = folder / f"{name}{suffix}"
        cv2.imwrite(str(path), ground[:, 200 * k: 200 * k + 500])
    damaged = folder / f"b{suffix}"
    data = damaged.read_bytes()
    damaged.write_bytes(data[: len(data) * 2 // 3])
    assert cv2.imread(str(damaged)) is not None or suffix != ".jpg"  # what OpenCV alone makes of the JPEG
    capfd.readouterr()
    code = cli_exit(["stitch", folder, "-o", tmp_path / "pano.png", "-q"])
    assert_one_line_error(code, capfd.readouterr().err, *fragments)
    assert not (tmp_path / "pano.png").exists()


def test_a_map_image_cut_short_is_refused_in_one_line(capfd, tmp_path):
    """``mosaic simulate MAP``: a map JPEG cut short was flown over with its missing rows grey."""
    import cv2

    rng = np.random.default_rng(6)
    path = tmp_path / "map.jpg"
    cv2.imwrite(str(path), cv2.GaussianBlur(rng.integers(0, 255, (900, 1200, 3), dtype=np.uint8), (0, 0), 3))
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    capfd.readouterr()
    code = cli_exit(["simulate", path, "-n", "5", "-o", tmp_path / "flight.mp4"])
    assert_one_line_error(code, capfd.readouterr().err, "map.jpg", "damaged image")
    assert not (tmp_path / "flight.mp4").exists()
