"""Loss terms and the per-variant objective.

Consistent inputs come from frames that are exact integer translations of one texture, so the
true homography of every frame pair is known exactly and bilinear sampling is exact too.  An
"oracle" network measures each patch pair's shift by phase correlation (OpenCV), independently
of the code under test: with it every term must vanish; a wrong direction or scale must not.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from conftest import textured_image
from mosaic_cli.geometry import chain as np_chain
from mosaic_cli.geometry.tensor import cumulative, frame_corners
from mosaic_cli.model import VARIANTS, HomographyNet, NetConfig
from mosaic_cli.model.patches import homography_to_offsets
from mosaic_cli.train.losses import (
    band_pass,
    chain_consistency,
    corner_distance,
    photometric,
    scale_consistency,
    spatial_consistency,
    temporal_smoothness,
)
from mosaic_cli.train.objective import LossWeights, Objective

pytestmark = pytest.mark.usefixtures("one_torch_thread")

W, H_ = 320, 180
CORNERS = frame_corners(W, H_)
STEP = (3, -2)  # content moves by (+3, -2) px per frame: H t -> t+1 is a translation by STEP


@pytest.fixture(scope="module")
def panning_frames():
    """(1, 6, 1, 180, 320) in [-1, 1]: frame t+1 shows at x + STEP what frame t shows at x."""
    gray = cv2.cvtColor(textured_image(420, 260, seed=3), cv2.COLOR_RGB2GRAY).astype(np.float32)
    frames = []
    for t in range(6):
        x0, y0 = 50 - STEP[0] * t, 40 - STEP[1] * t
        frames.append(gray[y0 : y0 + H_, x0 : x0 + W])
    return torch.tensor(np.stack(frames) / 127.5 - 1.0)[None, :, None]


def translation(dx, dy):
    return torch.tensor([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])


class PhaseOracle(nn.Module):
    """Offsets = the shift between the two channels of each patch pair, by cv2.phaseCorrelate."""

    def __init__(self, flip: bool = False):
        super().__init__()
        self.flip = flip

    def forward(self, patches, state=None):
        N, T = patches.shape[:2]
        out = torch.zeros(N, T, 4, 2)
        window = cv2.createHanningWindow(patches.shape[-1:] * 2, cv2.CV_64F)
        for n in range(N):
            for t in range(T):
                a, b = (patches[n, t, c].double().numpy() for c in (0, 1))
                (dx, dy), _ = cv2.phaseCorrelate(a, b, window)
                out[n, t] = torch.tensor([dx, dy]) * (-1 if self.flip else 1)
        return out, None


def batch_of(frames, positions):
    return {"frames": frames, "positions": torch.tensor([positions])}


# --- the terms one by one ----------------------------------------------------------------


@pytest.mark.slow
def test_photometric_formula_and_mask():
    torch.manual_seed(0)
    target = torch.rand(3, 1, 16, 16)
    warped = target + 0.1 * torch.randn(3, 1, 16, 16)
    mask = torch.ones(3, 1, 16, 16)
    expected = torch.sqrt(((target - warped) ** 2).flatten(1).sum(1) + 1e-6).mean()
    torch.testing.assert_close(photometric(target, warped, mask), expected)
    torch.testing.assert_close(photometric(target, warped, mask, "l1"), (target - warped).abs().mean())
    assert float(photometric(target, target, mask)) == pytest.approx(1e-3)
    # pixels outside the frame do not count, whatever their values; the rest count as a full patch
    mask[:, :, :, 8:] = 0
    garbage = warped.clone()
    garbage[:, :, :, 8:] = 100.0
    half = torch.sqrt(((target - warped)[..., :8] ** 2).flatten(1).sum(1) * 2 + 1e-6).mean()
    torch.testing.assert_close(photometric(target, garbage, mask), half)


def test_corner_distance_counts_projective_terms_in_pixels():
    I = torch.eye(3)
    assert float(corner_distance(I, translation(1.0, 0.0), CORNERS)) == pytest.approx(4.0)  # 4 corners x 1 px
    tilt = torch.eye(3)
    tilt[2, 0] = 1e-4  # a raw-entry L1 would call this 1e-4; it moves the right edge by ~10 px
    assert float(corner_distance(I, tilt, CORNERS)) > 10.0


def perturbed(H, scale, seed):
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn(H.shape, generator=g, dtype=H.dtype) * torch.tensor([[1e-3, 1e-3, 0.5], [1e-3, 1e-3, 0.5], [1e-6, 1e-6, 0]])
    return (H + scale * noise).requires_grad_()


def assert_positive_with_finite_gradient(value, leaf):
    assert float(value.detach()) > 0
    value.backward()
    assert torch.isfinite(leaf.grad).all() and leaf.grad.abs().sum() > 0


def test_spatial_consistency():
    same = translation(3, -2).expand(2, 3, 4, 3, 3)  # (B, M, T, 3, 3), every patch agrees
    assert float(spatial_consistency(same, CORNERS)) == 0.0
    assert float(spatial_consistency(same[:, :1], CORNERS)) == 0.0  # one patch: nothing to compare
    H = perturbed(same, 1.0, 0)
    assert_positive_with_finite_gradient(spatial_consistency(H, CORNERS), H)


def test_scale_consistency():
    parent = translation(3, -2).expand(2, 1, 3, 3, 3)
    children = parent.unsqueeze(-3).expand(2, 1, 3, 4, 3, 3)
    assert float(scale_consistency(parent, children, CORNERS)) == 0.0
    C = perturbed(children, 1.0, 1)
    assert_positive_with_finite_gradient(scale_consistency(parent, C, CORNERS), C)


def test_temporal_smoothness():
    steady = translation(3, -2).expand(2, 1, 5, 3, 3)
    assert float(temporal_smoothness(steady, CORNERS)) == 0.0
    H = perturbed(steady, 1.0, 2)
    assert_positive_with_finite_gradient(temporal_smoothness(H, CORNERS), H)


def test_chain_matches_numpy_chain():
    rng = np.random.default_rng(0)
    pairwise = np.eye(3) + rng.normal(0, [[0.01, 0.01, 2], [0.01, 0.01, 2], [1e-5, 1e-5, 0]], (2, 5, 3, 3))
    chained = cumulative(torch.tensor(pairwise)).numpy()
    for b in range(2):
        for s in range(1, 6):
            np.testing.assert_allclose(chained[b, s], np_chain(list(pairwise[b]), 0, s), rtol=1e-10, atol=1e-10)


def test_chain_consistency(panning_frames):
    positions = torch.tensor([[[96, 26], [40, 30]]])
    K = panning_frames.shape[1]
    exact = translation(*STEP).expand(1, 2, K - 1, 3, 3)
    assert float(chain_consistency(panning_frames, exact, positions, 128)) < 2e-3  # sqrt(1e-6) floor
    # each pair off by a third of a pixel: invisible pair by pair, but the chain drifts
    H = (exact @ translation(0.3, 0.0)).requires_grad_()
    assert_positive_with_finite_gradient(chain_consistency(panning_frames, H, positions, 128), H)
    drift = [float(chain_consistency(panning_frames[:, :k], exact[:, :, : k - 1] @ translation(0.3, 0.0), positions, 128)) for k in (3, 6)]
    assert drift[1] > drift[0]


# --- the objective end to end ------------------------------------------------------------


def test_oracle_makes_every_term_vanish(panning_frames):
    frames = panning_frames[:, :4]
    objective = Objective("reg-all", window=4)
    out = objective(PhaseOracle(), batch_of(frames, [(96, 26), (20, 40)]))
    assert set(out) == {"photometric", "spatial", "scale", "temporal1", "temporal2", "total"}
    # phase correlation is good to ~0.1 px per coordinate; these are sums over 4 corners x 2
    for name in ("spatial", "scale", "temporal1"):
        assert float(out[name]) < 1.0, out
    for name in ("photometric", "temporal2"):
        assert float(out[name]) < 1.0, out  # an L2 norm over 16384 pixels in [-1, 1]
    # the same net read in the wrong direction: frame t+1 -> t
    wrong = Objective("reg-t", window=4)(PhaseOracle(flip=True), batch_of(frames, [(96, 26)]))
    assert float(wrong["photometric"]) > 20 * float(out["photometric"]) and float(wrong["temporal2"]) > 20 * float(out["temporal2"])


@pytest.mark.slow
@pytest.mark.parametrize("space", ["gray", "band"])
def test_gradient_descent_on_the_photometric_loss_finds_the_true_homography(space):
    """Free corner offsets, optimised on one frame pair related by a known homography (rotation,
    zoom, tilt and shift): the loss and its gradient lead to the true offsets.  In the band
    space, also when the second frame is darker, lower in contrast and vignetted."""
    W_, H_ = 320, 180
    tex = cv2.GaussianBlur(cv2.cvtColor(textured_image(600, 400, seed=5), cv2.COLOR_RGB2GRAY), (0, 0), 2.0)
    x, y = 100, 80
    c = np.array([[1, 0, W_ / 2 - 0.5], [0, 1, H_ / 2 - 0.5], [0, 0, 1.0]])
    angle, zoom = 0.015, 1.02
    rot = np.array([[zoom * np.cos(angle), -zoom * np.sin(angle), 4.0], [zoom * np.sin(angle), zoom * np.cos(angle), -3.0], [0, 0, 1]])
    tilt = np.array([[1, 0, 0], [0, 1, 0], [1e-5, -2e-5, 1.0]])
    truth = c @ tilt @ rot @ np.linalg.inv(c)  # frame 0 -> frame 1
    to_texture = np.array([[1, 0, x], [0, 1, y], [0, 0, 1.0]])
    f0 = cv2.warpPerspective(tex, to_texture, (W_, H_), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    f1 = cv2.warpPerspective(tex, to_texture @ np.linalg.inv(truth), (W_, H_), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    if space == "band":
        yy, xx = np.mgrid[:H_, :W_]
        vignette = 1 - 0.4 * (((xx - W_ / 2) / (W_ / 2)) ** 2 + ((yy - H_ / 2) / (H_ / 2)) ** 2) / 2
        f1 = 0.6 * f1 * vignette + 20
    frames = torch.tensor(np.stack([f0, f1]), dtype=torch.float32)[None, :, None] / 127.5 - 1

    class FreeOffsets(nn.Module):
        def __init__(self):
            super().__init__()
            self.offsets = nn.Parameter(torch.zeros(4, 2))

        def forward(self, patches, state=None):
            return self.offsets.expand(*patches.shape[:2], 4, 2), None

    model, objective = FreeOffsets(), Objective("base", photometric_space=space)
    optimiser = torch.optim.Adam(model.parameters(), lr=0.1)
    for _ in range(150):
        loss = objective(model, batch_of(frames, [(96, 26)]))["total"]
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    expected = homography_to_offsets(torch.tensor(truth), torch.tensor([96, 26]), 128).float()
    assert (model.offsets.detach() - expected).abs().max() < 0.1, (model.offsets, expected)


def test_band_pass_is_blind_to_gain_and_offset_and_keeps_the_shift(panning_frames):
    frames = panning_frames[0, :2]  # (2, 1, h, w)
    band = band_pass(frames)
    assert band.shape == frames.shape
    rms = band.square().mean(dim=(-1, -2)).sqrt()
    torch.testing.assert_close(rms, torch.ones_like(rms), atol=5e-3, rtol=0)  # but for the 1e-4 floor
    torch.testing.assert_close(band_pass(0.5 * frames - 0.3), band, atol=1e-2, rtol=1e-2)
    # OpenCV on the CPU, kornia under autograd (and on a GPU): the same band
    torch.testing.assert_close(band_pass(frames.clone().requires_grad_()).detach(), band, atol=1e-3, rtol=1e-3)
    # the band of frame 1 is the band of frame 0 moved by STEP (away from the blur's borders)
    a = band[0, 0, 40:-40, 40:-40]
    b = band[1, 0, 40 + STEP[1] : H_ - 40 + STEP[1], 40 + STEP[0] : W - 40 + STEP[0]]
    torch.testing.assert_close(a, b, atol=0.05, rtol=0)


def test_oracle_makes_the_band_terms_vanish_too(panning_frames):
    frames = panning_frames[:, :4]
    objective = Objective("reg-all", window=4, photometric_space="band")
    out = objective(PhaseOracle(), batch_of(frames, [(96, 26), (20, 40)]))
    wrong = Objective("reg-t", window=4, photometric_space="band")(PhaseOracle(flip=True), batch_of(frames, [(96, 26)]))
    for name in ("photometric", "temporal2"):
        assert float(wrong[name]) > 20 * float(out[name]), (out, wrong)
    with pytest.raises(ValueError, match="photometric_space"):
        Objective("base", photometric_space="color")


def test_scale_term_halves_child_offsets(panning_frames):
    objective = Objective("reg-s")
    frames = panning_frames[:, :2]
    good = objective(PhaseOracle(), batch_of(frames, [(96, 26)]))
    # children read at the parent's scale (offsets not halved) must disagree by |STEP| per corner
    objective.child_offset_scale = 1.0
    bad = objective(PhaseOracle(), batch_of(frames, [(96, 26)]))
    assert float(good["scale"]) < 1.0 and float(bad["scale"]) == pytest.approx(4 * (abs(STEP[0]) + abs(STEP[1])), rel=0.1)


@pytest.mark.parametrize("variant", VARIANTS)
def test_every_variant_trains(variant, panning_frames):
    objective = Objective(variant, window=3 if variant not in ("base", "reg-p", "reg-s") else None)
    assert objective.head == ("lstm" if variant.startswith("lstm") else "cnn")
    assert objective.positions == (2 if variant in ("reg-p", "reg-all", "lstm-reg-all") else 1)
    assert Objective(variant).window == (2 if variant in ("base", "reg-p", "reg-s") else 16)
    torch.manual_seed(0)
    model = HomographyNet(NetConfig(head=objective.head))
    positions = [(96, 26), (30, 40)][: objective.positions]
    out = objective(model, batch_of(panning_frames[:, : objective.window], positions))
    terms = {k: v for k, v in out.items() if k != "total"}
    weights = objective.weights
    torch.testing.assert_close(out["total"], sum(weights[k] * v for k, v in terms.items()))
    out["total"].backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert model.regressor.weight.grad.abs().sum() > 0


def test_lstm_reg_t_is_the_lstm_with_the_temporal_terms_alone(panning_frames):
    objective = Objective("lstm-reg-t", window=4)
    assert objective.head == "lstm" and objective.positions == 1 and Objective("lstm-reg-t").window == 16
    out = objective(HomographyNet(NetConfig(head="lstm")), batch_of(panning_frames[:, :4], [(96, 26)]))
    assert set(out) == {"photometric", "temporal1", "temporal2", "total"}


def test_loss_weights_default_to_the_paper_and_can_be_overridden():
    assert LossWeights().resolved() == {"photometric": 1.0, "spatial": 1 / 9, "scale": 1 / 9, "temporal1": 1 / 9, "temporal2": 1.0}
    assert LossWeights(spatial=0.5, temporal2=None).resolved()["spatial"] == 0.5
    assert Objective("reg-all", LossWeights(temporal1=2.0)).weights["temporal1"] == 2.0
    with pytest.raises(ValueError):
        Objective("reg-q")
    with pytest.raises(ValueError):
        Objective("reg-p", positions=1)


def test_patches_outside_the_frame_are_refused(panning_frames):
    model = HomographyNet(NetConfig())
    for bad in ([(193, 0)], [(0, 53)], [(-1, 0)]):
        with pytest.raises(ValueError, match="inside"):
            Objective("base")(model, batch_of(panning_frames[:, :2], bad))
