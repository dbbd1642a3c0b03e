"""The learned estimator: streaming inference equals one plain forward pass, the patch
homography reaches full resolution exactly, consensus, confidence, failures, and ``mosaic track
--weights`` end to end.  Trained weights are not needed: a random net checks the plumbing
exactly, and a phase-correlation "net" (OpenCV, independent of mosaic) checks the geometry."""

from __future__ import annotations

import json
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from conftest import textured_image, write_clip
from mosaic_cli.cli import main
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import estimate_stream, make_estimator, weights
from mosaic_cli.estimators.learned import LearnedConfig, LearnedEstimator, default_weights, make_learned_estimator
from mosaic_cli.geometry import corner_error, four_point_to_homography, rect_corners, to_resolution
from mosaic_cli.model import HomographyNet, NetConfig, save_weights

pytestmark = pytest.mark.usefixtures("one_torch_thread")

FULL, WORK = (640, 360), (320, 180)
STEP_FULL = (6, -4)  # content moves by this many full-resolution pixels per frame


@pytest.fixture(scope="module")
def panning():
    """Eight 640x360 RGB frames: frame t+1 shows at x + STEP_FULL what frame t shows at x."""
    tex = textured_image(760, 480, seed=11)
    return [tex[60 - STEP_FULL[1] * t : 60 - STEP_FULL[1] * t + FULL[1], 60 - STEP_FULL[0] * t : 60 - STEP_FULL[0] * t + FULL[0]] for t in range(8)]


def checkpoint(tmp_path, head="lstm", seed=0):
    torch.manual_seed(seed)
    model = HomographyNet(NetConfig(head=head))
    path = tmp_path / f"{head}.safetensors"
    save_weights(path, model, model.config, "lstm-reg-all" if head == "lstm" else "reg-all")
    return path, model.eval()


def run(estimator, frames, size=FULL):
    estimates = list(estimate_stream(estimator, frames, size))
    return np.array([e.H for e in estimates]), np.array([e.confidence for e in estimates])


class PhaseNet(nn.Module):
    """Stands in for a trained net: the offsets are the patch pair's shift by phase correlation."""

    def __init__(self, bias=None):
        super().__init__()
        self.config = SimpleNamespace(patch=128, head="cnn")
        self.head = "cnn"
        self.bias = bias  # optional per-call offset added to the k-th patch: a deliberately wrong one
        self.dummy = nn.Parameter(torch.zeros(1))

    def features(self, pairs):
        window = cv2.createHanningWindow((128, 128), cv2.CV_64F)
        shifts = [cv2.phaseCorrelate(p[0].double().numpy(), p[1].double().numpy(), window)[0] for p in pairs]
        return torch.tensor(shifts, dtype=torch.float32)

    def step(self, features, state=None):
        offsets = features[..., None, :].expand(*features.shape[:-1], 4, 2).clone()
        if self.bias is not None:
            offsets = offsets + self.bias(offsets)
        return offsets, None


def phase_estimator(**kw):
    kw.setdefault("refine", None)  # the network's own estimate (the polish has tests of its own)
    kw.setdefault("fallback", "none")  # the learned path alone (the fallback has tests of its own)
    return LearnedEstimator(PhaseNet(kw.pop("bias", None)), {"variant": "phase", "work_size": WORK}, "cpu", LearnedConfig(**kw))


# --- streaming inference is exact ------------------------------------------------------


def reference_lstm(model, frames):
    """The paper's test-time procedure written out plainly: centre 128 patch of the 320x180 gray
    frame, one LSTM pass over the whole video, DLT (numpy), full resolution."""
    gray = [cv2.resize(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY), WORK, interpolation=cv2.INTER_AREA) for f in frames]
    patches = [torch.tensor(g[26:154, 96:224], dtype=torch.float32) * (2 / 255) - 1 for g in gray]
    pairs = torch.stack([torch.stack([a, b]) for a, b in zip(patches[:-1], patches[1:])])[None]
    with torch.no_grad():
        offsets, _ = model(pairs)
    corners = rect_corners(95.5, 25.5, 128, 128)
    H_work = four_point_to_homography(corners, offsets[0].double().numpy())
    return to_resolution(H_work, WORK, FULL)


