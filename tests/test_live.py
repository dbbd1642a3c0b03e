"""Live inputs over the loopback interface only: the bundled ffmpeg serves a small simulated
flight in real time (-re, MPEG-TS) over UDP and TCP and through standard input, and each
command runs against it.  Every run is bounded in time (subprocess timeouts)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import FFMPEG

SIZE = (320, 180)
FRAMES = 60
RUN_LIMIT = 90  # seconds any one command may take, far above what it needs


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> tuple[Path, dict]:
    """A 2-second shaky simulated flight (with its exact ground truth)."""
    folder = tmp_path_factory.mktemp("live")
    video = folder / "flight.mp4"
    subprocess.run([sys.executable, "-m", "mosaic_cli", "simulate", "-o", str(video), "-p", "shaky", "-n", str(FRAMES),
                    "--size", f"{SIZE[0]}x{SIZE[1]}", "--preset", "veryfast", "-q"], check=True, timeout=RUN_LIMIT)
    return video, json.loads(video.with_suffix(".gt.json").read_text())


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until_bound(port: int, udp: bool, limit: float = 30.0) -> None:
    """Wait until something on this machine listens on the port (mosaic's ffmpeg)."""
    table = Path("/proc/net/udp" if udp else "/proc/net/tcp")
    needle = f":{port:04X} "
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        for line in table.read_text().splitlines()[1:]:
            fields = line.split()
            if fields[1].upper().endswith(needle.strip()) and (udp or fields[3] == "0A"):
                return
        time.sleep(0.05)
    raise AssertionError(f"nothing listened on port {port} within {limit} s")


def mosaic(*args, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "mosaic_cli", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, **kwargs)


def send(video: Path, url: str) -> subprocess.CompletedProcess:
    """Serve the flight in real time as MPEG-TS (the video stream as it is, no re-encoding)."""
    return subprocess.run([FFMPEG, "-v", "error", "-re", "-i", str(video), "-c", "copy", "-f", "mpegts", url],
                          capture_output=True, timeout=RUN_LIMIT)


def finish(proc: subprocess.Popen) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=RUN_LIMIT)
    return proc.returncode, out.decode(), err.decode()


def offline_track(tmp_path: Path, video: Path) -> np.ndarray:
    out = tmp_path / "offline.json"
    subprocess.run([sys.executable, "-m", "mosaic_cli", "track", str(video), "-o", str(out), "-e", "orb", "-q"],
                   check=True, timeout=RUN_LIMIT)
    return np.array(json.loads(out.read_text())["pairwise"])


def corner_error(H: np.ndarray, truth: np.ndarray) -> np.ndarray:
    w, h = SIZE
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float).T
    a, b = H @ corners, truth @ corners
    return np.linalg.norm(a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:], axis=1).max(axis=-1)


def read_lines(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def test_track_from_stdin_writes_json_lines_equal_to_the_offline_track(tmp_path, flight):
    video, truth = flight
    with open(video, "rb") as stdin:
        rc, out, err = finish(mosaic("track", "-", "-o", "-", "-e", "orb", "-q", stdin=stdin))
    assert rc == 0, err
    lines = read_lines(out)
    assert [line["frame"] for line in lines] == list(range(FRAMES - 1))
    H = np.array([line["H"] for line in lines])
    # The same decoded frames as the file: the same estimates.
    np.testing.assert_allclose(H, offline_track(tmp_path, video), atol=1e-9)
    assert np.median(corner_error(H, np.array(truth["pairwise"]))) < 1.0
    assert all(0.0 <= line["confidence"] <= 1.0 for line in lines)


def test_track_over_udp_ends_on_timeout_with_every_frame(tmp_path, flight):
    video, _ = flight
    port = free_port(socket.SOCK_DGRAM)
    out = tmp_path / "udp.json"
    proc = mosaic("track", f"udp://127.0.0.1:{port}", "-o", out, "-e", "orb", "--timeout", "1.5")
    wait_until_bound(port, udp=True)
    sent = time.monotonic()
    assert send(video, f"udp://127.0.0.1:{port}?pkt_size=1316").returncode == 0
    stopped = time.monotonic()
    rc, _, err = finish(proc)
    assert rc == 0, err
    assert "sent nothing for 1.5 s (--timeout)" in err
    assert time.monotonic() - stopped < 30
    doc = json.loads(out.read_text())
    assert doc["frames"] == FRAMES  # nothing lost, the decoder's last frames included
    assert doc["meta"]["ended_by"] == "timeout"
    assert stopped - sent > 1.0  # it really was served in real time


def test_track_over_tcp_listening_follows_the_json_lines_file(tmp_path, flight):
    video, _ = flight
    port = free_port(socket.SOCK_STREAM)
    out = tmp_path / "pairs.jsonl"
    proc = mosaic("track", f"tcp://127.0.0.1:{port}?listen=1", "-o", out, "-e", "orb", "-q")
    wait_until_bound(port, udp=False)
    sender = subprocess.Popen([FFMPEG, "-v", "error", "-re", "-i", str(video), "-c", "copy", "-f", "mpegts",
                               f"tcp://127.0.0.1:{port}"])
    # Lines appear while the flight is still being sent.
    deadline = time.monotonic() + RUN_LIMIT
    while sender.poll() is None and time.monotonic() < deadline:
        if out.exists() and len(read_lines(out.read_text())) >= 5:
            break
        time.sleep(0.05)
    seen_while_sending = sender.poll() is None and out.exists() and len(read_lines(out.read_text())) >= 5
    sender.wait(timeout=RUN_LIMIT)
    rc, _, err = finish(proc)
    assert rc == 0, err
    assert seen_while_sending
    assert [line["frame"] for line in read_lines(out.read_text())] == list(range(FRAMES - 1))


def test_sigterm_ends_a_live_track_with_what_was_received(tmp_path, flight):
    video, _ = flight
    port = free_port(socket.SOCK_STREAM)
    out = tmp_path / "stopped.json"
    proc = mosaic("track", f"tcp://127.0.0.1:{port}?listen=1", "-o", out, "-e", "orb")
    wait_until_bound(port, udp=False)
    sender = subprocess.Popen([FFMPEG, "-v", "quiet", "-re", "-i", str(video), "-c", "copy", "-f", "mpegts",
                               f"tcp://127.0.0.1:{port}"])
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    rc, _, err = finish(proc)
    sender.wait(timeout=RUN_LIMIT)
    assert rc == 0, err
    assert "SIGTERM: ending with the" in err
    doc = json.loads(out.read_text())
    assert 2 <= doc["frames"] < FRAMES
    assert doc["meta"]["ended_by"] == "SIGTERM"


def test_no_sender_is_one_clear_error(tmp_path):
    port = free_port(socket.SOCK_DGRAM)
    rc, _, err = finish(mosaic("track", f"udp://127.0.0.1:{port}", "-o", tmp_path / "t.json", "-e", "orb", "--timeout", "0.5"))
    assert rc == 2
    assert err.strip() == f"mosaic: error: udp://127.0.0.1:{port}: no video arrived within 0.5 s (--timeout)"
    assert not (tmp_path / "t.json").exists()


def test_garbage_on_stdin_is_one_clear_error(tmp_path):
    rc, _, err = finish(mosaic("track", "-", "-o", tmp_path / "t.jsonl", "-e", "orb", stdin=subprocess.PIPE))
    assert rc == 2
    assert err.startswith("mosaic: error: standard input: cannot read a video stream") and err.count("\n") == 1
