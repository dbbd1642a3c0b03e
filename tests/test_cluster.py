"""The stitch on a Dask cluster (issue 52, mosaic_cli/stitch/cluster.py), on 127.0.0.1 inside the
test: the compose stage's tiles and the flights' scans spread over local worker processes give
the one-process result to the bit, a video's segments scanned at once land where the truth does;
a worker killed mid-run is retried; a scheduler that does not answer, a cluster that cannot see
the stitch's disk and bad options are one line each."""

from __future__ import annotations

import json
import os
import signal
import socket
import time

import cv2
import numpy as np
import pytest

from benchmarks.common import placement_errors
from benchmarks.flights import cut_flight
from mosaic_cli.errors import BadInput
from mosaic_cli.simulate.groundtruth import load_ground_truth
from mosaic_cli.stitch import StitchOptions, stitch
from mosaic_cli.stitch.cluster import ClusterOptions, _check_shared, connect, tile_runner
from mosaic_cli.stitch.compose import ComposeOptions, MemoryCanvas, PlacedImage, compose
from mosaic_cli.stitch.flights import stitch_flights
from tests.conftest import assert_one_line_error, mosaic_run, run_cli, textured_image

pytestmark = pytest.mark.alone  # wall-clock bounds: run with no other test beside it (conftest.py)

pytest.importorskip("distributed")


