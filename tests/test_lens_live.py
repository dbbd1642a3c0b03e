"""``--lens FILE`` on live inputs (issue 41): each frame undistorted as it arrives, as a file's
are as they are decoded; ``--lens auto`` refused there.  Live sources over the loopback interface
or standard input only, every run bounded in time."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading

import cv2
import numpy as np
import pytest

from conftest import assert_one_line_error, cli_exit, run_cli
from mosaic_cli.geometry.lens import radial_lens, undistorted_camera
from mosaic_cli.geometry.lens_files import read_lens

SIZE = (320, 180)
RUN_LIMIT = 300  # seconds any one command may take


@pytest.fixture(scope="module")
def wide(tmp_path_factory):
    """A short survey flight through a strong barrel lens (k1 -0.30 at the bench's focal length),
    its truth a lens file."""
    from mosaic_cli.simulate import SimulateOptions, parse_lens, simulate_flight

    out = tmp_path_factory.mktemp("lens_live") / "wide.mp4"
    simulate_flight(out, None, SimulateOptions(profile="survey", frames=30, size=SIZE, seed=3, lens=parse_lens(f"-0.30,0.0225,f={1050 * SIZE[0] / 1280}", SIZE)),
                    show_progress=False)
    return out


def opencv_undistorted(frame: np.ndarray, lens) -> np.ndarray:
    """The frame undistorted by OpenCV's own maps (the camera mosaic undistorts to)."""
    h, w = frame.shape[:2]
    at = lens.at((w, h))
    mx, my = cv2.initUndistortRectifyMap(at.K, at.D, None, undistorted_camera(at), (w, h), cv2.CV_32FC1)
    return cv2.remap(frame, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


@pytest.mark.parametrize("pixels", ["gray", "rgb", "yuv420p"])
def test_live_frames_are_undistorted_as_a_file_s(wide, pixels):
    """A live reader's frames through ``--lens FILE`` are the file reader's (the same pixels an
    offline run sees: RGB and yuv420p plane by plane before any conversion), and the gray ones
    are OpenCV's undistortion of the raw frames."""
    from mosaic_cli.estimators.lens import choose_lens
    from mosaic_cli.live.source import LiveStream
    from mosaic_cli.video import open_video

    gt = wide.with_suffix(".gt.json")
    kind = {"gray": {"gray": True}, "rgb": {"lazy_rgb": True}, "yuv420p": {"yuv420p": True}}[pixels]
    choice = choose_lens(str(gt), wide, live=True)
    assert choice.source == "file"
    with LiveStream(str(wide), pixels, live=False, quiet=True, lens=choice.image_filter) as live:
        received = [np.asarray(f) for f in live]
    with open_video(wide, **kind, lens=choose_lens(str(gt), wide).image_filter) as stream:
        decoded = [np.asarray(f) for f in stream]
    with open_video(wide, **kind) as stream:
        raw = [np.asarray(f) for f in stream]
    assert len(received) == len(decoded) == 30
    assert all(np.array_equal(a, b) for a, b in zip(received, decoded))
    assert not np.array_equal(received[0], raw[0])
    if pixels == "gray":
        lens = read_lens(gt)
        assert all(np.array_equal(a, opencv_undistorted(r, lens)) for a, r in zip(received, raw))


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_track_over_tcp_with_the_true_lens_file_matches_the_pinhole_truth(wide, tmp_path, capsys):
    """A live track (TCP on the loopback, served in real time) with the true lens file: its pairs
    are the undistorted frames' (read against the simulator's truth as test_lens reads a file's),
    well under the error of the frames taken as they are.  (In this process: test_live runs the
    live commands as processes.)"""
    from test_lens import pair_errors
    from test_live import send, wait_until_bound

    gt = wide.with_suffix(".gt.json")
    port = free_port()
    out = tmp_path / "live.json"
    sent = []
    sender = threading.Thread(target=lambda: (wait_until_bound(port, udp=False), sent.append(send(wide, f"tcp://127.0.0.1:{port}"))),
                              daemon=True)
    sender.start()
    code, err = run_cli(capsys, "track", f"tcp://127.0.0.1:{port}?listen=1", "-o", out, "-e", "orb", "--lens", gt)
    sender.join(RUN_LIMIT)
    assert code == 0 and sent and sent[0].returncode == 0, err
    assert "lens: pinhole from the file" in err
    doc = json.loads(out.read_text())
    assert doc["meta"]["lens"]["applied"] and len(doc["pairwise"]) == 29
    assert cli_exit(["track", wide, "-o", tmp_path / "none.json", "-e", "orb", "-q", "--no-overlay-detect"]) == 0
    given, none = np.median(pair_errors(out, gt)), np.median(pair_errors(tmp_path / "none.json", gt))
    assert given < 0.7 * none, (given, none)


@pytest.mark.slow
def test_stabilize_from_standard_input_writes_the_undistorted_view(wide, tmp_path):
    """``stabilize - OUT --lens FILE`` (one pass): each output frame is its warp (--warps) applied
    to the input frame undistorted by OpenCV, not to the frame as the lens saw it."""
    gt = wide.with_suffix(".gt.json")
    out, warps = tmp_path / "live.mp4", tmp_path / "warps.json"
    with open(wide, "rb") as stdin:
        done = subprocess.run([sys.executable, "-m", "mosaic_cli", "stabilize", "-", str(out), "-e", "orb", "--lens", str(gt),
                               "--warps", str(warps), "--crf", "0"], stdin=stdin, capture_output=True, timeout=RUN_LIMIT)
    assert done.returncode == 0, done.stderr.decode()
    assert "lens: pinhole from the file" in done.stderr.decode()
    from mosaic_cli.video import open_video

    with open_video(out, gray=True) as stream:
        written = [np.asarray(f, dtype=np.float64) for f in stream]
    with open_video(wide, gray=True) as stream:
        raw = [np.asarray(f) for f in stream]
    W = np.array(json.loads(warps.read_text())["warps"])
    assert len(written) == len(raw) == len(W) == 30
    lens = read_lens(gt)
    inner = (slice(20, -20), slice(30, -30))
    through, without = [], []
    for t in range(0, 30, 5):
        for frame, errors in ((opencv_undistorted(raw[t], lens), through), (raw[t], without)):
            expect = cv2.warpPerspective(frame, W[t], SIZE, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            errors.append(np.abs(expect.astype(np.float64) - written[t])[inner].mean())
    assert np.mean(through) < 2.0 and np.mean(without) > 2 * np.mean(through), (through, without)


def test_live_lens_refusals_are_one_clear_line(wide, tmp_path, capsys):
    port = free_port()
    code, err = run_cli(capsys, "track", f"udp://127.0.0.1:{port}", "-o", tmp_path / "t.json", "-e", "orb", "--lens", "auto")
    assert_one_line_error(code, err, "--lens auto", "lens FILE")
    code, err = run_cli(capsys, "stitch", f"udp://127.0.0.1:{port}", "-o", tmp_path / "p.png", "-e", "orb", "--lens", "auto")
    assert_one_line_error(code, err, "--lens auto", "lens FILE")
    code, err = run_cli(capsys, "stabilize", f"udp://127.0.0.1:{port}", tmp_path / "s.mp4", "-e", "orb", "--lens", "auto")
    assert_one_line_error(code, err, "--lens auto", "lens FILE")
    code, err = run_cli(capsys, "stabilize", wide, tmp_path / "s.mp4", "-e", "orb", "--latency", "1", "--keep-lens",
                        "--lens", wide.with_suffix(".gt.json"))
    assert_one_line_error(code, err, "--keep-lens", "--latency")
    # a lens of another aspect than the stream's: said once the stream's size is known
    other = tmp_path / "43.json"
    other.write_text(json.dumps(radial_lens((640, 480), 500, -0.1).to_json()))
    with open(wide, "rb") as stdin:
        done = subprocess.run([sys.executable, "-m", "mosaic_cli", "track", "-", "-o", "-", "-e", "orb", "--lens", str(other)],
                              stdin=stdin, capture_output=True, timeout=RUN_LIMIT)
    assert_one_line_error(done.returncode, done.stderr.decode(), "--lens", "aspect")


@pytest.mark.slow
def test_stitch_live_from_standard_input_with_a_lens_equals_the_offline_stitch(wide, tmp_path):
    """The frames a live stitch reads through ``--lens FILE`` are the offline stitch's: the same
    transforms and the same panorama."""
    gt = wide.with_suffix(".gt.json")
    common = ["-e", "orb", "-q", "--lens", str(gt), "--no-overlay-detect"]
    with open(wide, "rb") as stdin:
        live = subprocess.run([sys.executable, "-m", "mosaic_cli", "stitch", "-", "-o", str(tmp_path / "live.png"),
                               "--transforms", str(tmp_path / "live.json"), *common], stdin=stdin, capture_output=True,
                              timeout=RUN_LIMIT)
    assert live.returncode == 0, live.stderr.decode()
    assert cli_exit(["stitch", wide, "-o", tmp_path / "off.png", "--transforms", tmp_path / "off.json", "--rolling-shutter", "off",
                     *common]) == 0
    assert json.loads((tmp_path / "live.json").read_text()) == json.loads((tmp_path / "off.json").read_text())
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "live.png"), -1), cv2.imread(str(tmp_path / "off.png"), -1))
