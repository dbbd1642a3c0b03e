"""``mosaic track`` end to end on a rendered flight whose homographies are known exactly."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import Flight, cli_exit, write_clip
from mosaic_cli.estimators import make_estimator
from mosaic_cli.geometry import corner_error, to_resolution
from mosaic_cli.track import load_track

FULL = (640, 360)
WORK = (320, 180)


@pytest.fixture(scope="module")
def hd_flight():
    return Flight(n_frames=16, frame_size=FULL, map_size=(1800, 1400), seed=7)


@pytest.fixture(scope="module")
def hd_clip(tmp_path_factory, hd_flight):
    return write_clip(tmp_path_factory.mktemp("track") / "flight.mp4", hd_flight.frames, fps=25)


def run_track(*args):
    assert cli_exit(["track", *args, "-q"]) == 0


@pytest.mark.slow
def test_track_json_matches_exact_ground_truth(tmp_path, hd_flight, hd_clip):
    out = tmp_path / "track.json"
    run_track(hd_clip, "-o", out)
    data = json.loads(out.read_text())
    assert data["version"] == 1 and data["frames"] == 16 and data["size"] == list(FULL)
    assert data["fps"] == pytest.approx(25.0) and data["direction"] == "t_to_t+1"
    assert data["estimator"] == make_estimator().name  # the default, by the name of what it runs
    assert len(data["pairwise"]) == 15 and len(data["confidence"]) == 15
    assert data["meta"]["ms_per_frame"] > 0
    assert load_track(out).to_json() == data  # the streamed writer and the in-memory document agree
    pairwise = np.array(data["pairwise"])
    assert pairwise.shape == (15, 3, 3) and np.all(np.isfinite(pairwise))
    # pairwise[t] maps frame t to t+1 in full-resolution pixels; judge it at the working resolution
    errors = corner_error(to_resolution(pairwise, FULL, WORK), to_resolution(hd_flight.pairwise, FULL, WORK), WORK)
    assert np.median(errors) < 0.1 and errors.max() < 0.3, errors
    assert min(data["confidence"]) > 0.5
    # the opposite direction would be far off
    inverse = np.linalg.inv(hd_flight.pairwise)
    assert corner_error(pairwise, inverse, FULL).min() > 5


@pytest.mark.slow
def test_track_npy_and_max_frames(tmp_path, hd_flight, hd_clip):
    out = tmp_path / "track.npy"
    run_track(hd_clip, "-o", out, "--max-frames", 6)
    pairwise = np.load(out)
    assert pairwise.shape == (5, 3, 3)
    errors = corner_error(pairwise, hd_flight.pairwise[:5], FULL)
    assert errors.max() < 1.0, errors
    assert sorted(p.name for p in tmp_path.iterdir()) == ["track.npy"]
    assert out.stat().st_mode & 0o777 == 0o666 & ~current_umask()  # not mkstemp's 0600


def current_umask() -> int:
    import os

    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_identity_estimator_and_load_track(tmp_path, hd_clip):
    out = tmp_path / "identity.json"
    run_track(hd_clip, "-o", out, "--estimator", "identity")
    result = load_track(out)
    assert result.frames == 16 and result.estimator == "identity"
    assert np.array_equal(result.pairwise, np.broadcast_to(np.eye(3), (15, 3, 3)))
    assert result.info.source_size == FULL and np.all(result.confidence == 0)


@pytest.mark.slow
def test_track_reads_an_image_folder(tmp_path, flight):
    import cv2

    folder = tmp_path / "frames"
    folder.mkdir()
    for k, frame in enumerate(flight.frames):
        cv2.imwrite(str(folder / f"img{k}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    out = tmp_path / "t.json"
    run_track(folder, "-o", out)
    pairwise = np.array(json.loads(out.read_text())["pairwise"])
    assert len(pairwise) == len(flight.frames) - 1
    assert np.median(corner_error(pairwise, flight.pairwise, flight.frame_size)) < 0.1


def test_a_one_frame_video_says_there_is_no_frame_pair_and_writes_an_empty_track(tmp_path, capsys, texture):
    from mosaic_cli.cli import main

    video = write_clip(tmp_path / "one.mp4", [texture[:64, :96]], fps=10)
    out = tmp_path / "t.json"
    for quiet in ([], ["-q"]):  # said even with -q
        with pytest.raises(SystemExit) as exit_info:
            main(["track", str(video), "-o", str(out), "-e", "orb", *quiet])
        assert exit_info.value.code in (0, None)
        err = capsys.readouterr().err
        warning = f"mosaic: warning: {video} has only 1 frame: no frame pair to track; {out} holds an empty track\n"
        assert warning in err and "confidence" not in err
        data = json.loads(out.read_text())
        assert data["frames"] == 1 and data["pairwise"] == [] and data["confidence"] == []
