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
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import FFMPEG, assert_one_line_error, cli_exit, run_cli, simulated

pytestmark = pytest.mark.alone  # wall-clock bounds: run with no other test beside it (conftest.py)

SIZE = (320, 180)
FRAMES = 60
RUN_LIMIT = 300  # seconds any one command may take: far above what it needs, even on a loaded machine


@pytest.fixture(scope="module")
def shaky_flight(tmp_path_factory) -> tuple[Path, dict]:
    """5 s of a shaky simulated flight (long enough for the jitter's high-pass), exact truth."""
    video = simulated(tmp_path_factory.mktemp("shaky") / "shaky.mp4", "-p", "shaky", "-n", "150", "--size", f"{SIZE[0]}x{SIZE[1]}",
                      "--preset", "veryfast")
    return video, json.loads(video.with_suffix(".gt.json").read_text())


@pytest.fixture(scope="module")
def flight(shaky_flight) -> tuple[Path, dict]:
    """Its first 2 s, what the real-time tests send; the truth of those frames."""
    video, truth = shaky_flight
    short = video.with_name("short.mp4")
    subprocess.run([FFMPEG, "-v", "error", "-y", "-i", str(video), "-frames:v", str(FRAMES), "-c:v", "libx264",
                    "-preset", "veryfast", "-crf", "12", "-movflags", "+faststart", str(short)], check=True, timeout=RUN_LIMIT)
    return short, {"pairwise": truth["pairwise"][:FRAMES - 1]}


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


def stabilize_served(video: Path, out: Path, options):
    """``stabilize_live`` listening on loopback TCP, ``video`` sent to it in real time."""
    from mosaic_cli.live.stabilize import stabilize_live

    port = free_port(socket.SOCK_STREAM)
    sender = threading.Thread(target=lambda: (wait_until_bound(port, udp=False), send(video, f"tcp://127.0.0.1:{port}")),
                              daemon=True)
    sender.start()
    result = stabilize_live(f"tcp://127.0.0.1:{port}?listen=1", str(out), options, show_progress=False)
    sender.join(RUN_LIMIT)
    return result


def offline_track(tmp_path: Path, video: Path) -> np.ndarray:
    out = tmp_path / "offline.json"
    assert cli_exit(["track", video, "-o", out, "-e", "orb", "-q"]) == 0  # in this process: the offline run's output alone
    return np.array(json.loads(out.read_text())["pairwise"])


def corner_error(H: np.ndarray, truth: np.ndarray) -> np.ndarray:
    w, h = SIZE
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float).T
    a, b = H @ corners, truth @ corners
    return np.linalg.norm(a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:], axis=1).max(axis=-1)


