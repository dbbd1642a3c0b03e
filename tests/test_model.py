"""The network, the tensor geometry (DLT, projection, chaining) and patch warps (against OpenCV
and the numpy geometry), and the checkpoint format."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry import chain as np_chain
from mosaic_cli.geometry import cumulative as np_cumulative
from mosaic_cli.geometry import four_point_to_homography as np_four_point_to_homography
from mosaic_cli.geometry import project as np_project
from mosaic_cli.geometry import rect_corners
from mosaic_cli.geometry.tensor import cumulative, four_point_to_homography, project
from mosaic_cli.model import HomographyNet, NetConfig, load_weights, read_metadata, save_weights
from mosaic_cli.model.network import count_macs, count_parameters, macs_per_pair
from mosaic_cli.model.patches import (
    crop,
    homography_to_offsets,
    offsets_to_homography,
    patch_corners,
    sample_patches,
    warp_perspective,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def random_quads(rng, n, spread=8.0):
    """Patch corners at random places of a 320x180 frame, and where a random motion takes them."""
    pos = np.stack([rng.integers(0, 193, n), rng.integers(0, 53, n)], -1)
    src = np.array([rect_corners(x - 0.5, y - 0.5, 128, 128) for x, y in pos])
    return pos, src, src + rng.normal(0, spread, src.shape)


def smooth_image(rng, w=320, h=180):
    return cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.5)


# --- DLT ---------------------------------------------------------------------------------


def test_dlt_matches_opencv():
    rng = np.random.default_rng(0)
    _, src, dst = random_quads(rng, 64)
    src_t, dst_t = torch.tensor(src, dtype=torch.float32), torch.tensor(dst, dtype=torch.float32)
    H = four_point_to_homography(src_t, dst_t - src_t).double().numpy()
    for k in range(len(src)):
        ref = cv2.getPerspectiveTransform(src[k].astype(np.float32), dst[k].astype(np.float32))
        ref = ref / ref[2, 2]
        assert np.all(np.abs(H[k] - ref) <= 1e-4 * (1 + np.abs(ref))), (H[k], ref)


def test_dlt_batched_any_leading_shape_and_direction():
    rng = np.random.default_rng(1)
    pos, src, dst = random_quads(rng, 6)
    offsets = torch.tensor(dst - src).reshape(2, 3, 4, 2)
    positions = torch.tensor(pos).reshape(2, 3, 2)
    H = offsets_to_homography(offsets, positions, 128)
    assert H.shape == (2, 3, 3, 3) and H.dtype == torch.float64
    exact = np_four_point_to_homography(src, dst - src).reshape(2, 3, 3, 3)
    np.testing.assert_allclose(H.numpy(), exact, rtol=1e-9, atol=1e-9)
    # H maps the patch corners of frame t onto their displaced positions (t -> t+1), not back
    np.testing.assert_allclose(homography_to_offsets(H, positions, 128).numpy(), offsets.numpy(), atol=1e-8)
    assert patch_corners(torch.tensor([10, 20]), 128).tolist() == [[9.5, 19.5], [137.5, 19.5], [137.5, 147.5], [9.5, 147.5]]


def test_dlt_is_differentiable():
    rng = np.random.default_rng(2)
    pos, src, dst = random_quads(rng, 4)
    offsets = torch.tensor(dst - src, dtype=torch.float32, requires_grad=True)
    H = offsets_to_homography(offsets, torch.tensor(pos), 128)
    H.sum().backward()
    assert torch.isfinite(offsets.grad).all() and offsets.grad.abs().sum() > 0
    one = offsets[:1].detach().double().requires_grad_()
    assert torch.autograd.gradcheck(lambda o: offsets_to_homography(o, torch.tensor(pos[:1]), 128), (one,))


# --- warps -------------------------------------------------------------------------------


def test_warp_perspective_matches_opencv_interior():
    rng = np.random.default_rng(3)
    img = smooth_image(rng)
    H = np.array([[1.02, 0.03, 4.3], [-0.02, 0.98, -3.1], [2e-5, -3e-5, 1.0]])
    ref = cv2.warpPerspective(img, H, (320, 180), flags=cv2.INTER_LINEAR)
    out = warp_perspective(torch.tensor(img)[None, None], torch.tensor(H)[None], (320, 180))[0, 0].numpy()
    np.testing.assert_allclose(out[12:-12, 12:-12], ref[12:-12, 12:-12], atol=2e-4)


def test_sample_patches_matches_opencv_and_masks_outside_pixels():
    rng = np.random.default_rng(4)
    img = smooth_image(rng)
    H = np.array([[0.99, 0.02, -30.0], [-0.01, 1.01, 5.0], [1e-5, 2e-5, 1.0]])  # pushes part of the patch out
    positions = [(10, 40), (96, 26)]
    values, mask = sample_patches(
        torch.tensor(img)[None, None], torch.tensor(H)[None, None].expand(1, 2, 3, 3), torch.tensor([positions]), 128
    )
    for m, (x, y) in enumerate(positions):
        # out(p) = img(H (p + origin)): OpenCV's inverse-map warp with H @ T(origin)
        T = np.array([[1, 0, x], [0, 1, y], [0, 0, 1.0]])
        ref = cv2.warpPerspective(img, H @ T, (128, 128), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        ii, jj = np.mgrid[0:128, 0:128]
        pts = np.stack([jj + x, ii + y, np.ones_like(ii)], -1) @ H.T
        px, py = pts[..., 0] / pts[..., 2], pts[..., 1] / pts[..., 2]
        inside = (px >= 0) & (px <= 319) & (py >= 0) & (py <= 179)
        got_mask = mask[0, m, 0].numpy() > 0
        far = (np.abs(px) > 1e-3) & (np.abs(px - 319) > 1e-3) & (np.abs(py) > 1e-3) & (np.abs(py - 179) > 1e-3)
        assert np.array_equal(got_mask[far], inside[far])
        v = values[0, m, 0].numpy()
        np.testing.assert_allclose(v[got_mask], ref[got_mask], atol=2e-4)
        assert np.all(v[~got_mask] == 0)
    assert mask[0, 0].mean() < 0.9  # the first patch really was partly pushed out


def test_crop_and_chain_match_numpy():
    rng = np.random.default_rng(5)
    imgs = torch.tensor(rng.random((2, 1, 180, 320)), dtype=torch.float32)
    pos = torch.tensor([[[0, 0], [192, 52]], [[17, 3], [100, 50]]])
    out = crop(imgs, pos, 128)
    for n in range(2):
        for m in range(2):
            x, y = pos[n, m].tolist()
            assert torch.equal(out[n, m, 0], imgs[n, 0, y : y + 128, x : x + 128])
    pairwise = np.eye(3) + rng.normal(0, [[0.01, 0.01, 2], [0.01, 0.01, 2], [1e-5, 1e-5, 0]], (7, 3, 3))
    chained = cumulative(torch.tensor(pairwise)).numpy()
    assert chained.shape == (8, 3, 3)
    np.testing.assert_array_equal(chained[0], np.eye(3))
    for s in range(1, 8):
        np.testing.assert_allclose(chained[s], np_chain(list(pairwise), 0, s), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(chained, np_cumulative(list(pairwise)), rtol=1e-10, atol=1e-10)


def test_tensor_project_matches_numpy_and_checks_shapes():
    rng = np.random.default_rng(6)
    H = np.eye(3) + rng.normal(0, [[0.02, 0.02, 3], [0.02, 0.02, 3], [1e-4, 1e-4, 0]], (5, 3, 3))
    points = rng.uniform(-10, 330, (5, 7, 2))
    got = project(torch.tensor(H), torch.tensor(points)).numpy()
    np.testing.assert_allclose(got, np_project(H, points), rtol=1e-12, atol=1e-9)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        project(torch.eye(2), torch.tensor(points))
    with pytest.raises(ValueError, match=r"\(\.\.\., N, 2\)"):
        project(torch.tensor(H), torch.zeros(5, 7, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"\(\.\.\., 4, 2\)"):
        four_point_to_homography(torch.zeros(3, 2), torch.zeros(3, 2))
    with pytest.raises(ValueError, match="pairwise"):
        cumulative(torch.eye(3))


# --- network -----------------------------------------------------------------------------


@pytest.mark.parametrize("head", ["cnn", "lstm"])
def test_paper_preset_is_table_1(head):
    config = NetConfig(preset="paper", head=head)
    model = HomographyNet(config)
    convs = [m for m in model.backbone if isinstance(m, torch.nn.Conv2d)]
    assert [c.out_channels for c in convs] == [64, 64, 64, 64, 128, 128, 128, 128]
    assert all(c.kernel_size == (3, 3) and c.stride == (1, 1) for c in convs)
    assert sum(isinstance(m, torch.nn.MaxPool2d) for m in model.backbone) == 3
    assert config.flat_features == 128 * 16 * 16 and model.embed.out_features == 1024
    # the paper's sizes: 34.2 M (CNN) and 42.6 M (LSTM) parameters, 1.26 / 1.27 GMAC per pair
    params = count_parameters(model)
    assert round(params / 1e5) == (342 if head == "cnn" else 426)
    assert macs_per_pair(config) == count_macs(model)
    assert round(macs_per_pair(config) / 1e7) == (126 if head == "cnn" else 127)


@pytest.mark.parametrize("head", ["cnn", "lstm"])
def test_compact_preset_meets_its_budget(head):
    config = NetConfig(preset="compact", head=head)
    model = HomographyNet(config)
    assert count_parameters(model) * 4 <= 25e6
    assert macs_per_pair(config) == count_macs(model)
    assert macs_per_pair(config) <= macs_per_pair(NetConfig(preset="paper", head=head)) / 4
    # the regressor reads a spatial map, not a globally pooled vector
    assert config.flat_features == 64 * 8 * 8


@pytest.mark.parametrize("head", ["cnn", "lstm"])
def test_forward_equals_features_then_step(head):
    torch.manual_seed(0)
    model = HomographyNet(NetConfig(head=head, patch=64)).eval()  # small patches keep the test fast
    patches = torch.rand(2, 5, 2, 64, 64) * 2 - 1
    with torch.no_grad():
        offsets, state = model(patches)
        feats = model.features(patches.flatten(0, 1)).unflatten(0, (2, 5))
        again, _ = model.step(feats)
    assert offsets.shape == (2, 5, 4, 2)
    torch.testing.assert_close(offsets, again)
    assert (state is None) == (head == "cnn")


def test_lstm_state_streams_and_cnn_has_no_memory():
    torch.manual_seed(1)
    patches = torch.rand(3, 6, 2, 64, 64) * 2 - 1
    lstm = HomographyNet(NetConfig(head="lstm", patch=64)).eval()
    with torch.no_grad():
        whole, _ = lstm(patches)
        first, state = lstm(patches[:, :4])
        rest, _ = lstm(patches[:, 4:], state)
        fresh, _ = lstm(patches[:, 4:])
    torch.testing.assert_close(torch.cat([first, rest], 1), whole, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(fresh, whole[:, 4:])  # the state matters
    cnn = HomographyNet(NetConfig(head="cnn", patch=64)).eval()
    with torch.no_grad():
        a, _ = cnn(patches)
        b, _ = cnn(patches[:, [5, 4, 3, 2, 1, 0]])
    torch.testing.assert_close(a[:, [5, 4, 3, 2, 1, 0]], b)


def test_untrained_net_starts_near_identity():
    torch.manual_seed(2)
    model = HomographyNet(NetConfig()).eval()
    with torch.no_grad():
        offsets, _ = model(torch.rand(4, 2, 2, 128, 128) * 2 - 1)
    assert offsets.abs().max() < 0.5


def test_features_transfer_from_cnn_to_lstm():
    cnn, lstm = HomographyNet(NetConfig(head="cnn")), HomographyNet(NetConfig(head="lstm"))
    lstm.load_features_from(cnn)
    x = torch.rand(2, 2, 128, 128)
    cnn.eval(), lstm.eval()
    torch.testing.assert_close(cnn.features(x), lstm.features(x))
    assert len(lstm.feature_parameters()) == len(list(cnn.backbone.parameters())) + 2


def test_an_lstm_can_start_as_the_cnn_it_is_fine_tuned_from():
    """start_as: the LSTM head passes its input through with no memory yet, so a sequence of
    pairs gets the CNN's offsets, pair by pair, in any order."""
    torch.manual_seed(4)
    cnn, lstm = HomographyNet(NetConfig(head="cnn")).eval(), HomographyNet(NetConfig(head="lstm")).eval()
    with torch.no_grad():
        cnn.regressor.weight.normal_(std=0.05)  # offsets of a few px, as a trained net's
    pairs = torch.rand(1, 6, 2, 128, 128) * 2 - 1
    with torch.no_grad():
        largest = float(cnn.features(pairs.flatten(0, 1)).max())
        lstm.start_as(cnn, 5 * largest)
        expected, _ = cnn(pairs)
        got, _ = lstm(pairs)
        backwards, _ = lstm(pairs.flip(1))
    assert expected.abs().max() > 1.0
    torch.testing.assert_close(got, expected, atol=0.02 * float(expected.abs().max()), rtol=0)
    torch.testing.assert_close(backwards.flip(1), got, atol=0.02, rtol=0)  # no memory yet (the forget gate keeps 0.25%)
    with pytest.raises(ValueError, match="from a CNN head"):
        cnn.start_as(lstm, 1.0)
    with pytest.raises(ValueError, match="hidden == embed"):
        HomographyNet(NetConfig(head="lstm", hidden=256)).start_as(cnn, 1.0)