@pytest.mark.parametrize("chunk", [1, 3, 16])
def test_streaming_equals_one_pass_over_the_video(tmp_path, panning, chunk):
    path, model = checkpoint(tmp_path)
    # A random net's estimates do not register the frames: min_zncc=None keeps them (not failures).
    estimator = make_learned_estimator("lstm", weights=path, device="cpu", config=LearnedConfig(chunk=chunk, refine=None, min_zncc=None, prior="none"))
    assert estimator.name == "lstm-reg-all" and estimator.input_width == 320
    H, conf = run(estimator, panning)
    assert H.shape == (7, 3, 3) and np.all((conf >= 0) & (conf <= 1))
    np.testing.assert_allclose(H, reference_lstm(model, panning), rtol=1e-4, atol=1e-4)
    # a second video starts from a fresh state: same result again
    H2, _ = run(estimator, panning)
    np.testing.assert_allclose(H2, H, rtol=1e-6, atol=1e-6)


def test_reset_every_restarts_the_lstm(tmp_path, panning):
    path, model = checkpoint(tmp_path)
    estimator = make_learned_estimator("lstm", weights=path, device="cpu", config=LearnedConfig(chunk=5, reset_every=3, refine=None, min_zncc=None, prior="none"))
    H, _ = run(estimator, panning)
    segments = [reference_lstm(model, panning[s : s + 4]) for s in (0, 3)] + [reference_lstm(model, panning[6:8])]
    np.testing.assert_allclose(H, np.concatenate(segments), rtol=1e-4, atol=1e-4)
    carried, _ = run(make_learned_estimator("lstm", weights=path, device="cpu", config=LearnedConfig(refine=None, min_zncc=None, prior="none")), panning)
    assert not np.allclose(carried[3:], H[3:], atol=1e-7)


# --- geometry, consensus, confidence, failures -------------------------------------------


def translation(dx, dy):
    return np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])


@pytest.mark.parametrize("patches", [1, 5, 9])
def test_patch_homography_reaches_full_resolution_exactly(panning, patches):
    H, conf = run(phase_estimator(patches=patches, chunk=4), panning)
    truth = translation(*STEP_FULL)
    # the direction is frame t -> t+1, in full-resolution pixels
    assert np.abs(H - truth).max() < 0.3, H[0]
    assert conf.min() > 0.6


def test_consensus_ignores_one_wrong_patch(panning):
    def one_wrong(offsets):  # the second patch (top-left corner) is off by 15 px
        wrong = torch.zeros_like(offsets)
        wrong[1] = 15.0
        return wrong

    H, conf = run(phase_estimator(patches=5, bias=one_wrong), panning)
    assert np.abs(H - translation(*STEP_FULL)).max() < 0.3
    assert conf.min() > 0.6


def test_confidence_tells_registered_from_not(panning):
    _, good = run(phase_estimator(), panning)
    _, none = run(phase_estimator(bias=lambda o: -o), panning)  # predicts no motion at all
    assert good.min() > 0.6 and none.max() < 0.2
    _, split = run(phase_estimator(patches=5, bias=lambda o: torch.randn_like(o) * 8), panning)
    assert split.max() < 0.5  # patches that disagree lower the confidence


@pytest.mark.parametrize("bad", [float("nan"), 300.0])
def test_invalid_estimates_become_identity_with_zero_confidence(panning, bad):
    def broken(offsets):
        out = torch.zeros_like(offsets)
        out[..., 0, :] = bad  # NaN, or the TL corner thrown across the frame (a folded quad)
        return out

    H, conf = run(phase_estimator(bias=broken), panning)
    assert np.all(np.isfinite(H))
    np.testing.assert_array_equal(H, np.broadcast_to(np.eye(3), H.shape))
    assert np.all(conf == 0)


@pytest.mark.parametrize("refine", [None, "lk"])
def test_a_cut_to_unrelated_ground_is_a_failed_pair_not_a_weak_one(panning, refine):
    """Whatever a net says across a cut, the registered detail does not correlate: the pair is
    reported as failed (identity, confidence exactly 0), which is what stitch and stabilize
    look for, while the pairs on either side of the cut stay confident."""
    other = textured_image(*FULL, seed=99)
    frames = panning[:4] + [np.roll(other, 6 * k, axis=1) for k in range(4)]
    H, conf = run(phase_estimator(refine=refine), frames)
    assert conf[3] == 0.0
    np.testing.assert_array_equal(H[3], np.eye(3))
    assert np.delete(conf, 3).min() > 0.5


SPOILERS = {
    "blurred": lambda f: cv2.GaussianBlur(f, (0, 0), 6),
    "dark": lambda f: (f * 0.04).astype(np.uint8),
    "black": lambda f: np.zeros_like(f),
    "over-exposed": lambda f: np.clip(f.astype(int) * 4 + 120, 0, 255).astype(np.uint8),
    "white": lambda f: np.full_like(f, 255),
    "textureless": lambda f: np.full_like(f, 128),
}