def read_lines(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


def processes_in_session(session: int) -> list[int]:
    """The live processes whose session is ``session`` (Linux's /proc)."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended meanwhile
            continue
        if int(fields[3]) == session and fields[0] != "Z":
            pids.append(int(stat.parent.name))
    return pids


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
def test_sigterm_to_the_process_group_ends_a_live_stabilize_with_its_network_process(tmp_path, flight):
    """`timeout` and a terminal signal the whole process group, the network's process included
    (:mod:`mosaic_cli.live.network_process`): the run still ends as its stream's end would, its
    video written, and leaves no process behind."""
    video, _ = flight
    port = free_port(socket.SOCK_STREAM)
    out = tmp_path / "steady.mp4"
    proc = mosaic("stabilize", f"tcp://127.0.0.1:{port}?listen=1", out, "--latency", "1", start_new_session=True)
    wait_until_bound(port, udp=False)
    sender = subprocess.Popen([FFMPEG, "-v", "quiet", "-re", "-stream_loop", "-1", "-i", str(video), "-c", "copy", "-f", "mpegts",
                               f"tcp://127.0.0.1:{port}"])
    try:
        deadline = time.monotonic() + RUN_LIMIT
        while len(processes_in_session(proc.pid)) < 2 and time.monotonic() < deadline:  # mosaic and its network
            time.sleep(0.1)
        time.sleep(3.0)  # frames are coming in
        os.killpg(proc.pid, signal.SIGTERM)
        rc, _, err = finish(proc)
    finally:
        sender.kill()
        sender.wait(timeout=RUN_LIMIT)
    assert rc == 0, err
    assert "SIGTERM: ending with the" in err and "error" not in err, err
    assert count_frames(out) >= 30
    time.sleep(0.5)
    assert processes_in_session(proc.pid) == [], "a process of the run outlived it"


class _Unwound(Exception):
    """What the command line's own handler does to a run a signal reaches (it raises KeyboardInterrupt)."""


def test_a_signal_while_the_decoder_starts_asks_the_stream_to_end():
    """A signal that comes once the decoder listens, while ``on_started`` runs (stabilize
    imports its solver there, holding the interpreter for half a second), asks the stream to
    end as one a moment later would: the run's own handler is not the one that meets it (which
    unwound the run with a bare "terminated", seen once in CI)."""
    from mosaic_cli.errors import Interrupted
    from mosaic_cli.live.source import LiveStream

    def unwind(signum, frame):
        raise _Unwound

    port = free_port(socket.SOCK_STREAM)
    previous = signal.signal(signal.SIGTERM, unwind)
    try:
        with pytest.raises(Interrupted, match=r"stopped \(SIGTERM\) before any video arrived"):
            LiveStream(f"tcp://127.0.0.1:{port}?listen=1", "gray", timeout=10, on_started=lambda: os.kill(os.getpid(), signal.SIGTERM))
    finally:
        signal.signal(signal.SIGTERM, previous)

    def fails():
        raise RuntimeError("on_started failed")

    port = free_port(socket.SOCK_STREAM)  # whatever ends the start, the listening decoder goes with it
    with pytest.raises(RuntimeError, match="on_started failed"):
        LiveStream(f"tcp://127.0.0.1:{port}?listen=1", "gray", timeout=10, on_started=fails)
    assert not [p for p in Path("/proc").glob("[0-9]*") if f"127.0.0.1:{port}" in _cmdline(p)], "the decoder outlived the stream"


def _cmdline(process: Path) -> str:
    try:
        return (process / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
@pytest.mark.parametrize("command", ["track", "stitch", "stabilize"])
def test_a_signal_before_any_video_is_one_line_its_status_and_leaves_nothing(tmp_path, command):
    """SIGTERM to the process group while a live command listens and no sender has come: one
    line, the shell's status for the signal (143), no output, and no process of the run left
    (its decoder listening, the network's process)."""
    port = free_port(socket.SOCK_STREAM)
    out = tmp_path / {"track": "t.json", "stitch": "pano.png", "stabilize": "steady.mp4"}[command]
    proc = mosaic(command, f"tcp://127.0.0.1:{port}?listen=1", *([out] if command == "stabilize" else ["-o", out]),
                  start_new_session=True)
    wait_until_bound(port, udp=False)
    os.killpg(proc.pid, signal.SIGTERM)
    rc, _, err = finish(proc)
    assert rc == 128 + signal.SIGTERM, err
    assert err.strip() == f"mosaic: error: tcp://127.0.0.1:{port}?listen=1: stopped (SIGTERM) before any video arrived", err
    assert list(tmp_path.iterdir()) == []
    deadline = time.monotonic() + 5.0
    while processes_in_session(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert processes_in_session(proc.pid) == [], "a process of the run outlived it"


@pytest.mark.slow
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


# -- stabilize --latency ------------------------------------------------------------------

def gt_jitter(truth: dict, warps: np.ndarray | None) -> float:
    from mosaic_cli.stabilize.metrics import ground_truth_jitter

    return ground_truth_jitter(np.array(truth["map_to_frame"]), np.array(truth["smooth_map_to_frame"]), SIZE,
                               float(truth.get("fps", 30.0)), warps)


def count_frames(video: Path) -> int:
    run = subprocess.run([FFMPEG, "-hide_banner", "-i", str(video), "-map", "0:v:0", "-f", "null", "-"],
                         capture_output=True, timeout=RUN_LIMIT)
    frames = [line for line in run.stderr.decode().replace("\r", "\n").splitlines() if line.startswith("frame=")]
    return int(frames[-1].split("=")[1].split()[0])


@pytest.mark.slow
def test_stabilize_live_over_tcp_to_a_file_keeps_every_frame_and_steadies(tmp_path, flight):
    video, truth = flight
    port = free_port(socket.SOCK_STREAM)
    out, warps = tmp_path / "steady.mp4", tmp_path / "warps.json"
    proc = mosaic("stabilize", f"tcp://127.0.0.1:{port}?listen=1", out, "-e", "orb", "--warps", warps)
    wait_until_bound(port, udp=False)
    assert send(video, f"tcp://127.0.0.1:{port}").returncode == 0
    rc, _, err = finish(proc)
    assert rc == 0, err
    assert f"{FRAMES} frames in, {FRAMES} out" in err
    assert count_frames(out) == FRAMES
    assert len(json.loads(warps.read_text())["warps"]) == FRAMES


@pytest.mark.slow
def test_stabilize_with_a_latency_of_one_second_steadies_about_as_well_as_offline(tmp_path, shaky_flight):
    video, truth = shaky_flight
    jitter = {}
    # The file read in one pass; the same piped in faster than real time (a live input, held
    # back at the tracker's pace: its frames must not leave unsteadied at their deadlines).
    for name, source, extra in (("live", str(video), ["--latency", "1"]), ("piped", "-", ["--latency", "1"]),
                                ("offline", str(video), [])):
        warps = tmp_path / f"{name}.json"
        args = ["stabilize", source, str(tmp_path / f"{name}.mp4"), "-e", "orb", "--warps", str(warps), "-q", *extra]
        if name == "offline":  # the reference: in this process
            assert cli_exit(args) == 0
        else:
            with open(video, "rb") as stdin:
                subprocess.run([sys.executable, "-m", "mosaic_cli", *args], stdin=stdin, check=True, timeout=RUN_LIMIT)
        jitter[name] = gt_jitter(truth, np.array(json.loads(warps.read_text())["warps"]))
    for name in ("live", "piped"):
        assert jitter[name] < 0.5 * gt_jitter(truth, None), jitter
        assert jitter[name] <= 1.5 * jitter["offline"], jitter


@pytest.mark.slow
def test_stabilize_stdin_to_stdout_is_an_mpeg_ts_stream(tmp_path, flight):
    video, _ = flight
    with open(video, "rb") as stdin:
        proc = subprocess.run([sys.executable, "-m", "mosaic_cli", "stabilize", "-", "-", "-e", "orb", "--latency", "0.5",
                               "-q"], stdin=stdin, capture_output=True, timeout=RUN_LIMIT)
    assert proc.returncode == 0, proc.stderr.decode()
    assert proc.stdout[0] == 0x47 and proc.stdout[188] == 0x47  # MPEG-TS sync bytes
    (tmp_path / "out.ts").write_bytes(proc.stdout)
    assert count_frames(tmp_path / "out.ts") == FRAMES


@pytest.mark.slow
def test_a_solver_slower_than_the_latency_holds_no_frame_back_and_drops_none(tmp_path, flight, monkeypatch):
    """Every solve of the path takes longer than the whole budget (fault injected): the frames
    leave at their deadline on the path planned so far, every one of them."""
    from mosaic_cli.stabilize import StabilizeOptions
    from mosaic_cli.stabilize.online import OnlineL1Path

    solve = OnlineL1Path.solve

    def slow(self, window):
        time.sleep(1.5)
        return solve(self, window)

    monkeypatch.setattr(OnlineL1Path, "solve", slow)
    video, _ = flight
    out = tmp_path / "steady.mp4"
    result = stabilize_served(video, out, StabilizeOptions(estimator="orb", latency=1.0))
    assert result.frames_in == result.frames_out == len(result.warps) == FRAMES
    assert count_frames(out) == FRAMES
    assert result.late >= 1 and result.notes and "left at their deadline" in result.notes[-1]


def test_online_path_waits_at_most_its_horizon_and_equals_the_offline_path_when_it_sees_everything():
    from mosaic_cli.stabilize.online import Horizon, OnlineL1Path
    from mosaic_cli.stabilize.path import camera_motion, motion_model
    from mosaic_cli.stabilize.smoothing import L1Smoother

    rng = np.random.default_rng(1)
    n, size, model = 50, SIZE, motion_model("similarity")
    pairwise = np.tile(np.eye(3), (n - 1, 1, 1))
    pairwise[:, 0, 2] = 2.0 + rng.normal(0, 1.5, n - 1)  # a pan with shake
    pairwise[:, 1, 2] = rng.normal(0, 1.5, n - 1)

    horizon = Horizon(step=4, lookahead=6)
    online = OnlineL1Path(model, size, None, horizon)
    settled_at: list[int] = []
    for t in range(n):
        online.push(None if t == 0 else pairwise[t - 1])
        settled_at += [t] * len(online.settle())
    settled_at += [n - 1] * len(online.settle(final=True))
    assert len(settled_at) == n
    waits = np.array(settled_at) - np.arange(n)
    assert waits.min() >= 0 and waits.max() <= horizon.frames - 1

    whole = OnlineL1Path(model, size, None, Horizon(step=n, lookahead=n))
    for t in range(n):
        whole.push(None if t == 0 else pairwise[t - 1])
    assert len(whole.settle()) == 0
    views = whole.settle(final=True)
    offline = L1Smoother().smooth(camera_motion(pairwise, size, model), size, model, None)
    np.testing.assert_allclose(views, offline, atol=1e-9)


@pytest.mark.slow
def test_latency_too_short_for_the_frame_rate_is_one_clear_error(tmp_path, flight, capsys):
    video, _ = flight
    code, err = run_cli(capsys, "stabilize", video, tmp_path / "o.mp4", "-e", "orb", "--latency", "0.1")
    assert_one_line_error(code, err)
    assert err.startswith("mosaic: error: --latency 0.1 s is too short at 30 fps")
    assert not (tmp_path / "o.mp4").exists()


# -- stitch --live ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def survey(survey_320x180) -> Path:
    return survey_320x180  # (conftest: test_live_preview streams the same flight)


@pytest.mark.slow
def test_stitch_live_from_stdin_equals_the_offline_stitch(tmp_path, survey):
    with open(survey, "rb") as stdin:
        rc, _, err = finish(mosaic("stitch", "-", "-o", tmp_path / "live.png", "--transforms", tmp_path / "live.json",
                                   "-e", "orb", "-q", stdin=stdin))
    assert rc == 0, err
    assert cli_exit(["stitch", survey, "-o", tmp_path / "off.png", "--transforms", tmp_path / "off.json", "-e", "orb", "-q"]) == 0
    import cv2

    assert json.loads((tmp_path / "live.json").read_text()) == json.loads((tmp_path / "off.json").read_text())
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "live.png"), -1), cv2.imread(str(tmp_path / "off.png"), -1))


