"""int8 inference on CPUs: the feature extractor (backbone + first Linear), and the LSTM's weights.

The convolutions are most of a pair's cost on a CPU (4 ms of the compact net's 4.5 ms on one
core of the development machine); PyTorch's int8 kernels (x86/fbgemm, or qnnpack on ARM) run them
about 4x faster.  Static quantisation needs the range of every activation: they are measured once,
on patch pairs of real footage, and stored with the weights (metadata key ``int8``), so that
loading is deterministic and needs no data:

    calibrate(model, pairs)          (N, 2, P, P) pairs in [-1, 1] -> ranges (a JSON-able dict)
    quantized_features(model, ranges) -> a module (N, 2, P, P) -> (N, F), or None where the
                                        platform has no int8 engine or the ranges do not fit

    quantized_head(model, ranges)    -> a copy of ``model`` whose LSTM has int8 weights
                                        (dynamic: activations quantised on the fly, so no
                                        ranges are needed), or None where there is none, or
                                        where its offsets would stray from fp32's (measured
                                        when the ranges were, and stored with them)

Stepped one 16-pair chunk at a time, the LSTM reads its 4 MB of weights once a pair: in int8 a
chunk took 0.55 ms instead of 5.5 on the development machine.  The regressor stays in fp32.
"""

from __future__ import annotations

import contextlib
import copy
import warnings

import torch
from torch import Tensor, nn

from mosaic_cli.model.network import HomographyNet

RANGES_FORMAT = 1


class _Features(nn.Module):
    """The traceable part of the net: patch pairs -> features."""

    def __init__(self, model: HomographyNet):
        super().__init__()
        self.model = model

    def forward(self, patches: Tensor) -> Tensor:
        return self.model.features(patches)


def engine() -> str | None:
    """The int8 engine of this platform (x86 or qnnpack), None where there is none."""
    supported = torch.backends.quantized.supported_engines
    for name in ("x86", "fbgemm", "qnnpack"):
        if name in supported:
            return name
    return None


def _prepare(model: HomographyNet, observer, example: Tensor):
    """The features of ``model`` traced with ``observer`` after every activation (weights:
    per-channel symmetric int8, the engine's default), and the backend patterns they were
    prepared with (for :func:`convert_fx`)."""
    from torch.ao.quantization import QConfig, QConfigMapping, default_per_channel_weight_observer
    from torch.ao.quantization.quantize_fx import prepare_fx

    # x86 and fbgemm kernels need 7-bit activations to stay exact in their 16-bit accumulators.
    reduce_range = engine() in ("x86", "fbgemm")
    qconfig = QConfig(activation=observer.with_args(reduce_range=reduce_range),
                      weight=default_per_channel_weight_observer)
    features = _Features(copy.deepcopy(model).cpu().eval())
    with warnings.catch_warnings(), _no_stack_traces():
        warnings.simplefilter("ignore")  # torch.ao announces its move to torchao
        backend = _backend_config(features)
        return prepare_fx(features, QConfigMapping().set_global(qconfig), (example,), backend_config=backend), backend


def _backend_config(features: nn.Module):
    """The native int8 backend's patterns that can match in ``features``: those made only of
    the module types, functions and methods its graph calls, and the fused modules they fuse
    into.  The same quantised graph as with all 194 patterns, whose handler classes took 80 ms
    of the start-up to build (CHANGELOG.md, speed, 2026-11-27)."""
    import torch.ao.quantization.quantize_fx  # noqa: F401  (backend_config needs its utils loaded)
    from torch.ao.quantization.backend_config import BackendConfig, get_native_backend_config

    with _no_stack_traces():
        graph = torch.fx.symbolic_trace(features)
    called: set = set()
    for node in graph.graph.nodes:
        if node.op == "call_module":
            called.add(type(graph.get_submodule(node.target)))
        elif node.op in ("call_function", "call_method"):
            called.add(node.target)

    def parts(pattern):
        return [p for q in pattern for p in parts(q)] if isinstance(pattern, tuple) else [pattern]

    native = get_native_backend_config()
    kept = [c for c in native.configs if all(p in called for p in parts(c.pattern if c.pattern is not None else c._pattern_complex_format))]
    fused = {c.fused_module for c in kept if c.fused_module is not None}
    kept += [c for c in native.configs if c.pattern in fused]
    return BackendConfig(native.name).set_backend_pattern_configs(kept)


