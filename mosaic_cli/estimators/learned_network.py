"""Running the learned estimator's network over a chunk of frame pairs: the patches cut, the
backbone on the whole chunk in one batch (int8 on a CPU when the weights allow), the LSTM stepped
pair by pair with its state carried through the video (and reset where ``reset-every`` asks),
offsets -> DLT -> homographies, the patches' consensus, and each pair's seed for the polish
(after the motion prior, or the identity)."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import torch

from mosaic_cli.errors import BadInput
from mosaic_cli.estimators.base import Estimator
from mosaic_cli.estimators.learned_checks import WorkFrame
from mosaic_cli.estimators.learned_config import PATCH_LAYOUTS, LearnedConfig
from mosaic_cli.geometry.tensor import four_point_to_homography, project
from mosaic_cli.model.network import HomographyNet
from mosaic_cli.model.patches import offsets_to_homography


def patch_positions(work_size: tuple[int, int], patch: int, layout: int) -> np.ndarray:
    """Top-left (x, y) of the patches (M, 2): the centre (paper: x=96, y=26 at 320x180), the
    centre and the four corners, or a 3x3 grid spread over the frame."""
    w, h = work_size
    span_x, span_y = w - patch, h - patch
    cx, cy = span_x // 2, span_y // 2
    if layout == 1:
        pts = [(cx, cy)]
    elif layout == 5:
        pts = [(cx, cy), (0, 0), (span_x, 0), (span_x, span_y), (0, span_y)]
    elif layout == 9:
        pts = [(x, y) for y in (0, cy, span_y) for x in (0, cx, span_x)]
    else:
        raise BadInput(f"patches must be one of {', '.join(map(str, PATCH_LAYOUTS))}, got {layout}")
    return np.array(pts, dtype=np.int64)


class NetworkRun(Estimator):
    """The network half of :class:`~mosaic_cli.estimators.learned.LearnedEstimator`: a chunk's
    seeds (:meth:`_seeds`), the network's homographies and how much its patches agreed."""

    # Set by LearnedEstimator (__init__, reset).
    config: LearnedConfig
    model: HomographyNet
    _features: Callable[[torch.Tensor], torch.Tensor]  # the backbone (fp32, or int8 on a CPU)
    device: torch.device
    precision: str
    patch: int
    work_size_trained: tuple[int, ...]
    positions: np.ndarray  # the patches' top-left corners (M, 2)
    _positions_t: torch.Tensor
    _corners: np.ndarray  # the working frame's corners
    _prior_warp: bool  # the network reads frame t+1 pre-aligned by the motion prior
    _motion: np.ndarray  # the last confirmed pair's motion (working px): the prior
    _state: tuple[torch.Tensor, ...] | None  # the LSTM's (h, c) between chunks
    _pairs_done: int

    def warm_up(self) -> None:
        """Run the network once on a chunk of blank pairs at the trained working size, so that
        its first real chunk does not pay for CUDA's kernels and cuDNN's plans (1.2-1.3 s on an
        H200: docs/measurements/gpu.md) or a CPU's first int8 calls.  Called by the build, which
        the commands run beside other work (the overlay detection, a live stream's opening).
        Leaves nothing behind: the LSTM's state and the pair count are as they were."""
        w, h = self.work_size_trained
        if min(w, h) < self.patch:
            return
        kept_state = (self._state, self._pairs_done)
        kept_positions = (self.positions, self._positions_t) if hasattr(self, "positions") else None  # (after a reset)
        try:
            self.positions = patch_positions((w, h), self.patch, self.config.patches)
            self._positions_t = torch.as_tensor(self.positions, device=self.device)
            blank = [np.full((h, w), 128, np.uint8)] * self.config.chunk
            self._state = None
            self._predict(blank, blank)
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
        finally:
            self._state, self._pairs_done = kept_state
            if kept_positions is not None:
                self.positions, self._positions_t = kept_positions

    def _seeds(self, frames: list[WorkFrame]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each pair's starting estimate (n, 3, 3), whether the network's offsets were finite, and
        how much its patches agreed: the network's (after the motion prior), or the identity."""
        n = len(frames) - 1
        firsts, seconds = [f.gray for f in frames[:-1]], [f.gray for f in frames[1:]]
        if self.config.polish_start == "identity":
            return np.repeat(np.eye(3)[None], n, 0), np.ones(n, bool), np.ones(n)
        if self._prior_warp:
            # The motion prior P (the last confirmed motion when the chunk starts): the network reads
            # frame t+1 pre-aligned by P and regresses the rest R, so frame t -> t+1 is P @ R.
            prior = self._motion
            seconds = [cv2.warpPerspective(g, prior, self.work_size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                           borderMode=cv2.BORDER_REPLICATE) for g in seconds]
            residual, offsets_ok, agreement = self._network(firsts, seconds)
            return prior[None] @ residual, offsets_ok, agreement
        return self._network(firsts, seconds)

    def _network(self, firsts: list[np.ndarray], seconds: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The network's homographies (n, 3, 3) for the n pairs (firsts[k], seconds[k]), whether
        its offsets were finite, and how much its patches agreed."""
        H_patches, offsets_ok = self._predict(firsts, seconds)
        H_net, agreement = self._consensus(H_patches)
        return H_net, offsets_ok, agreement

    @torch.inference_mode()
    def _predict(self, firsts: list[np.ndarray], seconds: list[np.ndarray]):
        """Working-frame homographies (n, M, 3, 3) of every patch for the n pairs (firsts[k], seconds[k])."""
        n, M, P = len(firsts), len(self.positions), self.patch
        # Cut the patches before anything else: only they are converted and sent to the device.
        cut = np.stack([[frame[y : y + P, x : x + P] for x, y in self.positions] for frame in (*firsts, *seconds)])
        crops = torch.from_numpy(cut).to(self.device, non_blocking=True).float() * (2.0 / 255.0) - 1.0  # (2n, M, P, P)
        pairs = torch.stack([crops[:n], crops[n:]], dim=2).flatten(0, 1)  # (n*M, 2, P, P) in [-1, 1]
        if self.device.type == "cpu" and self.precision == "fp32":
            pairs = pairs.contiguous(memory_format=torch.channels_last)
        feats = self._features(pairs).unflatten(0, (n, M)).transpose(0, 1)  # (M, n, F)
        offsets = self._step(feats)  # (M, n, 4, 2)
        return self._homographies(offsets)

    def _homographies(self, offsets: torch.Tensor) -> tuple[torch.Tensor, np.ndarray]:
        """Offsets (M, n, 4, 2) -> working-frame homographies (n, M, 3, 3) and whether each pair's
        offsets were finite (n,)."""
        ok = torch.isfinite(offsets).flatten(2).all(-1).all(0).cpu().numpy()
        offsets = torch.nan_to_num(offsets.double(), nan=0.0, posinf=0.0, neginf=0.0)
        H = offsets_to_homography(offsets, self._positions_t[:, None, :], self.patch)  # (M, n, 3, 3)
        return H.transpose(0, 1), ok

    def _step(self, feats: torch.Tensor) -> torch.Tensor:
        """Regress the chunk's offsets, carrying (and if asked, periodically resetting) the LSTM state."""
        offsets, self._state = self._step_from(feats, self._state, self._pairs_done)
        self._pairs_done += feats.shape[1]
        return offsets

    def _step_from(self, feats: torch.Tensor, state: tuple[torch.Tensor, ...] | None,
                   done: int) -> tuple[torch.Tensor, tuple[torch.Tensor, ...] | None]:
        """The offsets of the pairs ``feats`` (M, n, F) from ``state`` after ``done`` pairs of the
        video, and the state after them: restarted where ``reset-every`` asks."""
        every = self.config.reset_every if self.model.head == "lstm" else None
        if not every:
            return self.model.step(feats, state)
        parts, start = [], 0
        while start < feats.shape[1]:
            if done % every == 0:
                state = None
            size = min(every - done % every, feats.shape[1] - start)
            part = slice(start, start + size)
            offsets, state = self.model.step(feats[:, part], state)
            parts.append(offsets)
            start += size
            done += size
        return torch.cat(parts, dim=1), state

    def _consensus(self, H_patches: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """One homography per pair from M patch estimates: the DLT of the per-corner median of
        where they send the frame corners; agreement = 1 / (1 + (spread / agreement_px)^2), the
        spread being the median over patches of their mean corner distance to the consensus."""
        n, M = H_patches.shape[:2]
        if M == 1:
            return H_patches[:, 0].cpu().numpy(), np.ones(n)
        corners = torch.as_tensor(self._corners, dtype=H_patches.dtype, device=H_patches.device)
        moved = project(H_patches, corners)  # (n, M, 4, 2)
        median = moved.median(dim=1).values  # (n, 4, 2)
        H = four_point_to_homography(corners.expand(n, 4, 2), median - corners)
        spread = (moved - median[:, None]).norm(dim=-1).mean(-1).median(dim=1).values
        agreement = 1.0 / (1.0 + (spread / self.config.agreement_px) ** 2)
        return H.cpu().numpy(), agreement.cpu().numpy()