@pytest.mark.slow
def test_stitch_live_over_udp_writes_a_growing_preview_and_ends_on_timeout(tmp_path, survey):
    import cv2

    port = free_port(socket.SOCK_DGRAM)
    preview, out = tmp_path / "preview.png", tmp_path / "pano.png"
    log = open(tmp_path / "stderr.txt", "w+")  # not a pipe: nobody reads it until the end
    proc = subprocess.Popen([sys.executable, "-m", "mosaic_cli", "stitch", f"udp://127.0.0.1:{port}", "-o", str(out),
                             "--live", "--preview", str(preview), "--every", "0.2", "-e", "orb", "--timeout", "1.5"],
                            stdout=subprocess.DEVNULL, stderr=log)
    wait_until_bound(port, udp=True)
    sender = subprocess.Popen([FFMPEG, "-v", "error", "-re", "-i", str(survey), "-c", "copy", "-f", "mpegts",
                               f"udp://127.0.0.1:{port}?pkt_size=1316"])
    sizes = []
    # Watched until mosaic ends: on a loaded machine the scan (and so the previews) may lag
    # behind the sender.
    deadline = time.monotonic() + RUN_LIMIT
    while proc.poll() is None and time.monotonic() < deadline:
        if preview.exists():
            image = cv2.imread(str(preview), cv2.IMREAD_UNCHANGED)
            assert image is not None  # never a half-written file
            sizes.append(int((image[..., 3] > 0).sum()))
        time.sleep(0.1)
    sender.wait(timeout=RUN_LIMIT)
    rc = proc.wait(timeout=RUN_LIMIT)
    final = cv2.imread(str(preview), cv2.IMREAD_UNCHANGED)  # the last one: every keyframe scanned
    sizes.append(int((final[..., 3] > 0).sum()))
    log.seek(0)
    err = log.read()
    log.close()
    assert rc == 0, err
    assert "(--timeout)" in err
    assert "120 frames ->" in err
    assert sizes and sizes[-1] > sizes[0]  # the covered area grew as the flight came in
    pano = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert pano is not None and pano.shape[2] == 4
    assert not list(tmp_path.glob(".*.part*"))


