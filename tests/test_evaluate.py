"""MACE (the paper's protocol), corner error, failure rate, annotations and `mosaic eval`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import cli_exit
from mosaic_cli.errors import BadInput
from mosaic_cli.evaluate import (
    evaluate,
    landmarks_from_ground_truth,
    mace,
    read_annotations,
    write_annotations,
)
from mosaic_cli.simulate import GroundTruth, plan_flight


@pytest.fixture(scope="module")
def gt():
    plan = plan_flight((2048, 2048), "paper", frames=121, size=(640, 360), seed=3)
    return GroundTruth.from_plan(plan, map_name="test")


def test_landmarks_are_exact_and_spread(gt):
    ann = landmarks_from_ground_truth(gt)
    assert ann.shape[1] == 6 and len(ann) >= 30
    assert set(ann[:, 0].astype(int)) == {0, 30, 60, 90}
    assert np.all(ann[:, 3] - ann[:, 0] == 30)
    w, h = gt.size
    assert np.all((ann[:, [1, 4]] >= 0) & (ann[:, [1, 4]] <= w - 1))
    assert np.all((ann[:, [2, 5]] >= 0) & (ann[:, [2, 5]] <= h - 1))
    # central area of frame f1, several distinct points per pair
    assert ann[:, 1].min() >= 0.2 * (w - 1) - 1e-9 and ann[:, 1].max() <= 0.8 * (w - 1) + 1e-9
    assert len(np.unique(ann[ann[:, 0] == 0][:, 1:3], axis=0)) >= 8


def test_mace_of_the_truth_is_zero(gt):
    ann = landmarks_from_ground_truth(gt)
    assert mace(gt.pairwise, ann, gt.size) < 1e-6
    m = evaluate(gt.pairwise, gt)
    assert m["mace"] < 1e-6 and m["corner_error"] < 1e-6 and m["failure_rate"] == 0.0 and m["pairs"] == 120


def test_mace_of_identity_is_the_mean_displacement(gt):
    ann = landmarks_from_ground_truth(gt)
    identity = np.tile(np.eye(3), (gt.frames - 1, 1, 1))
    # computed independently: per (f1, f2) pair mean displacement, then mean over pairs, x 1280/w
    per_pair = {}
    for f1, x1, y1, f2, x2, y2 in ann:
        per_pair.setdefault((f1, f2), []).append(np.hypot(x2 - x1, y2 - y1))
    expected = np.mean([np.mean(v) for v in per_pair.values()]) * 1280 / gt.size[0]
    assert mace(identity, ann, gt.size) == pytest.approx(expected, rel=1e-9)
    assert 20 < expected < 100  # 1-2 px/frame over 30 frames
    m = evaluate(identity, gt)
    assert m["mace"] == pytest.approx(expected, rel=1e-9)


def test_mace_averages_per_pair_then_over_pairs():
    # pair (0, 1) has 3 landmarks with error 1, pair (1, 2) one landmark with error 4
    pairwise = np.tile(np.eye(3), (2, 1, 1))
    ann = np.array(
        [[0, 10, 10, 1, 11, 10], [0, 20, 10, 1, 21, 10], [0, 30, 10, 1, 31, 10], [1, 5, 5, 2, 9, 5]], dtype=float
    )
    assert mace(pairwise, ann, (1280, 720)) == pytest.approx((1 + 4) / 2)
    assert mace(pairwise, ann, (640, 360)) == pytest.approx((1 + 4) / 2 * 2)  # 1280x720-equivalent


def test_mace_chains_estimates():
    T = np.array([[1, 0, 2.0], [0, 1, 1.0], [0, 0, 1]])
    pairwise = np.stack([T, T, T])
    ann = np.array([[0, 100, 100, 3, 106, 103], [3, 106, 103, 0, 100, 100]], dtype=float)
    assert mace(pairwise, ann, (1280, 720)) == pytest.approx(0.0, abs=1e-9)


def test_corner_error_and_failure_rate(gt):
    pred = gt.pairwise.copy()
    shift = np.array([[1, 0, 20.0], [0, 1, 0], [0, 0, 1]])  # 20 px at 640 wide = 40 equivalent
    pred[:12] = shift @ pred[:12]
    m = evaluate(pred, gt)
    assert m["failure_rate"] == pytest.approx(12 / 120)
    assert m["corner_error"] < 1e-6
    assert m["corner_error_mean"] == pytest.approx(12 * 40 / 120, rel=1e-6)


def test_short_prediction_is_scored_on_its_frames(gt):
    m = evaluate(gt.pairwise[:70], gt)
    assert m["pairs"] == 70 and m["frames"] == 71 and m["mace"] < 1e-6
    with pytest.raises(BadInput):
        evaluate(np.tile(np.eye(3), (200, 1, 1)), gt)


def test_non_finite_predictions_count_as_identity(gt):
    pred = gt.pairwise.copy()
    pred[5] = np.nan
    m = evaluate(pred, gt)
    assert m["invalid"] == 1 and np.isfinite(m["mace"])


def test_annotation_round_trip(tmp_path, gt):
    ann = landmarks_from_ground_truth(gt)
    path = tmp_path / "ann.txt"
    write_annotations(path, ann)
    back = read_annotations(path)
    np.testing.assert_allclose(back, ann, atol=1e-4)


def test_read_annotations_formats_and_errors(tmp_path):
    p = tmp_path / "a.txt"
    p.write_text("# header\n0 1 2 30 3 4\n\n30,5,6,60,7,8  # trailing\n")
    np.testing.assert_array_equal(read_annotations(p), [[0, 1, 2, 30, 3, 4], [30, 5, 6, 60, 7, 8]])
    for text, message in [("0 1 2 30 3\n", "expected 6"), ("0 1 x 30 3 4\n", "not a number"), ("0.5 1 2 30 3 4\n", "whole"), ("", "no annotations")]:
        p.write_text(text)
        with pytest.raises(BadInput, match=message):
            read_annotations(p)
    with pytest.raises(BadInput, match="no such file"):
        read_annotations(tmp_path / "missing.txt")


def test_annotations_beyond_the_prediction(gt):
    ann = np.array([[0, 1, 1, 500, 2, 2]], dtype=float)
    with pytest.raises(BadInput, match="frame 500"):
        mace(gt.pairwise, ann, gt.size)


def _write_track(path, pairwise, size):
    path.write_text(json.dumps({"version": 1, "frames": len(pairwise) + 1, "size": list(size), "fps": 30, "estimator": "test",
                                "direction": "t_to_t+1", "pairwise": np.asarray(pairwise).tolist()}))


def test_eval_command_gt_json_and_npy(tmp_path, gt, capsys):
    gt_path = tmp_path / "f.gt.json"
    gt.save(gt_path)
    track = tmp_path / "pred.json"
    _write_track(track, gt.pairwise, gt.size)
    out = tmp_path / "m.json"
    assert cli_exit(["eval", str(track), "--gt", str(gt_path), "--json", str(out)]) in (0, None)
    metrics = json.loads(out.read_text())
    assert metrics["mace"] < 1e-6 and metrics["failure_rate"] == 0 and metrics["pairs"] == 120
    assert "MACE" in capsys.readouterr().out
    npy = tmp_path / "pred.npy"
    np.save(npy, np.tile(np.eye(3), (120, 1, 1)))
    assert cli_exit(["eval", str(npy), "--gt", str(gt_path), "--json", str(out), "-q"]) in (0, None)
    assert json.loads(out.read_text())["mace"] > 10


def test_eval_command_annotations_only(tmp_path, gt):
    ann = tmp_path / "ann.txt"
    write_annotations(ann, landmarks_from_ground_truth(gt))
    npy = tmp_path / "pred.npy"
    np.save(npy, gt.pairwise)
    out = tmp_path / "m.json"
    assert cli_exit(["eval", str(npy), "--annotations", str(ann), "--size", "640x360", "--json", str(out), "-q"]) in (0, None)
    assert json.loads(out.read_text())["mace"] < 1e-3
    track = tmp_path / "pred.json"
    _write_track(track, gt.pairwise, gt.size)
    assert cli_exit(["eval", str(track), "--annotations", str(ann), "--json", str(out), "-q"]) in (0, None)
    assert json.loads(out.read_text())["mace"] < 1e-3


def test_eval_command_errors(tmp_path, gt, capsys):
    gt_path = tmp_path / "f.gt.json"
    gt.save(gt_path)
    track = tmp_path / "pred.json"
    _write_track(track, gt.pairwise, gt.size)
    cases = [
        ([str(track)], "--gt"),
        ([str(tmp_path / "missing.json"), "--gt", str(gt_path)], "no such file"),
        ([str(track), "--gt", str(tmp_path / "missing.gt.json")], "no such file"),
        ([str(gt_path.parent / "x.npy"), "--gt", str(gt_path)], "no such file"),
    ]
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{}")
    cases.append(([str(bad_json), "--gt", str(gt_path)], "pairwise"))
    npy = tmp_path / "p.npy"
    np.save(npy, np.eye(3))
    cases.append(([str(npy), "--gt", str(gt_path)], "shape"))
    ann = tmp_path / "ann.txt"
    ann.write_text("0 1 1 30 2 2\n")
    np.save(tmp_path / "ok.npy", gt.pairwise)
    cases.append(([str(tmp_path / "ok.npy"), "--annotations", str(ann)], "--size"))
    other = tmp_path / "other.json"
    _write_track(other, gt.pairwise, (1280, 720))
    cases.append(([str(other), "--gt", str(gt_path)], "1280x720"))
    # a track of part of the flight (or of another clip) is refused, not scored on what it covers
    short = tmp_path / "short.json"
    _write_track(short, gt.pairwise[:89], gt.size)
    cases.append(([str(short), "--gt", str(gt_path)], f"covers 90 frames but the ground truth {len(gt.pairwise) + 1}"))
    np.save(tmp_path / "long.npy", np.tile(np.eye(3), (len(gt.pairwise) + 30, 1, 1)))
    cases.append(([str(tmp_path / "long.npy"), "--gt", str(gt_path)], f"covers {len(gt.pairwise) + 31} frames"))
    for args, message in cases:
        capsys.readouterr()
        assert cli_exit(["eval", *args]) == 2, args
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, (args, err)


def test_score_is_what_eval_reports_and_every_spaces_the_landmarks(tmp_path, gt):
    """The library's ``score`` (what the command prints) against the metrics computed here from
    their parts: with the ground truth, on landmarks every ``every`` frames; with annotations
    alone, MACE at the track's own frame size."""
    from mosaic_cli.evaluate import EvalOptions, mace_pairs, score

    gt_path = tmp_path / "f.gt.json"
    gt.save(gt_path)
    track = tmp_path / "pred.json"
    identity = np.tile(np.eye(3), (gt.frames - 1, 1, 1))
    _write_track(track, identity, gt.size)
    for every in (30, 20):
        ann = landmarks_from_ground_truth(gt, every=every)
        metrics = score(track, EvalOptions(gt=gt_path, every=every))
        assert metrics["mace"] == pytest.approx(mace(identity, ann, gt.size), rel=1e-12)
        assert metrics["landmarks"] == len(ann) and metrics["prediction"] == str(track)
    assert set(landmarks_from_ground_truth(gt, every=20)[:, 0].astype(int)) == {0, 20, 40, 60, 80, 100}
    annotations = tmp_path / "ann.txt"
    write_annotations(annotations, landmarks_from_ground_truth(gt))
    alone = score(track, EvalOptions(annotations=annotations))
    pairs, errors = mace_pairs(identity, read_annotations(annotations), gt.size)
    assert alone["mace"] == pytest.approx(errors.mean(), rel=1e-12) and alone["landmark_pairs"] == len(pairs)
    np.save(tmp_path / "pred.npy", identity)
    with pytest.raises(BadInput, match="--size"):
        score(tmp_path / "pred.npy", EvalOptions(annotations=annotations))
    assert score(tmp_path / "pred.npy", EvalOptions(annotations=annotations, size=gt.size))["mace"] == pytest.approx(alone["mace"])