@pytest.mark.slow
@pytest.mark.parametrize("spoil", SPOILERS)
def test_the_shipped_default_is_right_or_says_it_is_unsure_on_spoiled_frames(spoil):
    """The shipped default weights, with frames 5 and 6 of a known pan spoiled: every estimate
    is finite, and each is either right (within 1 px) or flagged (confidence under 0.5); the
    pairs that touch a frame with nothing to register (black, white, blank, too dark) are placed
    by the motion carried over from the frames before (the pan's, exactly), at the low
    confidence that says nothing in the frames confirmed them."""
    tex = textured_image(800, 480, seed=11)
    frames = [tex[60 + 4 * t : 420 + 4 * t, 100 - 6 * t : 740 - 6 * t] for t in range(12)]  # (6, -4) px a frame
    frames[5], frames[6] = SPOILERS[spoil](frames[5]), SPOILERS[spoil](frames[6])
    H, conf = run(make_estimator("lstm", device="cpu"), frames)
    assert np.all(np.isfinite(H)) and np.all(np.isfinite(conf))
    errors = np.array([corner_error(h, translation(6, -4), FULL) for h in H])
    assert np.all((errors < 1.0) | (conf < 0.5)), (errors, conf)
    clean = [0, 1, 2, 3, 7, 8, 9, 10]
    assert errors[clean].max() < 0.5 and conf[clean].min() > 0.9
    if spoil in ("black", "white", "textureless", "dark"):
        assert errors[4:7].max() < 0.5, errors
        assert np.all(conf[4:7] == LearnedConfig().carry_confidence)
    else:
        assert conf[4] < 0.5  # a sharp frame and a spoiled one do not register as sure


# --- the motion prior, the ablation seeds and the classical fallback ------------------------

FAST_FULL = (36, -8)  # full-resolution px per frame: (18, -4) at the working width


@pytest.fixture(scope="module")
def fast_panning():
    """Ten 640x360 frames panning (36, -8) px a frame: beyond what a polish finds from the identity."""
    tex = textured_image(1100, 560, seed=5)
    x0, y0 = 20 + 9 * FAST_FULL[0], 100
    return [tex[y0 - FAST_FULL[1] * t : y0 - FAST_FULL[1] * t + FULL[1], x0 - FAST_FULL[0] * t : x0 - FAST_FULL[0] * t + FULL[0]]
            for t in range(10)]


def short_sighted(offsets):
    """A net that, like one trained on slow flights, sees at most 3 working px of motion."""
    return offsets.clamp(-3.0, 3.0) - offsets


def errors_against(H, truth):
    return np.array([corner_error(h, truth, FULL) for h in H])


def test_the_motion_prior_lets_a_short_sighted_net_follow_a_fast_pan(fast_panning):
    """prior=velocity pre-aligns frame t+1 by the last confirmed motion, so the network only has
    to see what changed: a net that sees 3 px tracks an 18 px/frame pan once the motion
    is known (here from the classical fallback on the first chunk), and without the prior it cannot."""
    truth = translation(*FAST_FULL)
    with_prior = phase_estimator(bias=short_sighted, prior="velocity", fallback="orb", refine="lk", chunk=3)
    H, conf = run(with_prior, fast_panning)
    assert errors_against(H, truth).max() < 0.5 and conf.min() > 0.3
    # the first chunk (3 pairs) has no prior yet; every later one is pre-aligned by the last motion
    assert with_prior.path_counts == {"learned": 6, "fallback": 3, "carried": 0, "failed": 0}
    assert sum(with_prior.path_counts.values()) == len(H)
    alone = phase_estimator(bias=short_sighted, prior="none", fallback="none", refine="lk")
    H, conf = run(alone, fast_panning)
    assert np.all(errors_against(H[conf > 0], truth) > 5) or np.all(conf == 0)
    assert alone.path_counts["failed"] >= 8


def test_the_fallback_takes_the_pairs_the_learned_path_cannot_confirm(fast_panning):
    """A net that predicts no motion at all: every pair goes to ORB, which gets it right, and the
    counts say so; without the fallback the same pairs are failures (identity, confidence 0)."""
    def blind(offsets):
        return -offsets

    truth = translation(*FAST_FULL)
    est = phase_estimator(bias=blind, prior="none", fallback="orb", refine="lk")
    H, conf = run(est, fast_panning)
    assert errors_against(H, truth).max() < 0.5 and conf.min() > 0.3
    assert est.path_counts == {"learned": 0, "fallback": 9, "carried": 0, "failed": 0}
    est = phase_estimator(bias=blind, prior="none", fallback="none", refine="lk")
    H, conf = run(est, fast_panning)
    np.testing.assert_array_equal(H, np.broadcast_to(np.eye(3), H.shape))
    assert np.all(conf == 0) and est.path_counts["failed"] == 9