@pytest.mark.slow
def test_the_previews_incremental_drift_control_places_keyframes_as_well_as_the_final_stitch(tmp_path, survey):
    from mosaic_cli.estimators import make_estimator
    from mosaic_cli.geometry import frame_corners, project
    from mosaic_cli.stitch import StitchOptions
    from mosaic_cli.stitch.live import IncrementalRegistration, PreviewOptions, stitch_live

    seen = {}
    update = IncrementalRegistration.update

    def spy(self, keyframes):
        seen["placements"], seen["indices"] = update(self, keyframes), [k.index for k in keyframes]
        return seen["placements"]

    IncrementalRegistration.update = spy
    try:
        result = stitch_live(str(survey), tmp_path / "p.png", make_estimator("orb"), StitchOptions(),
                             preview=PreviewOptions(tmp_path / "preview.png", 0.01), show_progress=False)
    finally:
        IncrementalRegistration.update = update
    truth = np.array(json.loads(survey.with_suffix(".gt.json").read_text())["map_to_frame"])
    indices = [i for i, _ in result.transforms]
    assert seen["indices"] == indices and result.previews >= 2
    corners = frame_corners(*SIZE)

    def errors(placements):
        out = []
        for a, i in enumerate(indices):
            for b, j in enumerate(indices):
                if j - i >= 30:
                    estimate = np.linalg.inv(placements[b]) @ placements[a]
                    exact = truth[j] @ np.linalg.inv(truth[i])
                    out.append(np.abs(project(estimate, corners) - project(exact, corners)).max())
        return np.median(out)

    final = errors([H for _, H in result.transforms])
    assert errors(seen["placements"]) <= 1.5 * final + 0.1


