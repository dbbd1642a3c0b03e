"""int8 CPU inference: calibrated ranges travel with the weights, the int8 features follow the
fp32 ones closely on textured patches, and the estimator picks int8 only when it can."""

from __future__ import annotations

import copy
import warnings

import numpy as np
import pytest
import torch

from conftest import textured_image
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import make_estimator
from mosaic_cli.model import HomographyNet, NetConfig, quantize, read_metadata, save_weights

pytestmark = [
    pytest.mark.skipif(quantize.engine() is None, reason="this PyTorch build has no int8 engine"),
    pytest.mark.usefixtures("one_torch_thread"),
]
PATCH = 128


def patch_pairs(count: int, seed: int) -> torch.Tensor:
    """(count, 2, P, P) gray patch pairs in [-1, 1]: a textured patch and the same ground a few
    pixels further on."""
    gray = textured_image(640, 480, seed=seed).mean(axis=2).astype(np.float32) / 127.5 - 1.0
    rng = np.random.default_rng(seed)
    pairs = []
    for _ in range(count):
        x, y = rng.integers(8, 640 - PATCH - 8), rng.integers(8, 480 - PATCH - 8)
        dx, dy = rng.integers(-6, 7, size=2)
        pairs.append(np.stack([gray[y : y + PATCH, x : x + PATCH], gray[y + dy : y + dy + PATCH, x + dx : x + dx + PATCH]]))
    return torch.from_numpy(np.stack(pairs))


@pytest.fixture(scope="module")
def net_and_ranges():
    torch.manual_seed(0)
    model = HomographyNet(NetConfig(head="cnn", patch=PATCH)).eval()
    return model, quantize.calibrate(model, patch_pairs(48, seed=1))


@pytest.mark.slow
def test_int8_features_follow_fp32_on_patches_it_was_not_calibrated_on(net_and_ranges):
    model, ranges = net_and_ranges
    int8 = quantize.quantized_features(model, ranges)
    assert int8 is not None
    test = patch_pairs(24, seed=7)
    with torch.inference_mode():
        exact, approx = model.features(test), int8(test)
        other = model.features(patch_pairs(24, seed=8))
    error = (approx - exact).norm(dim=1) / exact.norm(dim=1)
    assert float(error.median()) < 0.15
    # ...and far closer to its own fp32 features than to those of other patches
    assert float(error.max()) < 0.5 * float(((other - exact).norm(dim=1) / exact.norm(dim=1)).min())


def test_ranges_are_refused_by_another_network(net_and_ranges):
    _, ranges = net_and_ranges
    other = HomographyNet(NetConfig(head="cnn", patch=PATCH, backbone=((16, 2), 16, "M", 32, "M", 32, "M"))).eval()
    assert quantize.quantized_features(other, ranges) is None
    assert quantize.quantized_features(other, None) is None
    assert quantize.quantized_features(other, {**ranges, "format": quantize.RANGES_FORMAT + 1}) is None


def test_the_estimator_runs_int8_only_with_calibrated_weights(tmp_path, net_and_ranges):
    model, ranges = net_and_ranges
    with_ranges, without = tmp_path / "int8.safetensors", tmp_path / "plain.safetensors"
    save_weights(with_ranges, model, model.config, "base", int8=ranges)
    save_weights(without, model, model.config, "base")
    assert read_metadata(with_ranges)["int8"] == ranges
    assert read_metadata(without)["int8"] is None

    assert make_estimator("cnn", weights=str(with_ranges), device="cpu").precision == "int8"
    assert make_estimator("cnn:precision=fp32", weights=str(with_ranges), device="cpu").precision == "fp32"
    assert make_estimator("cnn", weights=str(without), device="cpu").precision == "fp32"
    with pytest.raises(BadInput, match="int8"):
        make_estimator("cnn:precision=int8", weights=str(without), device="cpu")
    with pytest.raises(BadInput, match="precision"):
        make_estimator("cnn:precision=fp16", weights=str(with_ranges), device="cpu")
    # the weights option in a name picks the checkpoint, whatever --weights says
    assert make_estimator(f"cnn:weights={with_ranges}", weights=str(without), device="cpu").precision == "int8"


