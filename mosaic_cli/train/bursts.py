"""Training for the stretches where the frames carry no motion cue (``mosaic train --bursts P``).

A fraction P of the training windows gets one burst: 1-3 consecutive frames, never the first
or the last of the window, spoilt as the simulator spoils them (:mod:`mosaic_cli.simulate.bursts`):
washed out by glare, smeared by a gust's blur, nearly black, or featureless.  The network reads
the spoilt frames; every photometric term compares the clean ones.  The clean frames are the
same raw video (no label is used), but a pair that touches a spoilt frame can only be placed
from what came before it: for the LSTM, the motion its state carries.  A pairwise network (the
CNN) sees nothing there to learn from; the sequence model learns to carry the motion through.

The draws come from the window's own generator (``(seed, index)``), after every other draw, so
that a run without bursts sees exactly the samples it always did.  The spoiling itself runs in
torch on the training device (:func:`spoil`), batched: a GPU pays nothing to the host for it.
"""

from __future__ import annotations

import numpy as np
import torch
from kornia.filters import motion_blur
from torch import Tensor

from mosaic_cli.simulate.bursts import CODES, PIXEL_KINDS
from mosaic_cli.simulate.bursts import LEVELS as SIMULATED_LEVELS

GLARE, BLUR, DARK, FLAT = (CODES[k] for k in PIXEL_KINDS)  # a frame's burst code; 0: clean
MAX_LENGTH = 3  # spoilt frames in a row
LEVELS = {CODES[k]: SIMULATED_LEVELS[k] for k in PIXEL_KINDS}  # the simulator's strengths, by code
BURST_KEYS = ("burst", "burst_level", "burst_angle")  # what a window of a run with bursts carries
NOISE = 2.0 / 127.5  # the sensor's floor on a spoilt frame (2 gray levels), in [-1, 1] units


def draw_burst(rng: np.random.Generator, window: int, probability: float) -> dict[str, np.ndarray]:
    """Per frame of a window of ``window`` frames: the burst code (0: clean), its level and the
    blur's angle (degrees); with ``probability`` one burst, frames 1..window-2 only."""
    code = np.zeros(window, np.int64)
    level = np.zeros(window, np.float32)
    angle = np.zeros(window, np.float32)
    if window >= 3 and rng.random() < probability:
        length = int(rng.integers(1, min(MAX_LENGTH, window - 2) + 1))
        first = int(rng.integers(1, window - length))  # frames first .. first+length-1 within 1..window-2
        kind = int(rng.integers(1, len(LEVELS) + 1))
        for t in range(first, first + length):
            code[t] = kind
            level[t] = rng.uniform(*LEVELS[kind])
            angle[t] = rng.uniform(0.0, 180.0)
    return {"burst": code, "burst_level": level, "burst_angle": angle}


def draw_bursts(generator: torch.Generator, batch: int, window: int, probability: float, device) -> dict[str, Tensor]:
    """:func:`draw_burst` for a whole batch at once, on ``device`` (``--data device``): (B, K)
    codes, levels and angles."""
    g, B, K = generator, int(batch), int(window)
    code = torch.zeros(B, K, dtype=torch.long, device=device)
    level = torch.zeros(B, K, device=device)
    angle = torch.zeros(B, K, device=device)
    if K < 3:
        return {"burst": code, "burst_level": level, "burst_angle": angle}
    has = torch.rand(B, generator=g, device=device) < probability
    length = torch.randint(1, min(MAX_LENGTH, K - 2) + 1, (B,), generator=g, device=device)
    first = 1 + (torch.rand(B, generator=g, device=device) * (K - 1 - length)).long()  # 1 .. K-1-length
    kind = torch.randint(1, len(LEVELS) + 1, (B,), generator=g, device=device)
    t = torch.arange(K, device=device)
    inside = has[:, None] & (t >= first[:, None]) & (t < (first + length)[:, None])
    code = torch.where(inside, kind[:, None], code)
    low = torch.tensor([0.0] + [LEVELS[k][0] for k in sorted(LEVELS)], device=device)[code]
    high = torch.tensor([0.0] + [LEVELS[k][1] for k in sorted(LEVELS)], device=device)[code]
    level = low + (high - low) * torch.rand(B, K, generator=g, device=device)
    angle = torch.where(inside, 180.0 * torch.rand(B, K, generator=g, device=device), angle)
    return {"burst": code, "burst_level": level, "burst_angle": angle}


def spoil(frames: Tensor, code: Tensor, level: Tensor, angle: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """``frames`` (B, K, 1, h, w) in [-1, 1] with the frames whose ``code`` (B, K) is non-zero
    spoilt as :func:`draw_burst` drew them (``level``, ``angle`` (B, K)); a new tensor, the
    clean frames unchanged.  Blur lengths are in 1280-wide px, scaled to the frames' width."""
    out = frames.clone()
    hit = code > 0
    if not bool(hit.any()):
        return out
    w = frames.shape[-1]
    lvl = level[..., None, None, None].to(frames.dtype)
    glare, dark, flat = (code == GLARE), (code == DARK), (code == FLAT)
    if bool(glare.any()):
        out[glare] = 1.0 - (1.0 - frames[glare]) * lvl[glare]
    if bool(dark.any()):
        out[dark] = -1.0 + (frames[dark] + 1.0) * lvl[dark]
    if bool(flat.any()):
        mean = frames[flat].mean(dim=(-1, -2), keepdim=True)
        out[flat] = mean + (frames[flat] - mean) * lvl[flat]
    for b, k in (code == BLUR).nonzero().tolist():  # a few frames a batch: one kernel each
        length = max(3, int(round(float(level[b, k]) * w / 1280.0)) | 1)
        out[b, k] = motion_blur(frames[b, k][None], length, float(angle[b, k]), 0.0, border_type="reflect")[0]
    noise = torch.randn(out[hit].shape, generator=generator, device=frames.device, dtype=frames.dtype) * NOISE
    out[hit] = (out[hit] + noise).clamp(-1.0, 1.0)
    return out


__all__ = ["BURST_KEYS", "draw_burst", "draw_bursts", "spoil"]