@pytest.mark.parametrize("extra", [[], ["-colorspace", "bt709", "-color_primaries", "bt709", "-color_trc", "bt709"]])
def test_live_rgb_frames_are_the_file_reader_s(tmp_path, extra):
    """A live source's RGB frames are converted as a file's are (yuv420p piped, converted in
    mosaic), whatever the stream's colour tags: a live stitch sees the pixels an offline one does."""
    from conftest import textured_image, write_clip
    from mosaic_cli.live.source import LiveStream
    from mosaic_cli.video import open_video

    clip = write_clip(tmp_path / "clip.mp4", [textured_image(320, 180, seed=k) for k in range(4)], extra=extra)
    with LiveStream(str(clip), "rgb", live=False, quiet=True) as live:
        received = list(live)
    with open_video(clip) as stream:
        decoded = list(stream)
    assert len(received) == len(decoded) == 4
    assert all(np.array_equal(a, b) for a, b in zip(received, decoded))
    assert all(np.array_equal(a.luma, b.luma) for a, b in zip(received, decoded))


@pytest.mark.slow
def test_a_live_stabilize_listens_while_its_network_is_still_loading(tmp_path, flight, monkeypatch):
    """The socket is open before the network has loaded (here a load held back until a sender
    has connected): a sender that starts at once is not refused, and every frame comes out."""
    import mosaic_cli.live.stabilize as live_stabilize
    from mosaic_cli.stabilize import StabilizeOptions

    wait_loaded = live_stabilize.NetworkProcess.wait_loaded
    connected = threading.Event()

    def held_back(self):
        assert connected.wait(45), "the load waited for a sender that never connected"
        time.sleep(1.0)  # a second of frames comes before the network is there
        return wait_loaded(self)

    monkeypatch.setattr(live_stabilize.NetworkProcess, "wait_loaded", held_back)
    video, _ = flight
    port = free_port(socket.SOCK_STREAM)

    def sender() -> None:
        wait_until_bound(port, udp=False)  # listening, though the load has not finished
        connected.set()
        send(video, f"tcp://127.0.0.1:{port}")

    thread = threading.Thread(target=sender, daemon=True)
    thread.start()
    out = tmp_path / "steady.mp4"
    result = live_stabilize.stabilize_live(f"tcp://127.0.0.1:{port}?listen=1", str(out), StabilizeOptions(latency=1.0),
                                           show_progress=False)
    thread.join(RUN_LIMIT)
    assert connected.is_set()
    assert result.frames_in == result.frames_out == FRAMES and count_frames(out) == FRAMES
    assert any("tracked by ORB while the network loaded" in n for n in result.notes), result.notes
    # Which estimator made how many pairs: ORB the first (here, with the load held back over a
    # 2 s clip, maybe all), the network any after; every pair counted once.
    assert result.pairs_by["orb"] >= 1 and set(result.pairs_by) <= {"orb", "lstm-reg-t"}, result.pairs_by
    assert sum(result.pairs_by.values()) == FRAMES - 1, result.pairs_by


def test_a_stream_that_ends_while_its_network_still_loads_does_not_wait_for_it(tmp_path, flight, monkeypatch):
    """A load that would take a minute more (held back here until its process is ended): the
    run ends with the stream, every frame out by ORB, and the network's process is ended."""
    import mosaic_cli.live.stabilize as live_stabilize
    from mosaic_cli.stabilize import StabilizeOptions

    wait_loaded = live_stabilize.NetworkProcess.wait_loaded
    children = []

    def slow(self):
        children.append(self._child)
        limit = time.monotonic() + 60
        while self._child.poll() is None and time.monotonic() < limit:
            time.sleep(0.05)
        return wait_loaded(self)

    monkeypatch.setattr(live_stabilize.NetworkProcess, "wait_loaded", slow)
    video, _ = flight
    port = free_port(socket.SOCK_STREAM)
    thread = threading.Thread(target=lambda: (wait_until_bound(port, udp=False), send(video, f"tcp://127.0.0.1:{port}")),
                              daemon=True)
    thread.start()
    started = time.monotonic()
    result = live_stabilize.stabilize_live(f"tcp://127.0.0.1:{port}?listen=1", str(tmp_path / "steady.mp4"),
                                           StabilizeOptions(latency=1.0), show_progress=False)
    assert time.monotonic() - started < 30, "the run waited for the network's load"
    assert result.frames_out == FRAMES and result.pairs_by == {"orb": FRAMES - 1}, result.pairs_by
    assert children and children[0].poll() is not None


