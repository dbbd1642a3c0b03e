"""The homography network of the paper (Table 1), in one file.

    patches (B, T, 2, P, P)  two gray patches, frame t and frame t+1 at the same place, in [-1, 1]
      -> backbone            VGG-like 3x3 convs + ReLU (no BatchNorm, as the paper)
      -> flatten             the spatial layout is kept: no global pooling
      -> embed               [dropout] Linear -> ReLU                       features (B, T, F)
      -> head "cnn"          dropout -> Linear(F, 8)                        (BASE, REG-*)
         head "lstm"         LSTM(F, hidden) -> dropout -> Linear(hidden, 8) (LSTM, LSTM-REG-ALL)
      -> offsets (B, T, 4, 2)

The 8 outputs are the displacements, in working-frame pixels, of the patch's four outer corners
(TL, TR, BR, BL, see :func:`mosaic_cli.model.patches.patch_corners`) from frame t to frame t+1:
a corner at ``c`` in frame t shows the ground that is at ``c + offset`` in frame t+1.  The DLT of
those four correspondences is the homography of the whole working frame, frame t -> frame t+1.

Two presets of the same code:

``paper``    exactly Table 1: [64, 64, M, 64, 64, M, 128, 128, M, 128, 128] on 128x128 ->
             128x16x16 = 32768 -> Linear 1024 (-> LSTM 1024) -> 8.  1.26 GMAC per pair.
``compact``  for CPUs: the first conv has stride 2 (the rest of the net sees 64x64 maps, like an
             input downsampled inside the net, but through 32 learned filters instead of a fixed
             low-pass), half the paper's widths, one more pooling so that the map the regressor
             reads is still spatial: 64x8x8 = 4096 -> Linear 512 (-> LSTM 512) -> 8.
             0.16 GMAC (1/8 of the paper) and 4.4 M parameters (17.4 MB fp32) with the LSTM head.

In the backbone spec an int is a 3x3 conv (+ReLU) to that many channels, ``(channels, stride)``
a strided one, and ``"M"`` a 2x2 max-pool (torchvision's VGG notation).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import Tensor, nn

HEADS = ("cnn", "lstm")
# The paper's training variants (Table 2; what each trains: mosaic_cli.train.objective).  A
# checkpoint records the variant that made it, so the model side knows their names.
# lstm-reg-t is not in the paper: the LSTM with the temporal priors alone, which costs a tenth of
# lstm-reg-all's forward passes (that reads two patches of every pair, and for R_s four quadrants of each).
VARIANTS = ("base", "reg-p", "reg-s", "reg-t", "reg-all", "lstm", "lstm-reg-t", "lstm-reg-all")

PRESETS: dict[str, dict[str, Any]] = {
    "paper": dict(backbone=(64, 64, "M", 64, 64, "M", 128, 128, "M", 128, 128), embed=1024, hidden=1024, dropout=0.5),
    "compact": dict(backbone=((32, 2), 32, 32, "M", 64, 64, "M", 64, 64, "M"), embed=512, hidden=512, dropout=0.3),
}

LSTMState = tuple[Tensor, ...]  # (h, c) of the "lstm" head


@dataclass
class NetConfig:
    """Network hyper-parameters.  ``None`` fields take the preset's value, so that a saved config
    (``to_dict``) is complete and reproduces the net even if a preset changes later."""

    preset: str = "compact"
    head: str = "cnn"  # "cnn" | "lstm"
    patch: int = 128
    dropout: float | None = None
    backbone: tuple | None = None
    embed: int | None = None  # feature size F (the first Linear)
    hidden: int | None = None  # LSTM hidden size

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}: choose one of {', '.join(PRESETS)}")
        for key, value in PRESETS[self.preset].items():
            if getattr(self, key) is None:
                setattr(self, key, value)
        self.backbone = tuple(tuple(b) if isinstance(b, list) else b for b in self.backbone)
        self.validate()

    def validate(self) -> None:
        """A checkpoint's or a training run's config (``mosaic train`` checks its flags first:
        train/config.py), so a bad value here is a bad file or a bug: ValueError."""
        if self.head not in HEADS:
            raise ValueError(f"unknown head {self.head!r}: choose one of {', '.join(HEADS)}")
        if self.patch % self.downsampling:
            raise ValueError(f"patch {self.patch} is not a multiple of the backbone's stride {self.downsampling}")

    @property
    def downsampling(self) -> int:
        """How much smaller the backbone's output map is than its input."""
        factor = 1
        for layer in self.backbone:
            if layer == "M":
                factor *= 2
            elif isinstance(layer, tuple):
                factor *= layer[1]
        return factor

    @property
    def out_channels(self) -> int:
        return [_conv_spec(layer)[0] for layer in self.backbone if layer != "M"][-1]

    @property
    def flat_features(self) -> int:
        """Length of the flattened backbone output (the first Linear's input)."""
        return self.out_channels * (self.patch // self.downsampling) ** 2

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> NetConfig:
        known = {k: v for k, v in data.items() if k in cls.__dataclass_fields__}
        return cls(**known)

    def to_json(self) -> str:
        return json.dumps(self.to_dict())


def _conv_spec(layer) -> tuple[int, int]:
    """(channels, stride) of a backbone conv entry."""
    return (layer[0], layer[1]) if isinstance(layer, tuple) else (int(layer), 1)


def make_backbone(spec: tuple, in_channels: int = 2) -> nn.Sequential:
    layers: list[nn.Module] = []
    channels = in_channels
    for layer in spec:
        if layer == "M":
            layers.append(nn.MaxPool2d(2))
            continue
        out, stride = _conv_spec(layer)
        layers += [nn.Conv2d(channels, out, 3, stride=stride, padding=1), nn.ReLU(inplace=True)]
        channels = out
    return nn.Sequential(*layers)



class HomographyNet(nn.Module):
    """Patch pairs -> corner offsets (working pixels, frame t -> frame t+1); see the module doc."""

    def __init__(self, config: NetConfig | None = None):
        super().__init__()
        self.config = config = config or NetConfig()
        self.backbone = make_backbone(config.backbone)
        self.embed = nn.Linear(config.flat_features, config.embed)
        if config.head == "lstm":
            self.lstm = nn.LSTM(config.embed, config.hidden, num_layers=1, batch_first=True)
            regressor_in = config.hidden
        else:
            self.lstm = None
            regressor_in = config.embed
        self.dropout = nn.Dropout(config.dropout)
        self.regressor = nn.Linear(regressor_in, 8)
        self._init_weights()

    def _init_weights(self) -> None:
        # He initialisation, as the paper; the regressor starts near zero so that an untrained
        # net predicts (almost) the identity, the best guess between consecutive video frames.
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.Linear)):
                nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                nn.init.zeros_(m.bias)
        nn.init.normal_(self.regressor.weight, std=1e-3)
        nn.init.zeros_(self.regressor.bias)

    @property
    def head(self) -> str:
        return self.config.head

    def features(self, patches: Tensor) -> Tensor:
        """(N, 2, P, P) patch pairs -> (N, F) features (backbone, flatten, first Linear, ReLU)."""
        x = self.backbone(patches).flatten(1)
        if self.lstm is None:
            # The paper drops out before both Linears of the CNN head only.
            x = self.dropout(x)
        return torch.relu(self.embed(x))

    def step(self, features: Tensor, state: LSTMState | None = None) -> tuple[Tensor, LSTMState | None]:
        """(B, T, F) features of T consecutive pairs -> offsets (B, T, 4, 2) and the new LSTM
        state (h, c), each (1, B, hidden); ``state=None`` starts from zeros.  The CNN head has no
        state and returns None."""
        if self.lstm is not None:
            features, state = self.lstm(features, state)
        else:
            state = None
        offsets = self.regressor(self.dropout(features))
        return offsets.unflatten(-1, (4, 2)), state

    def forward(self, patches: Tensor, state: LSTMState | None = None) -> tuple[Tensor, LSTMState | None]:
        """(B, T, 2, P, P) -> offsets (B, T, 4, 2), state (see :meth:`step`)."""
        B, T = patches.shape[:2]
        feats = self.features(patches.flatten(0, 1)).unflatten(0, (B, T))
        return self.step(feats, state)

    def feature_parameters(self) -> list[nn.Parameter]:
        """Backbone and first Linear: the part an LSTM variant takes (frozen) from a trained CNN."""
        return list(self.backbone.parameters()) + list(self.embed.parameters())

    def load_features_from(self, other: HomographyNet) -> None:
        """Copy backbone and first Linear from another net of the same preset (e.g. BASE -> LSTM)."""
        self.backbone.load_state_dict(other.backbone.state_dict())
        self.embed.load_state_dict(other.embed.state_dict())

    @torch.no_grad()
    def start_as(self, cnn: HomographyNet, feature_scale: float) -> None:
        """An LSTM head that starts as ``cnn``'s head: the features and first Linear copied, and
        the LSTM set to pass its input through, with no memory yet, so that the fine-tune begins
        at the CNN's answer and learns only what the sequence adds.

        With the input, forget and output gates held at s = sigmoid(6), 0.0025 and s by their
        biases, and the cell input at tanh(a x) (a = 1 / ``feature_scale``, the typical size of
        the features x), h = s tanh(s tanh(a x) + 0.0025 c), about s^2 a x while a x is small;
        the regressor is the CNN's, divided by s^2 a.  Needs hidden == embed."""
        if self.lstm is None or cnn.lstm is not None:
            raise ValueError("start_as makes an LSTM head from a CNN head")
        if self.config.hidden != self.config.embed:
            raise ValueError(f"start_as needs hidden == embed, got {self.config.hidden} and {self.config.embed}")
        self.load_features_from(cnn)
        a, open_gate = 1.0 / float(feature_scale), 6.0
        s = float(torch.sigmoid(torch.tensor(open_gate)))
        hidden = self.config.hidden
        lstm = self.lstm
        lstm.weight_ih_l0.zero_()
        lstm.weight_hh_l0.zero_()
        lstm.bias_hh_l0.zero_()
        lstm.weight_ih_l0[2 * hidden : 3 * hidden] = a * torch.eye(hidden)  # gates in torch's order: i, f, g, o
        lstm.bias_ih_l0.copy_(torch.cat([torch.full((hidden,), open_gate), torch.full((hidden,), -open_gate),
                                         torch.zeros(hidden), torch.full((hidden,), open_gate)]))
        self.regressor.weight.copy_(cnn.regressor.weight / (s * s * a))
        self.regressor.bias.copy_(cnn.regressor.bias)