def test_the_wide_retry_finds_what_the_cheap_polish_cannot_reach(panning):
    """A net 8 working px off: beyond the cheap polish's 3 px leash, within the wide one's reach.
    retry=none leaves the pair to what the seed alone reaches: failed, without a fallback."""
    def off_by_8(offsets):
        return torch.tensor([8.0, 0.0]).expand_as(offsets)

    truth = translation(*STEP_FULL)
    est = phase_estimator(bias=off_by_8, refine="lk")
    H, conf = run(est, panning)
    assert errors_against(H, truth).max() < 0.3 and conf.min() > 0.2
    assert est.path_counts["learned"] == len(H)
    est = phase_estimator(bias=off_by_8, refine="lk", retry="none")
    H, conf = run(est, panning)
    np.testing.assert_array_equal(H, np.broadcast_to(np.eye(3), H.shape))
    assert np.all(conf == 0) and est.path_counts["failed"] == len(H)


class ExplodingNet(PhaseNet):
    def features(self, pairs):
        raise AssertionError("the network must not run when the seed replaces it")


@pytest.mark.parametrize("start", ["identity", "velocity"])
def test_ablation_starts_replace_the_network_and_nothing_else(panning, start):
    """polish-start=identity / polish-start=velocity: the same polish, confirmation and counts, without the
    network: on a slow pan both find the motion (from the identity, the polish's own reach)."""
    est = LearnedEstimator(ExplodingNet(), {"variant": "phase", "work_size": WORK}, "cpu",
                           LearnedConfig(polish_start=start, fallback="none"))
    H, conf = run(est, panning)
    assert errors_against(H, translation(*STEP_FULL)).max() < 0.3 and conf.min() > 0.5
    assert est.path_counts["learned"] == len(H)


def test_velocity_seed_starts_each_pair_from_the_last_motion(fast_panning):
    """From the identity the polish cannot reach an 18 px motion; once the fallback has found
    it, the velocity seed carries it to every later pair without the fallback."""
    est = LearnedEstimator(ExplodingNet(), {"variant": "phase", "work_size": WORK}, "cpu", LearnedConfig(polish_start="velocity"))
    H, _ = run(est, fast_panning)
    assert errors_against(H, translation(*FAST_FULL)).max() < 0.5
    assert est.path_counts["fallback"] == 1 and est.path_counts["learned"] == 8


@pytest.mark.parametrize("option,value,message", [("polish_start", "zero", "polish-start must be one of"), ("prior", "kalman", "prior must be one of"),
                                                   ("fallback", "sift", "fallback must be one of"), ("retry", "narrow", "retry must be one of")])
def test_bad_ablation_options_are_refused(option, value, message):
    with pytest.raises(BadInput, match=message):
        phase_estimator(**{option: value})


def test_frames_smaller_than_the_patch_are_refused():
    estimator = phase_estimator()
    with pytest.raises(BadInput, match="smaller than"):
        estimator.reset((1000, 300))  # 320x96 at the working width


# --- selection, shipped weights, the command line ----------------------------------------


def test_weights_select_the_estimator(tmp_path):
    path, _ = checkpoint(tmp_path, head="cnn")
    estimator = make_estimator(None, weights=str(path), device="cpu")  # no name: the network the weights hold
    assert isinstance(estimator, LearnedEstimator) and estimator.model.head == "cnn" and estimator.name == "reg-all"
    for classical in ("orb", "orb-ransac", "orb-paper", "identity"):  # never the network instead of what was named
        with pytest.raises(BadInput, match=f"--weights goes with a learned estimator .* -e {classical} takes no weights"):
            make_estimator(classical, weights=str(path), device="cpu")
    with pytest.raises(BadInput, match="holds a cnn"):
        make_learned_estimator("lstm", weights=path)
    with pytest.raises(BadInput, match="--device"):
        make_learned_estimator("cnn", weights=path, device="tpu")
    with pytest.raises(BadInput, match="patches"):
        make_learned_estimator("cnn", weights=path, config=LearnedConfig(patches=4))