def test_the_bridge_hands_every_pair_over_once_when_the_network_arrives(tmp_path):
    """Frames tracked by ORB until the network has loaded, then by the network from the last
    frame ORB saw: one estimate per pair, in order, none lost or made twice, each close to the truth."""
    import concurrent.futures

    from mosaic_cli.estimators import OrbEstimator
    from mosaic_cli.live.stabilize import Bridged
    from mosaic_cli.video import open_video

    video = simulated(tmp_path / "shaky.mp4", "-p", "shaky", "-n", "30", "--size", f"{SIZE[0]}x{SIZE[1]}", "--preset", "veryfast",
                      "--seed", "3")
    truth = json.loads(video.with_suffix(".gt.json").read_text())
    with open_video(video, width=320, gray=True) as stream:
        grays = list(stream)
    loading: concurrent.futures.Future = concurrent.futures.Future()
    bridged = Bridged(loading, 320, None, SIZE)
    estimates = []
    for k, gray in enumerate(grays):
        if k == 12:
            loading.set_result(OrbEstimator(320))  # the "network" arrives after 12 frames
        estimates += bridged.feed(gray)
    estimates += bridged.finish()
    assert bridged.bridged == 12 and len(estimates) == len(grays) - 1
    H = np.array([e.H for e in estimates])
    assert np.median(corner_error(H, np.array(truth["pairwise"][:len(grays) - 1]))) < 1.0


@pytest.mark.slow
def test_live_track_and_stitch_listen_while_their_network_is_still_loading(tmp_path, flight, monkeypatch):
    """As live stabilize: the socket is open before the estimator exists (its load held back
    until a sender has connected), and every frame sent is tracked, or scanned, once it is."""
    import concurrent.futures

    import mosaic_cli.stitch.live as stitch_live_module
    from mosaic_cli.estimators import OrbEstimator
    from mosaic_cli.live.track import track_stream

    video, _ = flight

    def serve(port: int, connected: threading.Event) -> threading.Thread:
        def run() -> None:
            wait_until_bound(port, udp=False)  # listening, though nothing has loaded
            connected.set()
            send(video, f"tcp://127.0.0.1:{port}")

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        return thread

    # track: a future of the estimator, set once a sender connected
    port, connected = free_port(socket.SOCK_STREAM), threading.Event()
    loading: concurrent.futures.Future = concurrent.futures.Future()
    threading.Thread(target=lambda: (connected.wait(45), loading.set_result(OrbEstimator(320))), daemon=True).start()
    sender = serve(port, connected)
    result = track_stream(f"tcp://127.0.0.1:{port}?listen=1", loading, tmp_path / "live.json", show_progress=False, width=320)
    sender.join(RUN_LIMIT)
    assert connected.is_set() and len(result.pairwise) == FRAMES - 1

    # stitch: its estimator's build held back the same way
    build = stitch_live_module.make_stitch_estimator
    port, connected = free_port(socket.SOCK_STREAM), threading.Event()

    def held_back(options):
        assert connected.wait(45), "the load waited for a sender that never connected"
        return build(options)

    monkeypatch.setattr(stitch_live_module, "make_stitch_estimator", held_back)
    sender = serve(port, connected)
    from mosaic_cli.stitch import StitchOptions

    stitched = stitch_live_module.stitch_live(f"tcp://127.0.0.1:{port}?listen=1", tmp_path / "pano.png",
                                              options=StitchOptions(estimator="orb"), show_progress=False)
    sender.join(RUN_LIMIT)
    assert connected.is_set() and (tmp_path / "pano.png").is_file() and stitched.frames == FRAMES


@pytest.mark.slow
def test_a_tilt_correction_that_cannot_keep_up_live_is_planned_as_a_similarity_and_says_so(tmp_path, monkeypatch):
    """Every `tilt` solve takes longer than the whole budget (fault injected), its similarity
    part does not: past the start, the run switches once the frames keep leaving at their
    deadline, says so in one line, and the frames after the switch leave on a planned path again."""
    from mosaic_cli.live.schedule import KEEP_UP_AFTER, RECENT
    from mosaic_cli.stabilize import StabilizeOptions
    from mosaic_cli.stabilize.online import OnlineL1Path

    video = tmp_path / "long.mp4"  # 10 s: the start, the window that decides, and the frames after
    simulated(video, "-p", "shaky-tilt", "-n", "300", "--size", f"{SIZE[0]}x{SIZE[1]}", "--preset", "veryfast")
    solve = OnlineL1Path.solve

    def slow_tilt(self, window):
        if not self.similar_only:
            time.sleep(1.5)
        return solve(self, window)

    monkeypatch.setattr(OnlineL1Path, "solve", slow_tilt)
    result = stabilize_served(video, tmp_path / "steady.mp4", StabilizeOptions(estimator="orb", latency=1.0, model="tilt"))
    assert result.frames_in == result.frames_out == 300
    assert result.simplified_at is not None and KEEP_UP_AFTER + RECENT <= result.simplified_at < 300
    assert any("could not keep up live" in n for n in result.notes)
    # The solve under way when it switched still ends late (1.5 s of frames); the last frames are on time.
    before, after = result.lateness[KEEP_UP_AFTER:result.simplified_at], result.lateness[-60:]
    assert before.mean() > 0.5 and after.mean() < 0.1, (before.mean(), after.mean())