def test_config_round_trip_and_validation():
    config = NetConfig(preset="paper", head="lstm", dropout=0.1)
    assert NetConfig.from_dict(config.to_dict()) == config
    assert config.hidden == 1024 and config.backbone[2] == "M"
    for bad in (dict(preset="huge"), dict(head="gru"), dict(patch=100)):
        with pytest.raises(ValueError):
            NetConfig(**bad)


# --- checkpoints -------------------------------------------------------------------------


@pytest.mark.parametrize("head,variant", [("cnn", "reg-all"), ("lstm", "lstm-reg-all")])
def test_checkpoint_round_trip_is_exact(tmp_path, head, variant):
    torch.manual_seed(3)
    model = HomographyNet(NetConfig(head=head, dropout=0.2)).eval()
    path = tmp_path / "net.safetensors"
    save_weights(path, model, model.config, variant, extra={"step": 7})
    loaded, meta = load_weights(path)
    assert meta["variant"] == variant and meta["config"] == model.config and meta["extra"] == {"step": 7}
    assert meta["work_size"] == (320, 180) and meta["direction"] == "t_to_t+1"
    assert not loaded.training
    x = torch.rand(2, 3, 2, 128, 128) * 2 - 1
    with torch.no_grad():
        a, _ = model(x)
        b, _ = loaded(x)
    assert torch.equal(a, b)
    assert list(tmp_path.iterdir()) == [path]  # atomic: no temporary file left


def test_checkpoint_rejects_other_files(tmp_path):
    with pytest.raises(BadInput, match="no such"):
        load_weights(tmp_path / "missing.safetensors")
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"not a checkpoint at all")
    with pytest.raises(BadInput, match="not a safetensors"):
        load_weights(junk)
    foreign = tmp_path / "foreign.safetensors"
    save_file({"w": torch.zeros(3)}, str(foreign))
    with pytest.raises(BadInput, match="not a mosaic checkpoint"):
        read_metadata(foreign)
    # metadata that promises a different net than the tensors hold
    model = HomographyNet(NetConfig(head="cnn"))
    good = tmp_path / "good.safetensors"
    save_weights(good, model, model.config, "base")
    with open(good, "rb") as fh:
        header_len = int.from_bytes(fh.read(8), "little")
        header = fh.read(header_len).decode()
    lying = tmp_path / "lying.safetensors"
    meta = json.loads(header)["__metadata__"]
    meta["config"] = NetConfig(head="lstm").to_json()
    save_file(load_file(str(good)), str(lying), metadata=meta)
    with pytest.raises(BadInput, match="do not match"):
        load_weights(lying)