@pytest.mark.slow
def test_int8_lstm_steps_like_fp32_through_a_carried_state_or_is_not_used():
    """An LSTM head in int8, stepped over 48 pairs in 16-pair chunks with its state carried as
    the estimator does: kept only where its offsets stay within 0.05 working px of fp32's on real
    texture.  A freshly initialised LSTM passes (measured: under 0.01 px); for the shipped one,
    whatever its weights, quantized_head's verdict must match what int8 does to its offsets here,
    on textured patch pairs its own probe never saw."""
    from torch.ao.quantization import quantize_dynamic

    from mosaic_cli.estimators.learned import default_weights
    from mosaic_cli.model.checkpoint import load_weights

    shipped, shipped_meta = load_weights(default_weights("lstm"))
    torch.manual_seed(0)
    fresh = HomographyNet(NetConfig(head="lstm", patch=PATCH)).eval()
    for model in (fresh, shipped):
        with torch.inference_mode(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            int8 = quantize_dynamic(copy.deepcopy(model).eval(), {torch.nn.LSTM}, dtype=torch.qint8)
            features = model.features(patch_pairs(48, seed=3))[None]

            def offsets(net, features=features):
                state, out = None, []
                for chunk in features.split(16, dim=1):
                    step, state = net.step(chunk, state)
                    out.append(step)
                return torch.cat(out, dim=1)[0]

            error = float((offsets(int8) - offsets(model)).abs().max())
        keeps_int8 = error <= quantize.HEAD_TOLERANCE_PX  # measured here, independently of quantized_head's probe
        if model is fresh:
            assert keeps_int8, error  # a small random LSTM steps alike in int8 (under 0.01 px measured)
        head = quantize.quantized_head(model)
        assert (head is not None) == keeps_int8
        if model is shipped:  # and the verdict stored with its weights (no probe at load) is the same
            assert (quantize.quantized_head(model, shipped_meta["int8"]) is not None) == keeps_int8
        if head is not None:
            assert type(head.lstm).__module__.startswith("torch.ao.nn.quantized.dynamic")
        assert type(model.lstm) is torch.nn.LSTM  # the fp32 network itself is left as it was
    assert quantize.quantized_head(HomographyNet(NetConfig(head="cnn", patch=PATCH))) is None


def test_the_shipped_int8_estimator_loads_without_the_compiler_stack(fresh_interpreter_build):
    """Building the int8 features traces the network with FX; recording a stack trace per graph
    node imported torch._dynamo and torch._inductor, 1.5 s of every command's start-up.  (A fresh
    interpreter's builds, conftest's: none of them may load either.)"""
    run = fresh_interpreter_build
    assert run["precision"] == "int8"
    assert not run["after_default"]["torch._dynamo"] and not run["after_default"]["torch._inductor"]


@pytest.mark.slow
def test_a_head_error_stored_with_the_ranges_decides_only_when_clearly_on_one_side(monkeypatch):
    """with_head_error stores the int8 LSTM's probe error; quantized_head then skips the probe
    when the stored error is a factor STORED_VERDICT_MARGIN away from the tolerance, and probes
    near it, or without one for this engine."""
    torch.manual_seed(0)
    model = HomographyNet(NetConfig(head="lstm", patch=PATCH)).eval()
    ranges = quantize.with_head_error(model, {"format": quantize.RANGES_FORMAT, "activations": {}})
    engine = quantize.engine()
    measured = ranges["head_error"][engine]
    assert measured == quantize.head_error(model, quantize.quantize_dynamic_lstm(model))  # the probe, stored
    probes = []
    real_probe = quantize.head_error
    monkeypatch.setattr(quantize, "head_error", lambda *a, **k: probes.append(1) or real_probe(*a, **k))
    tolerance = quantize.HEAD_TOLERANCE_PX

    def verdict(stored: float | None, engine_name: str = engine) -> bool:
        held = {} if stored is None else {"head_error": {engine_name: stored}}
        return quantize.quantized_head(model, {**ranges, **held} if stored is not None else {"activations": {}}) is not None

    probes.clear()
    assert verdict(tolerance * 2.5) is False and not probes  # clearly outside: no int8 head, no probe
    assert verdict(tolerance / 2.5) is True and not probes  # clearly inside: int8, no probe
    keeps = measured <= tolerance
    assert verdict(tolerance * 1.1) is keeps and len(probes) == 1  # near the line: the probe decides
    assert verdict(None) is keeps and len(probes) == 2  # none stored: the probe decides
    assert verdict(tolerance * 2.5, "another-engine") is keeps and len(probes) == 3  # stored for another engine


def test_int8_features_from_the_patterns_the_net_uses_equal_those_from_every_pattern():
    """quantize._backend_config keeps only the native backend's patterns the feature graph can
    match: the converted graph and its int8 outputs are those of the full pattern set, bit for bit."""
    from torch.ao.quantization.backend_config import get_native_backend_config

    from mosaic_cli.estimators.learned import default_weights
    from mosaic_cli.model.checkpoint import load_weights

    model, meta = load_weights(default_weights("lstm"))
    fewer = quantize.quantized_features(model, meta["int8"])
    native = get_native_backend_config()
    assert len(quantize._backend_config(quantize._Features(model)).configs) < len(native.configs) / 10
    original = quantize._backend_config
    quantize._backend_config = lambda features: native
    try:
        every = quantize.quantized_features(model, meta["int8"])
    finally:
        quantize._backend_config = original
    assert fewer is not None and every is not None and fewer.code == every.code
    pairs = patch_pairs(8, seed=5) if model.config.patch == PATCH else torch.rand(8, 2, model.config.patch, model.config.patch) * 2 - 1
    with torch.inference_mode():
        assert torch.equal(fewer(pairs), every(pairs))