def test_a_path_planned_as_a_similarity_lets_the_settled_tilt_fade_out_smoothly():
    """After the switch, a window's similarity part is the similarity program's own, and the
    perspective terms the settled frames carried fall to zero over ``rejoin`` frames, never
    in one step."""
    from mosaic_cli.stabilize.online import Horizon, OnlineL1Path
    from mosaic_cli.stabilize.path import MODELS, fit_model
    from mosaic_cli.stabilize.smoothing import solve_window

    rng = np.random.default_rng(0)
    path = OnlineL1Path(MODELS["tilt"], (640, 360), None, Horizon.for_latency(1.0, 30.0, 3))
    path.push()
    for _ in range(60):
        H = np.eye(3)
        H[0, 2], H[1, 2] = 4 + rng.normal(0, 2), rng.normal(0, 2)
        H[2, :2] = rng.normal(0, 4e-5, 2)
        path.push(H, 1.0)
    window = path.pose()
    path.adopt(window, path.solve(window))
    path.commit(40)
    path.similar_only = True
    window = path.pose()
    params = path.solve(window)
    carried, tilt = len(window.fixed), slice(4, 6)
    assert np.any(window.fixed[-1, tilt] != 0)  # there is a tilt to fade out
    np.testing.assert_array_equal(params[:carried], window.fixed)
    similar = solve_window(fit_model(window.motion, MODELS["similarity"]), MODELS["similarity"], window.fixed[:, :4], (640, 360),
                           None, path.options)
    np.testing.assert_allclose(params[:, :4], similar, atol=1e-9)
    steps = np.abs(np.diff(params[carried - 1:, tilt], axis=0)).max(axis=0)
    assert np.all(steps <= 1.01 * np.abs(window.fixed[-1, tilt]) * np.pi / (2 * path.rejoin))  # a cosine's steepest step
    assert np.all(params[carried + path.rejoin:, tilt] == 0)


def test_the_network_loads_with_the_interpreter_handed_on_often_and_leaves_it_as_it_was():
    """While a live command's network loads beside its stream, the interpreter's lock is handed on
    every LOADING_SWITCH_INTERVAL (torch's import held it up to the default 5 ms each time a live
    thread asked: frames left at their deadline in cold runs, docs/measurements/live.md); the
    collector waits; both as they were once it is built, also when the build fails."""
    import gc
    import sys

    from mosaic_cli.live import loading

    before = sys.getswitchinterval()
    seen = loading.built_beside(lambda: (sys.getswitchinterval(), gc.isenabled())).result(timeout=10)
    assert seen == (pytest.approx(min(before, loading.LOADING_SWITCH_INTERVAL)), False)
    assert sys.getswitchinterval() == pytest.approx(before) and gc.isenabled()

    def fails():
        raise ValueError("no such weights")

    with pytest.raises(ValueError, match="no such weights"):
        loading.built_beside(fails).result(timeout=10)
    assert sys.getswitchinterval() == pytest.approx(before) and gc.isenabled()


# Every live command ends when its stream ends, with the default (learned) estimator, whose
# pool of threads once kept a live track or stitch alive after its output was written.
END_GRACE = 2.0  # seconds from the end of the stream (or the output written, the later) to the exit
HANG_LIMIT = 60.0  # seconds after the stream's end at which a run that has not exited counts as hung
UDP_TIMEOUT = 1.0  # a UDP stream has no end but silence: --timeout says when


def _serve(video: Path, transport: str, port: int) -> subprocess.Popen:
    """ffmpeg sending the flight in real time over ``transport`` (stdin: to its standard output)."""
    target = {"stdin": "pipe:1", "tcp-listen": f"tcp://127.0.0.1:{port}", "tcp-connect": f"tcp://127.0.0.1:{port}?listen=1",
              "udp": f"udp://127.0.0.1:{port}?pkt_size=1316"}[transport]
    return subprocess.Popen([FFMPEG, "-v", "error", "-re", "-i", str(video), "-c", "copy", "-f", "mpegts", target],
                            stdout=subprocess.PIPE if transport == "stdin" else subprocess.DEVNULL)


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["stdin", "tcp-listen", "tcp-connect", "udp"])
@pytest.mark.parametrize("command", ["track", "stitch", "stabilize"])
def test_a_live_command_exits_once_its_stream_has_ended_and_its_output_is_written(tmp_path, flight, command, transport):
    video, _ = flight
    port = free_port(socket.SOCK_DGRAM if transport == "udp" else socket.SOCK_STREAM)
    source = {"stdin": "-", "tcp-listen": f"tcp://127.0.0.1:{port}?listen=1", "tcp-connect": f"tcp://127.0.0.1:{port}",
              "udp": f"udp://127.0.0.1:{port}"}[transport]
    out = tmp_path / {"track": "t.json", "stitch": "pano.png", "stabilize": "steady.mp4"}[command]
    args = [command, source, *([out] if command == "stabilize" else ["-o", out]), "-q", "--timeout",
            str(UDP_TIMEOUT if transport == "udp" else 30)]
    sender = None
    if transport == "stdin":
        sender = _serve(video, transport, port)
        proc = mosaic(*args, stdin=sender.stdout)
        sender.stdout.close()  # mosaic holds the pipe's only reading end
    elif transport == "tcp-connect":
        sender = _serve(video, transport, port)
        wait_until_bound(port, udp=False)
        proc = mosaic(*args)
    else:
        proc = mosaic(*args)
        wait_until_bound(port, udp=transport == "udp")
        sender = _serve(video, transport, port)
    try:
        assert sender.wait(timeout=RUN_LIMIT) == 0
        stream_ended = time.time()
        deadline = time.monotonic() + HANG_LIMIT
        while proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        exited = time.time()
        assert proc.poll() is not None, f"{command} over {transport} still runs {HANG_LIMIT} s after its stream ended"
    finally:
        if proc.poll() is None:
            proc.kill()
        _, err = proc.communicate(timeout=RUN_LIMIT)
    assert proc.returncode == 0, err.decode()
    assert out.exists()
    written = out.stat().st_mtime
    silence = UDP_TIMEOUT if transport == "udp" else 0.0
    assert exited - max(stream_ended + silence, written) < END_GRACE, (
        f"{command} over {transport} exited {exited - stream_ended:.1f} s after its stream ended, "
        f"{exited - written:.1f} s after writing {out.name}")