# --------------------------------------------------------------------------------------------
# Cost accounting


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def macs_per_pair(config: NetConfig) -> int:
    """Multiply-accumulates to turn one patch pair into 8 offsets (convs, Linears and one LSTM
    step), counted by formula; pooling and activations are not counted."""
    size, channels, macs = config.patch, 2, 0
    for layer in config.backbone:
        if layer == "M":
            size //= 2
            continue
        out, stride = _conv_spec(layer)
        size //= stride
        macs += size * size * out * channels * 9
        channels = out
    macs += config.flat_features * config.embed
    if config.head == "lstm":
        macs += 4 * config.hidden * (config.embed + config.hidden)
        macs += config.hidden * 8
    else:
        macs += config.embed * 8
    return macs


def count_macs(model: HomographyNet) -> int:
    """The same count as :func:`macs_per_pair`, measured with forward hooks on one pair."""
    total = [0]

    def conv_hook(m: nn.Conv2d, inputs, output):
        total[0] += output.numel() * m.in_channels * m.kernel_size[0] * m.kernel_size[1] // m.groups

    def linear_hook(m: nn.Linear, inputs, output):
        total[0] += output.numel() * m.in_features

    def lstm_hook(m: nn.LSTM, inputs, output):
        steps = output[0].shape[0] * output[0].shape[1]
        total[0] += steps * 4 * m.hidden_size * (m.input_size + m.hidden_size)

    hooks = []
    for m in model.modules():
        if isinstance(m, nn.Conv2d):
            hooks.append(m.register_forward_hook(conv_hook))
        elif isinstance(m, nn.Linear):
            hooks.append(m.register_forward_hook(linear_hook))
        elif isinstance(m, nn.LSTM):
            hooks.append(m.register_forward_hook(lstm_hook))
    p = model.config.patch
    was_training = model.training
    model.eval()
    with torch.no_grad():
        model(torch.zeros(1, 1, 2, p, p, device=next(model.parameters()).device))
    model.train(was_training)
    for h in hooks:
        h.remove()
    return total[0]


__all__ = [
    "HEADS",
    "VARIANTS",
    "PRESETS",
    "NetConfig",
    "HomographyNet",
    "LSTMState",
    "make_backbone",
    "count_parameters",
    "macs_per_pair",
    "count_macs",
]
