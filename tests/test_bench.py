"""`mosaic bench`: stage timings, accuracy on a simulated flight, JSON report, errors."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import cli_exit
from mosaic_cli.bench import BenchOptions, run_bench, run_flights, simulated_flight, time_estimator
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import LEARNED, learned
from mosaic_cli.estimators.base import Estimator, PairEstimate, StageTimer
from mosaic_cli.estimators.learned import default_weights
from mosaic_cli.simulate import plan_flight, procedural_map, write_flight


@pytest.fixture(scope="module")
def map_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("map") / "map.png"
    cv2.imwrite(str(path), cv2.cvtColor(procedural_map((1024, 1024), seed=4), cv2.COLOR_RGB2BGR))
    return path


@pytest.mark.slow
def test_bench_command_small_run(tmp_path, map_file, capsys):
    out = tmp_path / "bench.json"
    code = cli_exit(["bench", "--frames", "40", "--map", str(map_file), "--size", "640x360", "--estimators", "orb,identity", "--json", str(out)])
    assert code in (0, None)
    report = json.loads(out.read_text())
    assert set(report["estimators"]) == {"orb", "identity"}
    for e in report["estimators"].values():
        assert e["ms_per_frame"] > 0 and e["fps"] > 0 and e["frames"] == 40
        for stage in ("decode", "preprocess", "estimate"):
            assert set(e["stages"][stage]) >= {"p50", "p95"}
            assert e["stages"][stage]["p95"] >= e["stages"][stage]["p50"] >= 0
        assert {"mace", "corner_error", "failure_rate"} <= set(e)
    orb, ident = report["estimators"]["orb"], report["estimators"]["identity"]
    assert orb["mace"] < 0.25 * ident["mace"]
    assert orb["corner_error"] < 0.25 * ident["corner_error"]
    assert report["source"]["kind"] == "simulated"
    text = capsys.readouterr().out
    assert "orb" in text and "identity" in text


def shipped_weights(name: str) -> bool:
    try:
        default_weights(name)
    except BadInput:
        return False
    return True


@pytest.mark.slow
def test_bench_default_estimators_run_learned_ones_with_weights_and_skip_the_others(tmp_path, map_file):
    report = run_bench(BenchOptions(map_image=map_file, flight=simulated_flight(frames=6, size=(320, 180))), show_progress=False)
    assert {"orb", "identity"} <= set(report["estimators"])
    for name in LEARNED:
        if shipped_weights(name):  # the shipped checkpoint: benchmarked like any other
            assert report["estimators"][name]["frames"] == 6
            assert not any(note.startswith(name) for note in report["notes"])
        else:  # none shipped: a note says why it is missing, and the run still succeeds
            assert name not in report["estimators"]
            assert any(note.startswith(f"{name}: skipped") for note in report["notes"])


def test_bench_names_a_missing_learned_estimator_when_it_was_asked_for(tmp_path, map_file, monkeypatch):
    """Skipping is for the defaults only: a learned estimator named with -e must run or fail."""
    def no_weights(kind):
        raise BadInput(f"no shipped weights for {kind!r} yet")

    monkeypatch.setattr(learned, "default_weights", no_weights)
    with pytest.raises(BadInput, match="no shipped weights"):
        run_bench(BenchOptions(estimators=["cnn"], map_image=map_file, flight=simulated_flight(frames=6, size=(320, 180))), show_progress=False)
    report = run_bench(BenchOptions(map_image=map_file, flight=simulated_flight(frames=6, size=(320, 180))), show_progress=False)
    assert not set(LEARNED) & set(report["estimators"])
    assert sorted(note.split(":")[0] for note in report["notes"] if "skipped" in note) == sorted(LEARNED)


@pytest.mark.slow
def test_bench_on_a_video_reports_latency_only(tmp_path):
    rgb = procedural_map((800, 800), seed=1)
    plan = plan_flight((800, 800), "paper", frames=35, size=(320, 180), seed=1)
    video = tmp_path / "clip.mp4"
    write_flight(video, rgb, plan, show_progress=False)
    scored = run_bench(BenchOptions(estimators=["identity"], video=video, flight=simulated_flight(frames=35)), show_progress=False)
    assert scored["estimators"]["identity"]["mace"] is not None  # ground truth beside it
    (tmp_path / "clip.gt.json").unlink()
    report = run_bench(BenchOptions(estimators=["identity"], video=video, flight=simulated_flight(frames=8)), show_progress=False)
    e = report["estimators"]["identity"]
    assert e["mace"] is None and e["frames"] == 8 and e["ms_per_frame"] > 0


class Batching(Estimator):
    """Holds frames back and answers in batches of 3, like a learned estimator."""

    name = "batching"

    def reset(self, full_size):
        super().reset(full_size)
        self.pending = 0
        self.prepared_frames = 0

    def prepare(self, frame):
        self.prepared_frames += 1
        return super().prepare(frame)

    def feed(self, frame):
        self.prepared(frame)
        self.pending += 1
        if self.pending == 3:
            self.pending = 0
            return [PairEstimate(np.eye(3), 1.0)] * 3
        return []

    def finish(self):
        return [PairEstimate(np.eye(3), 1.0)] * self.pending

    def _estimate(self, prev, cur):  # pragma: no cover
        raise AssertionError


def test_time_estimator_spreads_batch_time_and_leaves_the_estimator_untimed():
    est = Batching(32)
    frames = [np.zeros((18, 32), np.uint8)] * 8
    pairwise, times = time_estimator(est, frames, (32, 18))
    assert len(pairwise) == 8 and len(times.preprocess) == 8 and len(times.estimate) == 8
    assert est.prepared_frames == 8  # every frame prepared once, through the estimator's own timer
    # frames 0-2 and 3-5 come back in batches of 3, frames 6-7 at finish(): each batch's
    # estimation time is shared evenly by its frames, and nothing is lost in the sharing
    for batch in (slice(0, 3), slice(3, 6), slice(6, 8)):
        assert len(set(times.estimate[batch])) == 1 and len(set(times.cpu[batch])) == 1
    assert all(t >= 0 for t in times.preprocess)
    assert est.timings is None  # the benchmark's timer is gone with the run


def test_stage_timer_records_prepare_calls_only_when_set():
    est = Batching(32)
    est.reset((64, 36))
    est.prepared(np.zeros((36, 64), np.uint8))
    assert est.timings is None and est.prepared_frames == 1
    est.timings = StageTimer()
    for _ in range(3):
        est.prepared(np.zeros((36, 64), np.uint8))
    assert len(est.timings.ms["prepare"]) == 3 and est.timings.total("prepare") == sum(est.timings.ms["prepare"])


@pytest.mark.parametrize(
    "args,message",
    [
        (["--estimators", "nope"], "unknown estimator"),
        (["--estimators", ""], "empty"),
        (["--estimators", "orb,orb"], "twice"),
        (["--profile", "x"], "--profile must be one of"),
        (["--frames", "1"], "at least 2"),
        (["--video", "/nonexistent.mp4"], "no such file"),
        (["--map", "/nonexistent.png"], "no such file"),
    ],
)
def test_bench_command_errors(args, message, capsys):
    assert cli_exit(["bench", "-q", *args]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


# --- a folder of flights -------------------------------------------------------------------


@pytest.fixture(scope="module")
def flights_dir(tmp_path_factory):
    """Two short flights of different profiles, each X.mp4 with its X.gt.json, plus a video
    without ground truth (ignored)."""
    folder = tmp_path_factory.mktemp("flights")
    rgb = procedural_map((1400, 1400), seed=2)
    for name, profile, seed in (("a_paper", "paper", 1), ("b_fast", "fast", 2)):
        plan = plan_flight((1400, 1400), profile, frames=64, size=(320, 180), seed=seed)
        write_flight(folder / f"{name}.mp4", rgb, plan, preset="veryfast", show_progress=False)
    plan = plan_flight((1400, 1400), "paper", frames=8, size=(320, 180), seed=3)
    write_flight(folder / "c_nogt.mp4", rgb, plan, preset="veryfast", show_progress=False)
    (folder / "c_nogt.gt.json").unlink()
    return folder


@pytest.mark.slow
def test_flights_pool_what_mosaic_eval_reports_per_flight(tmp_path, flights_dir):
    """bench --flights against `mosaic track` + `mosaic eval` on each flight, combined by hand:
    MACE weighted by landmark pairs, failures by frame pairs, the median corner error from the
    tracks and the ground truth directly."""
    from mosaic_cli.geometry import corner_error
    from mosaic_cli.simulate import load_ground_truth

    out = tmp_path / "bench.json"
    assert cli_exit(["bench", "-q", "--flights", str(flights_dir), "-e", "orb,identity", "--json", str(out)]) in (0, None)
    report = json.loads(out.read_text())
    assert report["source"]["flights"] == ["a_paper", "b_fast"] and report["source"]["profiles"] == ["paper", "fast"]
    for name in ("orb", "identity"):
        evals, corners = {}, []
        for flight in ("a_paper", "b_fast"):
            track, metrics = tmp_path / f"{flight}.{name}.json", tmp_path / f"{flight}.{name}.eval.json"
            assert cli_exit(["track", str(flights_dir / f"{flight}.mp4"), "-e", name, "-o", str(track), "-q"]) in (0, None)
            assert cli_exit(["eval", str(track), "--gt", str(flights_dir / f"{flight}.gt.json"), "--json", str(metrics), "-q"]) in (0, None)
            evals[flight] = json.loads(metrics.read_text())
            gt = load_ground_truth(flights_dir / f"{flight}.gt.json")
            pred = np.array(json.loads(track.read_text())["pairwise"])
            corners.append(corner_error(pred, gt.pairwise, gt.size) * 1280 / gt.size[0])
        e = report["estimators"][name]
        lp = {f: m["landmark_pairs"] for f, m in evals.items()}
        assert min(lp.values()) >= 1
        mace = sum(m["mace"] * lp[f] for f, m in evals.items()) / sum(lp.values())
        failures = sum(m["failure_rate"] * m["pairs"] for m in evals.values()) / sum(m["pairs"] for m in evals.values())
        assert e["mace"] == pytest.approx(mace, rel=1e-9)
        assert e["failure_rate"] == pytest.approx(failures, abs=1e-12)
        assert e["corner_error"] == pytest.approx(float(np.median(np.concatenate(corners))), rel=1e-9)
        assert e["pairs"] == 126 and e["landmark_pairs"] == sum(lp.values())
        assert e["profiles"]["paper"]["mace"] == pytest.approx(evals["a_paper"]["mace"], rel=1e-9)
        assert e["profiles"]["fast"]["mace"] == pytest.approx(evals["b_fast"]["mace"], rel=1e-9)
        assert e["per_flight"]["b_fast"]["corner_error"] == pytest.approx(evals["b_fast"]["corner_error"], rel=1e-9)
        assert e["ms_per_frame"]["p50"] > 0 and e["cpu_ms_per_frame"]["p50"] >= 0
    assert report["estimators"]["orb"]["mace"] < 0.1 * report["estimators"]["identity"]["mace"]


@pytest.mark.slow
def test_flights_estimator_options_and_errors(tmp_path, flights_dir, capsys):
    report = run_flights(BenchOptions(estimators=["orb", "orb:refine=none"], flights=flights_dir), show_progress=False)
    assert list(report["estimators"]) == ["orb", "orb:refine=none"]
    polished, plain = report["estimators"]["orb"], report["estimators"]["orb:refine=none"]
    assert polished["corner_error"] < plain["corner_error"]  # the option reached the estimator
    assert cli_exit(["bench", "-q", "--flights", str(tmp_path)]) == 2
    assert "with an X.gt.json beside it" in capsys.readouterr().err
    assert cli_exit(["bench", "-q", "--flights", str(flights_dir), "-e", "orb:patches=5"]) == 2
    assert "has no option 'patches'" in capsys.readouterr().err
    assert cli_exit(["bench", "-q", "--flights", str(flights_dir), "--video", str(flights_dir / "a_paper.mp4")]) == 2
    assert "not both" in capsys.readouterr().err


# --- the paper's baseline ------------------------------------------------------------------


def load_script():
    from benchmarks import baseline_orb

    return baseline_orb


def test_orb_paper_matches_the_baseline_script(flights_dir):
    """The `orb-paper` estimator against benchmarks/baseline_orb.py (independent of mosaic_cli) on
    the same clip, decoded by OpenCV for both: the same working-resolution homographies and
    confidences (at full resolution they differ by the script's diag(s, s, 1) scaling, which
    ignores pixel centres)."""
    from mosaic_cli.estimators import estimate_stream, make_estimator
    from mosaic_cli.geometry import to_resolution

    clip = str(flights_dir / "b_fast.mp4")
    WIDTH = 320  # the flight's own width: ORB finds its features (at 160 px it fails on most pairs)
    script = load_script().track_baseline(clip, work_width=WIDTH)
    cap = cv2.VideoCapture(clip)
    frames = []
    while True:
        ok, bgr = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    size = (frames[0].shape[1], frames[0].shape[0])
    estimates = list(estimate_stream(make_estimator("orb-paper", work_width=WIDTH), frames, size))
    ours = np.array([e.H for e in estimates])
    theirs = np.array(script["pairwise"])
    assert len(ours) == len(theirs) == 63
    s = size[0] / WIDTH
    down, up = np.diag([1 / s, 1 / s, 1.0]), np.diag([s, s, 1.0])
    small = (WIDTH, WIDTH * size[1] // size[0])
    np.testing.assert_allclose(to_resolution(ours, size, small), down @ theirs @ up, rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose([e.confidence for e in estimates], script["confidence"], rtol=1e-12)
    assert np.any(np.abs(theirs - np.eye(3)).max(axis=(1, 2)) > 1e-3)  # it did estimate motion
    # Both copies could share a mistake (a direction, a scale): the exact ground truth of the
    # simulated flight says they estimate the motion that was flown.
    from mosaic_cli.evaluate import corner_errors
    from mosaic_cli.simulate import load_ground_truth

    gt = load_ground_truth(clip)
    errors = corner_errors(ours, np.asarray(gt.pairwise), size)
    identity = corner_errors(np.broadcast_to(np.eye(3), ours.shape), np.asarray(gt.pairwise), size)
    assert np.median(errors) < 0.35 * np.median(identity)  # (a reversed direction would double it)