@pytest.mark.slow
def test_a_missed_latency_is_one_warning_that_says_by_how_much(tmp_path, flight, monkeypatch, capsys):
    """A render slower than the stream (fault injected: 0.1 s a frame at 30 fps): the frames
    still all come out, and one ``mosaic: warning:`` line gives the 95th percentile the run
    reached against the bound (the latency plus a frame interval)."""
    import mosaic_cli.live.stabilize as live_stabilize
    from mosaic_cli.stabilize import StabilizeOptions

    warp = live_stabilize.warp_yuv

    def slow(*args, **kwargs):
        time.sleep(0.1)
        return warp(*args, **kwargs)

    monkeypatch.setattr(live_stabilize, "warp_yuv", slow)
    video, _ = flight
    result = stabilize_served(video, tmp_path / "o.mp4", StabilizeOptions(estimator="orb", latency=1.0))
    assert result.frames_out == FRAMES
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("mosaic: warning: --latency")]
    bound = 1.0 + 1.0 / result.fps
    late = int(np.count_nonzero(result.latencies > bound))
    assert result.latency(95) > bound and warnings == [
        f"mosaic: warning: --latency 1 s missed: p95 {result.latency(95):.2f} s, {late} of {FRAMES} frames later than "
        f"{bound:.2f} s (the latest {result.latency(100):.2f} s); this machine could not keep up with "
        f"{SIZE[0]}x{SIZE[1]} at {result.fps:g} fps: a longer --latency, or a smaller input, would"]


@pytest.mark.slow
@pytest.mark.parametrize("command,signals", [("track", (signal.SIGINT, signal.SIGINT)), ("stitch", (signal.SIGINT, signal.SIGINT)),
                                             ("stabilize", (signal.SIGINT, signal.SIGINT)), ("stitch", (signal.SIGTERM, signal.SIGTERM))])
def test_a_second_signal_abandons_a_live_run_in_one_line_and_leaves_nothing(tmp_path, flight, command, signals):
    """The first Ctrl-C (or SIGTERM) ends a live stream as its end would (docs/guide/live.md); a
    second one abandons the run: one line, 130 (143 for SIGTERM), no traceback, no output."""
    video, _ = flight
    port = free_port(socket.SOCK_STREAM)
    out = tmp_path / {"track": "t.json", "stitch": "pano.png", "stabilize": "steady.mp4"}[command]
    source = f"tcp://127.0.0.1:{port}?listen=1"
    proc = mosaic(command, source, *([out] if command == "stabilize" else ["-o", out]), "-q")
    wait_until_bound(port, udp=False)
    sender = subprocess.Popen([FFMPEG, "-v", "quiet", "-re", "-stream_loop", "-1", "-i", str(video), "-c", "copy", "-f", "mpegts",
                               f"tcp://127.0.0.1:{port}"])
    try:
        time.sleep(2.0)  # frames are coming in
        proc.send_signal(signals[0])
        time.sleep(0.05)
        proc.send_signal(signals[1])
        rc, _, err = finish(proc)
    finally:
        sender.kill()
        sender.wait(timeout=RUN_LIMIT)
    name = "interrupted" if signals[1] == signal.SIGINT else "terminated"
    assert rc == (130 if signals[1] == signal.SIGINT else 143), err
    assert "Traceback" not in err and err.strip().splitlines()[-1] == f"mosaic: error: {name}", err
    assert sorted(p.name for p in tmp_path.iterdir()) == [], "the abandoned run left files behind"