@contextlib.contextmanager
def _no_stack_traces():
    """FX tracing without a Python stack trace recorded on each graph node: symbolising one
    imports torch._dynamo and torch._inductor, 1.5 of the 1.7 s the int8 features took to build
    at start-up (CHANGELOG.md, speed, 2026-11-27); the traced graph is the same."""
    import torch.fx.config

    if not hasattr(torch.fx.config, "do_not_emit_stack_traces"):  # torch 2.11 (the GPU machine's) has no such switch
        yield
        return
    before = torch.fx.config.do_not_emit_stack_traces
    torch.fx.config.do_not_emit_stack_traces = True
    try:
        yield
    finally:
        torch.fx.config.do_not_emit_stack_traces = before


def _observers(prepared: nn.Module) -> dict[str, nn.Module]:
    from torch.ao.quantization.observer import ObserverBase

    return {name: m for name, m in prepared.named_modules() if isinstance(m, ObserverBase)}


@torch.no_grad()
def calibrate(model: HomographyNet, pairs: Tensor, batch: int = 64) -> dict:
    """Activation ranges of ``model``'s features over ``pairs`` (N, 2, P, P) in [-1, 1]: a
    histogram per activation, reduced to the range that minimises the quantisation error
    (PyTorch's HistogramObserver), so that a few outliers do not coarsen every other value."""
    from torch.ao.quantization.observer import HistogramObserver

    if engine() is None:
        raise RuntimeError("this PyTorch build has no int8 engine")
    torch.backends.quantized.engine = engine()
    # int8 runs on the CPU only (its LSTM kernels exist for no other backend): a net trained on a
    # GPU is measured as a CPU copy, and the training net stays where it is.
    model, pairs = _on_cpu(model), pairs.cpu()
    prepared, _ = _prepare(model, HistogramObserver, pairs[:1])
    for chunk in pairs.split(batch):
        prepared(chunk.float())
    ranges = {}
    for name, obs in _observers(prepared).items():
        if getattr(obs, "dtype", None) != torch.quint8:
            continue
        scale, zero = (float(v) for v in obs.calculate_qparams())
        # The range [lo, hi] whose min-max quantisation gives exactly this scale and zero point.
        ranges[name] = [(obs.quant_min - zero) * scale, (obs.quant_max - zero) * scale]
    return with_head_error(model, {"format": RANGES_FORMAT, "pairs": int(len(pairs)), "activations": ranges})


def _on_cpu(model: HomographyNet) -> HomographyNet:
    """``model`` itself when its weights are on the CPU, else a CPU copy of it."""
    if all(p.device.type == "cpu" for p in model.parameters()):
        return model
    return copy.deepcopy(model).cpu()


def with_head_error(model: HomographyNet, ranges: dict) -> dict:
    """``ranges`` with the int8 LSTM's :func:`head_error` on this platform's engine added (key
    ``head_error``: {engine: px}), so that loading need not probe it (a quarter of a second of
    the start-up); unchanged for a net without an LSTM."""
    if model.lstm is None or engine() is None:
        return ranges
    torch.backends.quantized.engine = engine()
    model = _on_cpu(model)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        int8 = quantize_dynamic_lstm(model)
    return {**ranges, "head_error": {**ranges.get("head_error", {}), engine(): head_error(model, int8)}}


def quantized_features(model: HomographyNet, ranges: dict | None) -> nn.Module | None:
    """The int8 feature extractor of ``model`` with the calibrated ``ranges``; None when the
    platform has no int8 engine or the ranges were made for another network or PyTorch."""
    from torch.ao.quantization.observer import MinMaxObserver
    from torch.ao.quantization.quantize_fx import convert_fx

    if not ranges or ranges.get("format") != RANGES_FORMAT or engine() is None:
        return None
    torch.backends.quantized.engine = engine()
    P = model.config.patch
    prepared, backend = _prepare(model, MinMaxObserver, torch.zeros(1, 2, P, P))
    observers = {name: obs for name, obs in _observers(prepared).items() if getattr(obs, "dtype", None) == torch.quint8}
    stored = ranges.get("activations", {})
    if set(observers) != set(stored):
        return None
    for name, obs in observers.items():
        lo, hi = stored[name]
        obs.min_val = torch.tensor(float(lo))
        obs.max_val = torch.tensor(float(hi))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return convert_fx(prepared, backend_config=backend).eval()


