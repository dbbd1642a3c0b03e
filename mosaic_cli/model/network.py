"""The homography network of the paper (Table 1), in one file.

    patches (B, T, 2, P, P)  two gray patches, frame t and frame t+1 at the same place, in [-1, 1]
      -> backbone            VGG-like 3x3 convs + ReLU (no BatchNorm, as the paper)
      -> flatten             the spatial layout is kept: no global pooling
      -> embed               [dropout] Linear -> ReLU                       features (B, T, F)
      -> head "cnn"          dropout -> Linear(F, 8)                        (BASE, REG-*)
         head "lstm"         LSTM(F, hidden) -> dropout -> Linear(hidden, 8) (LSTM, LSTM-REG-ALL)
         head "carry"        the BASE's head (the CNN's Linear(F, 8), or     (CARRY: the sequence
                             LSTM-REG-T's LSTM and Linear: carry_base), then  model that remembers)
                             a gated LSTM cell that blends a carried motion
                             with its answer (CarryHead)
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

HEADS = ("cnn", "lstm", "carry")
SEQUENCE_HEADS = ("lstm", "carry")  # the heads with a state carried from pair to pair
# The paper's training variants (Table 2; what each trains: mosaic_cli.train.objective).  A
# checkpoint records the variant that made it, so the model side knows their names.
# lstm-reg-t is not in the paper: the LSTM with the temporal priors alone, which costs a tenth of
# lstm-reg-all's forward passes (that reads two patches of every pair, and for R_s four quadrants of each).
# carry is not in the paper either: the CARRY head (below) trained on cached features against a teacher (train.carry).
VARIANTS = ("base", "reg-p", "reg-s", "reg-t", "reg-all", "lstm", "lstm-reg-t", "lstm-reg-all", "carry")

PRESETS: dict[str, dict[str, Any]] = {
    "paper": dict(backbone=(64, 64, "M", 64, 64, "M", 128, 128, "M", 128, 128), embed=1024, hidden=1024, dropout=0.5),
    "compact": dict(backbone=((32, 2), 32, 32, "M", 64, 64, "M", 64, 64, "M"), embed=512, hidden=512, dropout=0.3),
}

CARRY_BASES = ("cnn", "lstm")  # the heads a carry head may read the BASE's answer from (NetConfig.carry_base)

LSTMState = tuple[Tensor, ...]  # (h, c) of the "lstm" head, (h, c, previous offsets) of the "carry" head


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
    carry_code: int = 64  # carry head: the features' code its cell and gate read
    carry_hidden: int = 128  # carry head: its LSTM cell's size
    carry_window: int = 32  # carry head: the training window (frames); its forget gates start at timescales up to it
    carry_cues: int = 0  # carry head: per-pair image cues it also reads (patch_cues: 0 or CUES)
    carry_correction: float | None = None  # carry head: the most its cell may move the carried motion (working px); None: unbounded
    carry_gate_memory: bool = True  # carry head: its gate reads the cell's state too (False: the current pair's evidence alone)
    carry_base: str = "cnn"  # carry head: the head whose answer it blends ("cnn": the BASE's Linear; "lstm": LSTM-REG-T's LSTM and Linear)

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
        if self.carry_base not in CARRY_BASES:
            raise ValueError(f"unknown carry base {self.carry_base!r}: choose one of {', '.join(CARRY_BASES)}")
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



# The carry head's cell reads offsets divided by this (working px): the motions of a frame pair
# are a few to some tens of px, which this brings to order one.
OFFSET_SCALE = 8.0
# The gate's starting logit: sigmoid(-5) = 0.0067 of the carried motion, the rest the CNN's.  A
# window's first pair is the CNN's exactly; later pairs differ from it by 0.7% of the carried
# motion's distance to it.  The gate opens through the weights of its input layer, which start
# far from saturation, not through this bias: the shipped head's stayed near -5 while its gate
# learned to weigh the carried motion 0.79 on event pairs (models/README.md, "The carry head").
GATE_START = -5.0
GATE_HIDDEN = 32
CUES = 6  # patch_cues per pair


def patch_cues(pairs: Tensor) -> Tensor:
    """(N, 2, P, P) patch pairs in [-1, 1] -> (N, 6) cues of whether each frame can show motion:
    per patch its mean, its contrast (standard deviation) and the log of its mean absolute
    gradient.  Glare, darkness and flat ground collapse the contrast, which the features alone
    show the head less directly."""
    x = pairs.float()
    gradient = (x[..., :, 1:] - x[..., :, :-1]).abs().mean((-1, -2)) + (x[..., 1:, :] - x[..., :-1, :]).abs().mean((-1, -2))
    return torch.cat([x.mean((-1, -2)), x.std((-1, -2)), torch.log(gradient + 1e-3)], dim=1)


class CarryHead(nn.Module):
    """A sequence head that carries the motion itself (issue 38).  Per frame pair t, from the
    pair's features f_t, its image cues k_t (:func:`patch_cues`, where the config asks for them),
    the CNN's offsets o_t (the frozen BASE head on f_t) and its own previous output y_{t-1}::

        x_t = [relu(code(f_t)), k_t, o_t / S, y_{t-1} / S]
        h_t, c_t = LSTMCell(x_t, (h_{t-1}, c_{t-1}))         the memory
        m_t = y_{t-1} + S * motion(h_t)                       the carried motion, corrected
                                                              (or by at most C px: C tanh(motion(h_t)))
        w_t = sigmoid(gate([h_t, x_t, |o_t - y_{t-1}| / S]))  how far to trust it (without h_t where
                                                              gate_memory is off: the pair's evidence alone)
        y_t = o_t + w_t (m_t - o_t)

    ``motion`` starts at zero and the gate at GATE_START, so the head starts as the CNN (exactly
    on a sequence's first pair, where y_{-1} is o_0, then within 0.7% of the carried motion's
    distance); the cell's forget gates start with chrono initialisation (biases log U(1, W-1),
    the input gates' their negatives: Tallec & Ollivier, 2018) so that its memory spans up to
    a training window of W frames from the first step.  The state is (h, c, y_{t-1}); none
    starts a sequence."""

    def __init__(self, features: int, code: int, hidden: int, window: int, cues: int = 0, correction: float | None = None,
                 gate_memory: bool = True):
        super().__init__()
        self.hidden, self.features, self.cues, self.correction = hidden, features, cues, correction
        self.gate_memory = gate_memory
        self.code = nn.Linear(features, code)
        self.cell = nn.LSTMCell(code + cues + 16, hidden)
        self.motion = nn.Linear(hidden, 8)
        self.gate = nn.Sequential(nn.Linear(hidden * gate_memory + code + cues + 24, GATE_HIDDEN), nn.ReLU(), nn.Linear(GATE_HIDDEN, 1))
        self.window = window

    @torch.no_grad()
    def reset_parameters(self) -> None:
        nn.init.kaiming_normal_(self.code.weight, nonlinearity="relu")
        nn.init.zeros_(self.code.bias)
        self.cell.reset_parameters()
        h = self.hidden
        chrono = torch.log(torch.empty(h).uniform_(1.0, max(2.0, float(self.window - 1))))
        self.cell.bias_ih[h : 2 * h] = chrono  # gates in torch's order: i, f, g, o
        self.cell.bias_ih[:h] = -chrono
        self.cell.bias_hh.zero_()
        nn.init.zeros_(self.motion.weight)
        nn.init.zeros_(self.motion.bias)
        nn.init.kaiming_normal_(self.gate[0].weight, nonlinearity="relu")
        nn.init.zeros_(self.gate[0].bias)
        nn.init.zeros_(self.gate[2].weight)
        nn.init.constant_(self.gate[2].bias, GATE_START)

    def forward(self, features: Tensor, cnn: Tensor, state: LSTMState | None = None, confirmed: Tensor | None = None,
                confirm: Tensor | None = None, trust: Tensor | None = None) -> tuple[Tensor, LSTMState, Tensor]:
        """features (B, T, F) (with cues, (B, T, F + cues): :func:`patch_cues` appended), the
        CNN's offsets (B, T, 8) -> offsets (B, T, 8), the state after the last pair, and the gate
        w (B, T): the weight each pair gave the carried motion.  ``confirmed`` (B, T, 8) and
        ``confirm`` (B, T) bool: after each pair t where ``confirm`` holds, the previous output
        the next pair reads (y_t) is ``confirmed[:, t]`` instead of the head's own: the motion the
        frames confirmed (the teacher's in training, the polished or fallback estimate at
        inference), so that a burst starts from a checked motion rather than an unchecked one.
        ``trust`` (B, T) bool: the pairs whose gate is 1 whatever it reads (the carried motion
        taken whole: the estimator's ``carry-blend=spoilt``, on pairs it found a spoilt frame in)."""
        B, T = cnn.shape[:2]
        if state is None:
            zeros = cnn.new_zeros(B, self.hidden)
            h, c, previous = zeros, zeros, cnn[:, 0]
        else:
            h, c, previous = (s[0] for s in state)
        code = torch.relu(self.code(features[..., : self.features]))
        if self.cues:
            code = torch.cat([code, features[..., self.features:]], dim=-1)
        outputs, weights = [], []
        for t in range(T):
            x = torch.cat([code[:, t], cnn[:, t] / OFFSET_SCALE, previous / OFFSET_SCALE], dim=1)
            h, c = self.cell(x, (h, c))
            step = OFFSET_SCALE * self.motion(h) if self.correction is None else self.correction * torch.tanh(self.motion(h))
            carried = previous + step
            disagreement = (cnn[:, t] - previous).abs() / OFFSET_SCALE
            w = torch.sigmoid(self.gate(torch.cat([h, x, disagreement] if self.gate_memory else [x, disagreement], dim=1)))
            if trust is not None:
                w = torch.where(trust[:, t, None], torch.ones_like(w), w)
            previous = cnn[:, t] + w * (carried - cnn[:, t])
            outputs.append(previous)
            if confirm is not None and confirmed is not None:
                previous = torch.where(confirm[:, t, None], confirmed[:, t], previous)
            weights.append(w[:, 0])
        return torch.stack(outputs, 1), (h[None], c[None], previous[None]), torch.stack(weights, 1)


class HomographyNet(nn.Module):
    """Patch pairs -> corner offsets (working pixels, frame t -> frame t+1); see the module doc."""

    def __init__(self, config: NetConfig | None = None):
        super().__init__()
        self.config = config = config or NetConfig()
        self.backbone = make_backbone(config.backbone)
        self.embed = nn.Linear(config.flat_features, config.embed)
        if config.head == "lstm" or (config.head == "carry" and config.carry_base == "lstm"):
            self.lstm = nn.LSTM(config.embed, config.hidden, num_layers=1, batch_first=True)
            regressor_in = config.hidden
        else:
            self.lstm = None
            regressor_in = config.embed
        self.dropout = nn.Dropout(config.dropout)
        self.regressor = nn.Linear(regressor_in, 8)  # the carry head: the CNN's, which it reads
        self.carry = (CarryHead(config.embed, config.carry_code, config.carry_hidden, config.carry_window, config.carry_cues,
                                config.carry_correction, config.carry_gate_memory) if config.head == "carry" else None)
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
        if self.carry is not None:
            self.carry.reset_parameters()

    @property
    def head(self) -> str:
        return self.config.head

    def features(self, patches: Tensor) -> Tensor:
        """(N, 2, P, P) patch pairs -> (N, F) features (backbone, flatten, first Linear, ReLU)."""
        x = self.backbone(patches).flatten(1)
        if self.lstm is None:
            # The paper drops out before both Linears of the CNN head only.  The carry head reads
            # the CNN's features as they are, the same graph, so the CNN's int8 ranges fit it.
            x = self.dropout(x)
        return torch.relu(self.embed(x))

    def step(self, features: Tensor, state: LSTMState | None = None, trust: Tensor | None = None) -> tuple[Tensor, LSTMState | None]:
        """(B, T, F) features of T consecutive pairs -> offsets (B, T, 4, 2) and the new LSTM
        state (h, c), each (1, B, hidden); ``state=None`` starts from zeros.  The carry head's
        state is (h, c, y) (:meth:`carry_step`; ``trust``: its pairs that take the carried motion
        whole, :class:`CarryHead`); the CNN head has no state and returns None."""
        if self.carry is not None:
            offsets, state, _ = self.carry_step(features, state, trust)
            return offsets.unflatten(-1, (4, 2)), state
        if self.lstm is not None:
            features, state = self.lstm(features, state)
        else:
            state = None
        offsets = self.regressor(self.dropout(features))
        return offsets.unflatten(-1, (4, 2)), state

    def base_offsets(self, features: Tensor, state: LSTMState | None = None) -> tuple[Tensor, LSTMState | None]:
        """The BASE's answer that a carry head reads: (B, T, F) features -> offsets (B, T, 8) and
        the BASE's own state after them (h, c of LSTM-REG-T's LSTM; None for the CNN's Linear)."""
        if self.lstm is None:
            return self.regressor(features), None
        out, state = self.lstm(features, state)
        return self.regressor(out), state

    def carry_step(self, features: Tensor, state: LSTMState | None = None,
                   trust: Tensor | None = None) -> tuple[Tensor, LSTMState, Tensor]:
        """The carry head's step: (B, T, F [+ cues]) -> offsets (B, T, 8), the state, the gate (B, T).

        The state is (h, c, previous output), as :class:`CarryHead`'s; over an LSTM base, h and c
        are the head's cell's followed by the base LSTM's (one tuple, so that a restart, or the
        estimator feeding the previous output, treats both alike)."""
        assert self.carry is not None
        carry_state, base_state = self.split_carry_state(state)
        base, base_state = self.base_offsets(features[..., : self.config.embed], base_state)
        offsets, carry_state, gate = self.carry(features, base, carry_state, trust=trust)
        if base_state is not None:
            h, c, previous = carry_state
            carry_state = (torch.cat([h, base_state[0]], -1), torch.cat([c, base_state[1]], -1), previous)
        return offsets, carry_state, gate

    def split_carry_state(self, state: LSTMState | None) -> tuple[LSTMState | None, LSTMState | None]:
        """A carry head's state (:meth:`carry_step`) -> the head's own (h, c, previous output) and
        its BASE's (h, c of LSTM-REG-T's LSTM; None over the CNN's Linear, or with no state)."""
        if state is None or self.lstm is None:
            return state, None
        k = self.config.carry_hidden
        h, c, previous = state
        return (h[..., :k], c[..., :k], previous), (h[..., k:].contiguous(), c[..., k:].contiguous())

    def head_inputs(self, patches: Tensor, features: Tensor) -> Tensor:
        """What :meth:`step` reads of the pairs (N, 2, P, P) whose features (N, F) these are: the
        features, with :func:`patch_cues` appended for a carry head that reads them."""
        if self.carry is None or not self.config.carry_cues:
            return features
        return torch.cat([features, patch_cues(patches).to(features.dtype)], dim=-1)

    def forward(self, patches: Tensor, state: LSTMState | None = None) -> tuple[Tensor, LSTMState | None]:
        """(B, T, 2, P, P) -> offsets (B, T, 4, 2), state (see :meth:`step`)."""
        B, T = patches.shape[:2]
        flat = patches.flatten(0, 1)
        feats = self.head_inputs(flat, self.features(flat)).unflatten(0, (B, T))
        return self.step(feats, state)

    def feature_parameters(self) -> list[nn.Parameter]:
        """Backbone and first Linear: the part an LSTM variant takes (frozen) from a trained CNN;
        for the carry head also its BASE's head (the regressor, and LSTM-REG-T's LSTM), which it reads."""
        frozen = list(self.backbone.parameters()) + list(self.embed.parameters())
        if self.carry is None:
            return frozen
        return frozen + list(self.regressor.parameters()) + (list(self.lstm.parameters()) if self.lstm is not None else [])

    @torch.no_grad()
    def start_as_carry(self, base: HomographyNet) -> None:
        """A carry head on ``base`` (a CNN, or LSTM-REG-T where ``carry_base`` is "lstm"): its
        features and head copied (the carry head then starts as the base: :class:`CarryHead`)."""
        if self.carry is None or base.config.head != self.config.carry_base:
            raise ValueError(f"start_as_carry makes a carry head on a {self.config.carry_base} head, not {base.config.head}")
        self.load_features_from(base)
        self.regressor.load_state_dict(base.regressor.state_dict())
        if self.lstm is not None:
            self.lstm.load_state_dict(base.lstm.state_dict())

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
    if config.head == "lstm" or (config.head == "carry" and config.carry_base == "lstm"):
        macs += 4 * config.hidden * (config.embed + config.hidden)
        macs += config.hidden * 8
    else:
        macs += config.embed * 8
    if config.head == "carry":
        code, hidden, cues = config.carry_code, config.carry_hidden, config.carry_cues
        macs += config.embed * code + 4 * hidden * (code + cues + 16 + hidden) + hidden * 8
        macs += (hidden * config.carry_gate_memory + code + cues + 24) * GATE_HIDDEN + GATE_HIDDEN
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

    def cell_hook(m: nn.LSTMCell, inputs, output):
        total[0] += output[0].shape[0] * 4 * m.hidden_size * (m.input_size + m.hidden_size)

    hooks = []
    for m in model.modules():
        if isinstance(m, nn.Conv2d):
            hooks.append(m.register_forward_hook(conv_hook))
        elif isinstance(m, nn.Linear):
            hooks.append(m.register_forward_hook(linear_hook))
        elif isinstance(m, nn.LSTM):
            hooks.append(m.register_forward_hook(lstm_hook))
        elif isinstance(m, nn.LSTMCell):
            hooks.append(m.register_forward_hook(cell_hook))
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
    "SEQUENCE_HEADS",
    "VARIANTS",
    "CarryHead",
    "CUES",
    "patch_cues",
    "PRESETS",
    "NetConfig",
    "HomographyNet",
    "LSTMState",
    "make_backbone",
    "count_parameters",
    "macs_per_pair",
    "count_macs",
]
