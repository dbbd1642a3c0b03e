"""`mosaic bench`: stage timings, accuracy on a simulated flight, JSON report, errors."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from mosaic_cli.bench import run_bench, time_estimator
from mosaic_cli.cli import main
from mosaic_cli.estimators.base import Estimator, PairEstimate
from mosaic_cli.simulate import plan_flight, procedural_map, write_flight


def run_cli(args):
    with pytest.raises(SystemExit) as exc:
        main(args)
    return exc.value.code


@pytest.fixture(scope="module")
def map_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("map") / "map.png"
    cv2.imwrite(str(path), cv2.cvtColor(procedural_map((1024, 1024), seed=4), cv2.COLOR_RGB2BGR))
    return path


def test_bench_command_small_run(tmp_path, map_file, capsys):
    out = tmp_path / "bench.json"
    code = run_cli(["bench", "--frames", "40", "--map", str(map_file), "--size", "640x360", "--estimators", "orb,identity", "--json", str(out)])
    assert code in (0, None)
    report = json.loads(out.read_text())
    assert set(report["estimators"]) == {"orb", "identity"}
    for name, e in report["estimators"].items():
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


def test_bench_default_estimators_skip_missing_learned_ones(tmp_path, map_file):
    report = run_bench(map_path=map_file, frames=6, size=(320, 180), show_progress=False)
    assert {"orb", "identity"} <= set(report["estimators"])
    for name in ("lstm", "cnn"):
        assert name in report["estimators"] or any(note.startswith(name) for note in report["notes"])


def test_bench_on_a_video_reports_latency_only(tmp_path):
    rgb = procedural_map((800, 800), seed=1)
    plan = plan_flight((800, 800), "paper", frames=35, size=(320, 180), seed=1)
    video = tmp_path / "clip.mp4"
    write_flight(video, rgb, plan, show_progress=False)
    scored = run_bench(video=video, estimators=["identity"], frames=35, show_progress=False)
    assert scored["estimators"]["identity"]["mace"] is not None  # ground truth beside it
    (tmp_path / "clip.gt.json").unlink()
    report = run_bench(video=video, estimators=["identity"], frames=8, show_progress=False)
    e = report["estimators"]["identity"]
    assert e["mace"] is None and e["frames"] == 8 and e["ms_per_frame"] > 0


class Batching(Estimator):
    """Holds frames back and answers in batches of 3, like a learned estimator."""

    name = "batching"

    def reset(self, full_size):
        super().reset(full_size)
        self.pending = 0

    def feed(self, frame):
        self.prepare(frame)
        self.pending += 1
        if self.pending == 3:
            self.pending = 0
            return [PairEstimate(np.eye(3), 1.0)] * 3
        return []

    def finish(self):
        return [PairEstimate(np.eye(3), 1.0)] * self.pending

    def _estimate(self, prev, cur):  # pragma: no cover
        raise AssertionError


def test_time_estimator_spreads_batch_time_and_restores_prepare():
    est = Batching(32)
    frames = [np.zeros((18, 32), np.uint8)] * 8
    pairwise, times = time_estimator(est, frames, (32, 18))
    assert len(pairwise) == 8 and len(times.preprocess) == 8 and len(times.estimate) == 8
    assert "prepare" not in est.__dict__  # the instance override is gone


@pytest.mark.parametrize(
    "args,message",
    [
        (["--estimators", "nope"], "unknown estimator"),
        (["--estimators", ""], "empty"),
        (["--estimators", "orb,orb"], "twice"),
        (["--profile", "x"], "unknown profile"),
        (["--frames", "1"], "at least 2"),
        (["--video", "/nonexistent.mp4"], "no such file"),
        (["--map", "/nonexistent.png"], "no such file"),
    ],
)
def test_bench_command_errors(args, message, capsys):
    assert run_cli(["bench", "-q", *args]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