def test_default_weights(tmp_path, monkeypatch):
    monkeypatch.setattr(weights, "REPO_MODELS", tmp_path)
    monkeypatch.setattr(weights.importlib.resources, "files", lambda package: tmp_path / "absent")
    monkeypatch.setattr(weights, "Path", _only_under(tmp_path))
    with pytest.raises(BadInput, match="no shipped weights for 'lstm' yet: pass --weights FILE"):
        default_weights("lstm")
    shipped, _ = checkpoint(tmp_path, head="lstm")
    assert default_weights("lstm") == shipped
    assert make_estimator("lstm", device="cpu").model.head == "lstm"


def _only_under(root):
    """A Path that pretends no file exists outside ``root`` (so installed weights do not leak in)."""
    from pathlib import Path

    class Confined(type(Path())):
        def is_file(self):
            return str(self).startswith(str(root)) and super().is_file()

    return Confined


@pytest.mark.slow
def test_track_cli_with_weights(tmp_path, panning):
    path, model = checkpoint(tmp_path)
    clip = write_clip(tmp_path / "pan.mp4", panning, fps=10)
    out = tmp_path / "track.json"
    with pytest.raises(SystemExit) as exit_info:
        main(["track", str(clip), "-o", str(out), "--weights", str(path), "--device", "cpu", "-q"])
    assert exit_info.value.code in (0, None)
    data = json.loads(out.read_text())
    assert data["estimator"] == "lstm-reg-all" and data["frames"] == 8 and data["direction"] == "t_to_t+1"
    pairwise = np.array(data["pairwise"])
    assert pairwise.shape == (7, 3, 3) and np.all(np.isfinite(pairwise))
    # the same numbers as the estimator on the decoded frames
    from mosaic_cli.video import open_video

    with open_video(clip, width=320, gray=True) as stream:
        frames = list(stream)
    direct, _ = run(make_learned_estimator("lstm", weights=path, device="cpu"), frames, FULL)
    np.testing.assert_allclose(pairwise, direct, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize(
    "args,message",
    [
        (["--weights", "{tmp}/missing.safetensors"], "no such weights file"),
        (["--weights", "{clip}"], "not a safetensors checkpoint"),
        (["--weights", "{ckpt}", "--device", "tpu"], "--device"),
    ],
)

def test_track_cli_refuses_bad_weights(tmp_path, panning, capsys, args, message):
    path, _ = checkpoint(tmp_path)
    clip = write_clip(tmp_path / "pan.mp4", panning[:3], fps=10)
    out = tmp_path / "track.json"
    args = [a.format(tmp=tmp_path, clip=clip, ckpt=path) for a in args]
    with pytest.raises(SystemExit) as exit_info:
        main(["track", str(clip), "-o", str(out), *args, "-q"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


@pytest.mark.slow
def test_track_cli_flags_reach_the_estimator(tmp_path, panning, capsys):
    path, _ = checkpoint(tmp_path, head="cnn")
    clip = write_clip(tmp_path / "pan.mp4", panning, fps=10)
    out = tmp_path / "track.json"

    def track(*args):
        with pytest.raises(SystemExit) as exit_info:
            main(["track", str(clip), "-o", str(out), "-q", *args])
        return exit_info.value.code

    from mosaic_cli.video import open_video

    with open_video(clip, width=320, gray=True) as stream:
        frames = list(stream)
    config = LearnedConfig(patches=5, refine=None, chunk=3)
    direct, _ = run(make_learned_estimator("cnn", weights=path, device="cpu", config=config), frames, FULL)
    # through an estimator name with options
    assert track("-e", "cnn:patches=5:refine=none:chunk=3", "--weights", str(path), "--device", "cpu") in (0, None)
    np.testing.assert_allclose(np.array(json.loads(out.read_text())["pairwise"]), direct, rtol=1e-6, atol=1e-6)
    out.unlink()
    for args, message in (
        (["-e", "orb:patches=5"], "has no option 'patches'"),
        (["-e", "lstm:reset-every=0", "--weights", str(path)], "reset-every must be at least 1"),
        (["-e", "cnn:patches=4", "--weights", str(path)], "patches must be one of 1, 5, 9"),
        (["-e", "cnn:refine=sift", "--weights", str(path)], "refine must be one of lk, ecc or none"),
        # track's old flags: refused in one line that says how they are written now
        (["-e", "cnn", "--patches", "5"], "--patches is an estimator setting now: -e cnn:patches=5"),
        (["--chunk", "3"], "--chunk is an estimator setting now: -e lstm:chunk=3"),
        (["-e", "cnn:patches", "--weights", str(path)], "NAME:OPTION=VALUE"),
        (["--weights", str(path), "--threads", "0"], "--threads must be at least 1"),
    ):
        capsys.readouterr()
        assert track(*args) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
        assert not out.exists()