# The int8 LSTM is kept only where its offsets stay this close to fp32's (working px) on a probe:
# an LSTM whose regressor amplifies small hidden values (one started as a CNN's head) can lose
# more to int8 than its speed is worth.
HEAD_TOLERANCE_PX = 0.05


# A head error stored with the weights decides alone only this far from the tolerance (a factor):
# another CPU's int8 kernels may round a little differently.
STORED_VERDICT_MARGIN = 2.0


def quantized_head(model: HomographyNet, ranges: dict | None = None, tolerance: float = HEAD_TOLERANCE_PX) -> HomographyNet | None:
    """A copy of ``model`` with its LSTM's weights in int8; None without an LSTM or an int8
    engine, or where the int8 head's offsets stray more than ``tolerance`` working px from
    fp32's on a probe (:func:`head_error`).  The probe's error as measured when ``ranges`` were
    (:func:`with_head_error`, for this engine) is used instead where it is clearly on one side of
    the tolerance; near it, or missing, the probe runs here."""
    if model.lstm is None or engine() is None:
        return None
    torch.backends.quantized.engine = engine()
    stored = (ranges or {}).get("head_error", {}).get(engine())
    if stored is not None and stored >= tolerance * STORED_VERDICT_MARGIN:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch.ao announces its move to torchao
        int8 = quantize_dynamic_lstm(model)
    if stored is not None and stored <= tolerance / STORED_VERDICT_MARGIN:
        return int8
    return int8 if head_error(model, int8) <= tolerance else None


def quantize_dynamic_lstm(model: HomographyNet) -> HomographyNet:
    """A copy of ``model`` (not in place) whose LSTM has int8 weights."""
    from torch.ao.quantization import quantize_dynamic

    return quantize_dynamic(model.eval(), {nn.LSTM}, dtype=torch.qint8)


@torch.inference_mode()
def head_error(model: HomographyNet, int8: HomographyNet, pairs: int = 48, chunk: int = 16) -> float:
    """The largest offset difference (working px) between ``model``'s head and ``int8``'s, both
    stepped over the features of ``pairs`` probe patch pairs, ``chunk`` pairs at a time with the
    state carried, as the estimator runs them.  The probe: smoothed noise, the second patch of
    each pair the first moved by a few pixels (fixed seed: the same verdict on every load)."""
    generator = torch.Generator().manual_seed(0)
    p = model.config.patch
    ground = torch.rand(1, 1, 4 * p, 4 * p, generator=generator)
    for _ in range(2):
        ground = torch.nn.functional.avg_pool2d(ground, 5, stride=1, padding=2, count_include_pad=False)
    ground = (ground - ground.mean()) / ground.std().clamp(min=1e-6) * 0.5
    corners = torch.randint(8, 3 * p - 8, (pairs, 2), generator=generator)
    moves = torch.randint(-6, 7, (pairs, 2), generator=generator)
    cut = [torch.stack([ground[0, 0, y : y + p, x : x + p], ground[0, 0, y + dy : y + dy + p, x + dx : x + dx + p]])
           for (x, y), (dx, dy) in zip(corners.tolist(), moves.tolist())]
    # (1, pairs, F), a chunk at a time: no more memory than the estimator's own chunks
    features = torch.cat([model.eval().features(part) for part in torch.stack(cut).clamp(-1, 1).split(chunk)])[None]

    def offsets(net: HomographyNet) -> Tensor:
        state, out = None, []
        for part in features.split(chunk, dim=1):
            step, state = net.step(part, state)
            out.append(step)
        return torch.cat(out, dim=1)

    return float((offsets(int8) - offsets(model)).abs().max())


__all__ = ["HEAD_TOLERANCE_PX", "RANGES_FORMAT", "STORED_VERDICT_MARGIN", "engine", "calibrate", "head_error", "quantized_features",
           "quantized_head", "quantize_dynamic_lstm", "with_head_error"]