def _views(count: int = 12, seed: int = 3):
    ground = textured_image(1200, 700, seed=5)
    rng = np.random.default_rng(seed)
    views = []
    for k in range(count):
        H = np.array([[1.0, 0.02, 20 + 180 * (k % 6) + rng.uniform(-6, 6)], [-0.02, 1.0, 20 + 230 * (k // 6)], [1e-5, 0, 1]])
        view = cv2.warpPerspective(ground, np.linalg.inv(H), (300, 260))
        views.append((np.clip(view * (0.85 + 0.3 * rng.random()), 0, 255).astype(np.uint8), H))
    return views


CANVAS = (1140, 530)


@pytest.mark.slow
def test_compose_on_a_local_cluster_is_the_one_process_panorama_to_the_bit(tmp_path):
    options = ComposeOptions(tile=128)
    alone = compose([PlacedImage(v.copy(), H) for v, H in _views()], CANVAS, options)
    other = compose([PlacedImage(v.copy(), H) for v, H in _views(seed=4)], CANVAS, options)
    with connect(ClusterOptions(workers=2), tmp_path) as client:
        sink = MemoryCanvas(CANVAS)
        placed = [PlacedImage(v.copy(), H) for v, H in _views()]
        assert compose(placed, CANVAS, options, sink=sink, runner=tile_runner(client)) is None
        assert all(p.image is None for p in placed)  # pixels dropped once drawn
        # A second panorama on the same workers (a flight in two parts): none of the first's
        # keyframes, which the workers kept, is drawn in it.
        second = MemoryCanvas(CANVAS)
        compose([PlacedImage(v.copy(), H) for v, H in _views(seed=4)], CANVAS, options, sink=second, runner=tile_runner(client))
    assert np.array_equal(sink.rgba, alone) and (alone[..., 3] == 255).mean() > 0.5
    assert np.array_equal(second.rgba, other) and not np.array_equal(other, alone)


@pytest.mark.slow
def test_a_worker_killed_mid_compose_is_retried_and_the_panorama_is_the_same(tmp_path):
    options = ComposeOptions(tile=64)
    alone = compose([PlacedImage(v.copy(), H) for v, H in _views()], CANVAS, options)
    with connect(ClusterOptions(workers=2), tmp_path) as client:
        pids = client.run(os.getpid)
        killed = []

        class KillingSink(MemoryCanvas):
            def write(self, x, y, rgba):
                if not killed:  # the first tile back: one worker dies with its queued rows
                    victim = sorted(pids.values())[0]
                    os.kill(victim, signal.SIGKILL)
                    killed.append(victim)
                super().write(x, y, rgba)

        sink = KillingSink(CANVAS)
        compose([PlacedImage(v.copy(), H) for v, H in _views()], CANVAS, options, sink=sink, runner=tile_runner(client))
    assert killed and np.array_equal(sink.rgba, alone)


@pytest.mark.slow
def test_two_flights_on_workers_give_the_one_process_map(tmp_path):
    """The flights scanned in worker processes (each its own estimator) and the tiles blended
    there: the transforms and the panorama of the stitch in one process."""
    full = tmp_path / "full.mp4"
    mosaic_run("simulate", "-p", "survey", "-n", "240", "--size", "320x180", "-o", full, "-q", "--seed", "3", "--preset", "ultrafast")
    flights = [cut_flight(full, 0, 140, tmp_path / "a.mp4"), cut_flight(full, 100, 240, tmp_path / "b.mp4")]
    results = {}
    for name, cluster in (("alone", ClusterOptions()), ("workers", ClusterOptions(workers=2))):
        options = StitchOptions(estimator="orb", compose=ComposeOptions(tile=128), cluster=cluster)
        out, js = tmp_path / f"{name}.png", tmp_path / f"{name}.json"
        stitch_flights(flights, out, options=options, transforms=js, show_progress=False)
        results[name] = (cv2.imread(str(out), cv2.IMREAD_UNCHANGED), json.loads(js.read_text()))
    (alone, alone_js), (spread, spread_js) = results["alone"], results["workers"]
    assert spread_js == alone_js and len({f["flight"] for f in alone_js["frames"]}) == 2
    assert np.array_equal(spread, alone)


@pytest.mark.slow
def test_a_long_video_is_scanned_in_segments_on_the_workers_and_lands_where_the_truth_does(tmp_path):
    """One video cut into two segments, each scanned by a worker with its own estimator, joined
    by registration: one panorama of both, every keyframe placed within 2 px of the exact
    homographies (as the one-process stitch places them), and the rolling shutter's line said."""
    video = tmp_path / "flight.mp4"
    mosaic_run("simulate", "-p", "survey", "-n", "240", "--size", "320x180", "-o", video, "-q", "--seed", "3", "--preset", "ultrafast")
    truth = load_ground_truth(video).map_to_frame
    placed = {}
    for name, cluster in (("alone", ClusterOptions()), ("workers", ClusterOptions(workers=2, segment_frames=100))):
        options = StitchOptions(estimator="orb", compose=ComposeOptions(tile=128), cluster=cluster, rolling_shutter="auto")
        js = tmp_path / f"{name}.json"
        result = stitch(video, tmp_path / f"{name}.png", options=options, transforms=js, show_progress=False)
        frames = json.loads(js.read_text())["frames"]
        indices, H = [f["index"] for f in frames], [np.array(f["H"]) for f in frames]
        placed[name] = (result, indices, placement_errors(indices, H, truth, (320, 180), gap=1))
    (alone, _, alone_err), (spread, spread_at, spread_err) = placed["alone"], placed["workers"]
    assert len(spread.panoramas) == 1 and spread.panoramas[0].segments == 2 and alone.panoramas[0].segments == 1
    assert min(spread_at) < 120 <= max(spread_at)  # keyframes of both segments
    assert spread.frames == alone.frames == 240
    assert spread.rolling is not None  # measured over the whole video once the segments are back
    assert np.median(alone_err) < 2.0 and np.median(spread_err) < 2.0 and np.percentile(spread_err, 90) < 2 * max(np.percentile(alone_err, 90), 2.0)


@pytest.mark.slow
def test_a_segment_with_no_usable_frame_is_scanned_as_one_process_scans_it(tmp_path):
    """A video whose second half is black: its second segment holds no usable frame, so the
    video is scanned here whole, as one process scans it (which names the frames it drops): the
    same transforms, and the same frames reported dropped."""
    full = tmp_path / "full.mp4"
    mosaic_run("simulate", "-p", "survey", "-n", "240", "--size", "320x180", "-o", full, "-q", "--seed", "3", "--preset", "ultrafast")
    video = tmp_path / "half_black.mp4"
    reader = cv2.VideoCapture(str(full))
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (320, 180))
    for k in range(240):
        ok, frame = reader.read()
        assert ok
        writer.write(frame if k < 120 else np.zeros_like(frame))  # the second segment (frames 120-239) all black
    writer.release()
    reader.release()
    results = {}
    for name, cluster in (("alone", ClusterOptions()), ("workers", ClusterOptions(workers=2, segment_frames=100))):
        options = StitchOptions(estimator="orb", compose=ComposeOptions(tile=128), cluster=cluster)
        js = tmp_path / f"{name}.json"
        result = stitch(video, tmp_path / f"{name}.png", options=options, transforms=js, show_progress=False)
        results[name] = (json.loads(js.read_text()), result.dropped, result.frames)
    assert results["workers"] == results["alone"]
    assert results["alone"][1] and max(i for i, _ in results["alone"][1]) >= 120  # the black frames are named


@pytest.mark.slow
def test_a_worker_killed_mid_scan_is_retried_and_the_panorama_is_the_same(tmp_path):
    """A running cluster (``--scheduler``) whose worker is killed while it scans a segment: Dask
    runs the segment again on a fresh worker, and the transforms and panorama are those of the
    same run undisturbed."""
    import threading

    from distributed import Client, LocalCluster

    video = tmp_path / "flight.mp4"
    mosaic_run("simulate", "-p", "survey", "-n", "240", "--size", "320x180", "-o", video, "-q", "--seed", "3", "--preset", "ultrafast")
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None,
                      silence_logs=40) as cluster, Client(cluster) as client:
        options = StitchOptions(estimator="orb", compose=ComposeOptions(tile=128),
                                cluster=ClusterOptions(scheduler=cluster.scheduler_address, segment_frames=100))
        outputs = {}
        for name in ("calm", "killed"):
            killed: list[int] = []
            done = threading.Event()

            def kill_a_scanning_worker(done=done, killed=killed):
                while not done.is_set() and not killed:
                    busy = [(w, k) for w, keys in client.processing().items() for k in keys if "scan_remote" in str(k)]
                    if busy:
                        worker, key = busy[0]
                        os.kill(client.run(os.getpid, workers=[worker])[worker], signal.SIGKILL)
                        killed.append(key)
                    time.sleep(0.02)

            killer = threading.Thread(target=kill_a_scanning_worker) if name == "killed" else None
            if killer is not None:
                killer.start()
            js = tmp_path / f"{name}.json"
            try:
                stitch(video, tmp_path / f"{name}.png", options=options, transforms=js, show_progress=False)
            finally:
                done.set()
                if killer is not None:
                    killer.join()
            outputs[name] = (json.loads(js.read_text()), cv2.imread(str(tmp_path / f"{name}.png"), cv2.IMREAD_UNCHANGED))
            if name == "killed":  # the segment's task was being run when its worker died, and was run again
                assert killed, "no worker was killed during the scan"
                story = client.run_on_scheduler(lambda dask_scheduler, key=killed[0]: [t[2] for t in dask_scheduler.story(key)])
                assert story.count("processing") >= 2, story
    (calm_js, calm), (killed_js, killed_pano) = outputs["calm"], outputs["killed"]
    assert killed_js == calm_js and np.array_equal(killed_pano, calm)


@pytest.mark.slow
def test_a_scheduler_that_does_not_answer_is_one_line_within_10_s(capsys, tmp_path, plain_160x90):
    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    start = time.monotonic()
    code, err = run_cli(capsys, "stitch", plain_160x90, "-o", tmp_path / "p.png", "-q", "--estimator", "orb",
                        "--scheduler", f"tcp://127.0.0.1:{port}")
    assert time.monotonic() - start < 10.0
    assert_one_line_error(code, err, f"--scheduler tcp://127.0.0.1:{port}", "no Dask scheduler answered")
    assert list(tmp_path.iterdir()) == []


def test_a_cluster_whose_workers_cannot_see_the_disk_is_refused(tmp_path):
    class Blind:
        def run(self, function, *args):
            return {"tcp://10.0.0.7:4000": False, "tcp://10.0.0.8:4000": function(*args)}

    with pytest.raises(BadInput, match="1 of the cluster's workers cannot see"):
        _check_shared(Blind(), tmp_path)
    assert list(tmp_path.iterdir()) == []  # the probe file is gone


@pytest.mark.parametrize("workers,scheduler,said", [
    (0, None, "--workers must be 1 or more"),
    (2, "tcp://127.0.0.1:8786", "give one of them"),
    (None, "127.0.0.1:8786", "an address such as tcp://HOST:PORT"),
])
def test_bad_cluster_options_are_one_line(capsys, tmp_path, plain_160x90, workers, scheduler, said):
    args = (["--workers", str(workers)] if workers is not None else []) + (["--scheduler", scheduler] if scheduler else [])
    code, err = run_cli(capsys, "stitch", plain_160x90, "-o", tmp_path / "p.png", "-q", "--estimator", "orb", *args)
    assert_one_line_error(code, err, said)
