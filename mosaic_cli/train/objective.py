"""The training objective of each variant of the paper (Table 2):

    Loss = L + lambda_p R_p + lambda_s R_s + lambda_t1 R_t1 + lambda_t2 R_t2

=============  ====  ======  =========  ===================================
variant        head  window  positions  terms
=============  ====  ======  =========  ===================================
base           cnn   2       1          L
reg-p          cnn   2       2          L, R_p
reg-s          cnn   2       1          L, R_s
reg-t          cnn   16      1          L, R_t1, R_t2
reg-all        cnn   16      2          L, R_p, R_s, R_t1, R_t2
lstm           lstm  16      1          L
lstm-reg-t     lstm  16      1          L, R_t1, R_t2        (not in the paper)
lstm-reg-all   lstm  16      2          L, R_p, R_s, R_t1, R_t2
=============  ====  ======  =========  ===================================

A batch is ``{"frames": (B, K, 1, h, w) float in [-1, 1], "positions": (B, M, 2) long}``: K
consecutive gray working frames and the top-left (x, y) of M patches, each fully inside the
frame and used at the same place in every frame of the window (and, in a run with bursts,
``"burst"``, ``"burst_level"``, ``"burst_angle"`` (B, K): the frames the network reads spoilt,
see :mod:`.bursts`).  The objective cuts the patch
pairs itself, runs the net over the window (the LSTM starts from a zero state in each window),
turns the offsets into homographies frame t -> t+1 with the DLT, and evaluates the terms of
:mod:`.losses`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from mosaic_cli.geometry.tensor import frame_corners
from mosaic_cli.model.network import VARIANTS, HomographyNet
from mosaic_cli.model.patches import crop, offsets_to_homography, sample_patches
from mosaic_cli.train import losses
from mosaic_cli.train.bursts import spoil

TERMS = ("photometric", "spatial", "scale", "temporal1", "temporal2")

_VARIANT_TERMS = {
    "base": ("photometric",),
    "reg-p": ("photometric", "spatial"),
    "reg-s": ("photometric", "scale"),
    "reg-t": ("photometric", "temporal1", "temporal2"),
    "reg-all": TERMS,
    "lstm": ("photometric",),
    "lstm-reg-t": ("photometric", "temporal1", "temporal2"),
    "lstm-reg-all": TERMS,
}
PAPER_WINDOW = 16  # the paper's K


@dataclass
class LossWeights:
    """Weights of the terms.  ``None`` is the paper's choice: lambda_p = lambda_s = lambda_t1 =
    1/(9 N) and lambda_t2 = 1/N, N the number of compared pairs of the term.  Since the terms of
    :mod:`.losses` are already means over their N pairs, that is 1/9 and 1."""

    photometric: float = 1.0
    spatial: float | None = None
    scale: float | None = None
    temporal1: float | None = None
    temporal2: float | None = None

    def resolved(self) -> dict[str, float]:
        paper = {"photometric": 1.0, "spatial": 1 / 9, "scale": 1 / 9, "temporal1": 1 / 9, "temporal2": 1.0}
        return {k: float(paper[k] if getattr(self, k) is None else getattr(self, k)) for k in TERMS}


class Objective:
    """``objective(model, batch)`` -> every active term by name plus ``"total"``.

    ``window`` (K frames) and ``positions`` (M patches per frame pair) default to the table in the
    module docstring; ``photometric_norm`` is "l2" (the authors' code) or "l1" (the paper's text);
    ``photometric_space`` is "gray" (the paper: the network's input itself) or "band" (each frame
    band-passed and scaled to unit RMS first, :func:`.losses.band_pass`: blind to exposure, haze
    and vignetting).  The network always sees the gray patches.
    """

    def __init__(
        self,
        variant: str,
        weights: LossWeights | None = None,
        patch: int = 128,
        window: int | None = None,
        positions: int | None = None,
        photometric_norm: str = "l2",
        photometric_space: str = "gray",
    ):
        variant = variant.lower()
        if variant not in VARIANTS:
            raise ValueError(f"unknown variant {variant!r}: choose one of {', '.join(VARIANTS)}")
        if photometric_norm not in losses.PHOTOMETRIC_NORMS:
            raise ValueError(f"photometric_norm must be one of {', '.join(losses.PHOTOMETRIC_NORMS)}")
        if photometric_space not in losses.PHOTOMETRIC_SPACES:
            raise ValueError(f"photometric_space must be one of {', '.join(losses.PHOTOMETRIC_SPACES)}")
        self.variant = variant
        self.terms = _VARIANT_TERMS[variant]
        self.weights = (weights or LossWeights()).resolved()
        self.patch = int(patch)
        temporal = "temporal1" in self.terms or self.head == "lstm"
        self.window = int(window) if window is not None else (PAPER_WINDOW if temporal else 2)
        self.positions = int(positions) if positions is not None else (2 if "spatial" in self.terms else 1)
        self.photometric_norm = photometric_norm
        self.photometric_space = photometric_space
        self.check_positions = True  # off where the batches are made valid (train.data.DeviceWindows): the check waits for the device
        if self.window < 2:
            raise ValueError("window must be at least 2 frames")
        if "spatial" in self.terms and self.positions < 2:
            raise ValueError(f"{variant} needs at least 2 patch positions per frame pair (R_p)")
        if "scale" in self.terms and self.patch % 2:
            raise ValueError("R_s needs an even patch size")

    @property
    def head(self) -> str:
        """The network head this variant trains: "cnn" or "lstm"."""
        return "lstm" if self.variant.startswith("lstm") else "cnn"

    # ---------------------------------------------------------------------------------------

    def __call__(self, model: HomographyNet, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        frames, positions = batch["frames"], batch["positions"].long()
        B, K, _, h, w = frames.shape
        self.check_batch(frames, positions)
        crops = self.cut_patches(frames, positions)  # (B, K, M, 1, P, P)
        # With bursts, the network reads the spoilt frames; the photometric terms below compare the clean ones.
        read = crops if "burst" not in batch else self.cut_patches(
            spoil(frames, batch["burst"], batch["burst_level"], batch["burst_angle"]), positions)
        pairs = torch.cat([read[:, :-1], read[:, 1:]], dim=3).transpose(1, 2)  # (B, M, T, 2, P, P)
        H, H_children = self.predict(model, pairs, positions)
        corners = frame_corners(w, h, device=frames.device)
        seen, seen_crops = frames, crops  # what the photometric terms compare
        if self.photometric_space == "band":
            seen = losses.band_pass(frames)
            seen_crops = self.cut_patches(seen, positions)

        out: dict[str, Tensor] = {}
        out["photometric"] = self.pair_photometric(seen, seen_crops, H, positions)
        if "spatial" in self.terms:
            out["spatial"] = losses.spatial_consistency(H, corners)
        if "scale" in self.terms:
            out["scale"] = losses.scale_consistency(H, H_children, corners)
        if "temporal1" in self.terms:
            out["temporal1"] = losses.temporal_smoothness(H, corners)
        if "temporal2" in self.terms:
            out["temporal2"] = losses.chain_consistency(seen, H, positions, self.patch, self.photometric_norm)
        out["total"] = sum(self.weights[name] * value for name, value in out.items())
        return out

    def check_batch(self, frames: Tensor, positions: Tensor) -> None:
        """Shapes and patch positions (a negative index would silently wrap around)."""
        if frames.dim() != 5 or positions.dim() != 3 or positions.shape[-1] != 2 or len(positions) != len(frames):
            raise ValueError(f"batch shapes: frames {tuple(frames.shape)} (B, K, 1, h, w), positions {tuple(positions.shape)} (B, M, 2)")
        if not self.check_positions:
            return
        h, w = frames.shape[-2:]
        low = positions.amin(dim=(0, 1))
        high = positions.amax(dim=(0, 1))
        if bool((low < 0).any()) or int(high[0]) > w - self.patch or int(high[1]) > h - self.patch:
            raise ValueError(f"patch positions must keep {self.patch}x{self.patch} patches inside {w}x{h} frames")

    # Stages -------------------------------------------------------------------------------

    def cut_patches(self, frames: Tensor, positions: Tensor) -> Tensor:
        """(B, K, C, h, w), (B, M, 2) -> the patches (B, K, M, C, P, P) of every frame."""
        B, K = frames.shape[:2]
        pos = positions[:, None].expand(B, K, *positions.shape[1:]).flatten(0, 1)
        return crop(frames.flatten(0, 1), pos, self.patch).unflatten(0, (B, K))

    def predict(self, model: HomographyNet, pairs: Tensor, positions: Tensor) -> tuple[Tensor, Tensor | None]:
        """Homographies frame t -> t+1 of the patch pairs (B, M, T, 2, P, P) cut at ``positions``
        (B, M, 2): (B, M, T, 3, 3), and with R_s those of their quadrants (B, M, T, 4, 3, 3), else
        None.  One forward pass for all (one DDP-friendly call, one big batch); every (b, m) and
        every quadrant is its own sequence, so the LSTM starts from zeros in each window."""
        B, M, T = pairs.shape[:3]
        inputs = [pairs.flatten(0, 1)]
        if "scale" in self.terms:
            children, child_positions = self.child_pairs(pairs, positions)
            inputs.append(children.flatten(0, 1))
        offsets, _ = model(torch.cat(inputs) if len(inputs) > 1 else inputs[0])
        H = offsets_to_homography(offsets[: B * M].unflatten(0, (B, M)), positions[:, :, None, :], self.patch)
        if len(inputs) == 1:
            return H, None
        child_offsets = offsets[B * M :].unflatten(0, (B, 4 * M)) / self.child_offset_scale
        H_children = offsets_to_homography(child_offsets, child_positions[:, :, None, :], self.patch // 2)
        return H, H_children.unflatten(1, (M, 4)).transpose(2, 3)

    # A quadrant resized x2 (bilinear with pixel-centre alignment, as cv2.resize) is a similarity
    # of scale 2 of the frame: its offsets are twice the frame's, exactly.
    child_offset_scale = 2.0

    def child_pairs(self, pairs: Tensor, positions: Tensor) -> tuple[Tensor, Tensor]:
        """The four quadrants (TL, TR, BR, BL) of every patch pair resized x2 to the net's input
        size: (B, 4M, T, 2, P, P), ordered m-major, and their top-left pixels (B, 4M, 2)."""
        B, M, T, C, P, _ = pairs.shape
        half = P // 2
        children, child_positions = [], []
        for qx, qy in [(0, 0), (half, 0), (half, half), (0, half)]:
            child = pairs[..., qy : qy + half, qx : qx + half].flatten(0, 2)
            child = F.interpolate(child, scale_factor=2, mode="bilinear", align_corners=False)
            children.append(child.unflatten(0, (B, M, T)))
            child_positions.append(positions + torch.tensor([qx, qy], device=positions.device))
        return torch.stack(children, dim=2).flatten(1, 2), torch.stack(child_positions, dim=2).flatten(1, 2)

    def pair_photometric(self, frames: Tensor, crops: Tensor, H: Tensor, positions: Tensor) -> Tensor:
        """L: every patch of frame t against frame t+1 sampled through H[t]."""
        B, K = frames.shape[:2]
        M = positions.shape[1]
        T = K - 1
        nxt = frames[:, 1:].flatten(0, 1)  # (B*T, C, h, w)
        H_flat = H.transpose(1, 2).flatten(0, 1)  # (B*T, M, 3, 3)
        pos = positions[:, None].expand(B, T, M, 2).flatten(0, 1)
        warped, mask = sample_patches(nxt, H_flat, pos, self.patch)
        target = crops[:, :-1].flatten(0, 1)  # (B*T, M, C, P, P)
        return losses.photometric(target, warped, mask, self.photometric_norm)


__all__ = ["TERMS", "PAPER_WINDOW", "LossWeights", "Objective"]
