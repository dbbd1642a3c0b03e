"""The learned estimator's per-pair checks batched on the device: a chunk's cheap LK polish, its
refit and the correlation check in one batch (:mod:`.batched`, OpenCV's arithmetic), for a GPU or
``polish-with=torch``.  A pair it settles gets the check :meth:`.PairChecks._check` would give it;
the others are left to that check."""

from __future__ import annotations

import numpy as np
import torch

from mosaic_cli.estimators import batched
from mosaic_cli.estimators.learned_checks import PairCheck, PairChecks, WorkFrame
from mosaic_cli.estimators.refine import Polish, erode_mask
from mosaic_cli.geometry import is_valid


class BatchedPairChecks(PairChecks):
    """:class:`.PairChecks` with a chunk's checks batched on the device (:meth:`_batch_checks`)."""

    # Set by LearnedEstimator (__init__, reset).
    device: torch.device
    _positions_t: torch.Tensor
    _batch_masks_t: tuple | None

    def _batch_checks(self, pairs: list[tuple[WorkFrame, WorkFrame]], seeds: np.ndarray,
                      offsets_ok: np.ndarray) -> list[PairCheck | None]:
        """The checks of the pairs the batched polish settles (:mod:`.batched`): the cheap LK polish
        of every plausible pair of textured frames, its refit and the correlation of the detail it
        registers, in one batch on the device and one copy back; a pair settles when the refit
        holds (enough inliers, close to the seed, plausible: :func:`.batched.settled`) and
        its detail correlates, as :meth:`_check` settles it without the wide polish or the
        fallback.  None for the others."""
        c = self.config
        checks: list[PairCheck | None] = [None] * len(pairs)
        todo = [k for k, (prev, cur) in enumerate(pairs) if prev.textured and cur.textured and bool(offsets_ok[k])
                and is_valid(seeds[k], self.work_size, max_area_ratio=c.max_area_ratio)]
        if not todo:
            return checks
        dev = self.device
        firsts, seconds = [pairs[k][0] for k in todo], [pairs[k][1] for k in todo]
        tracked = [f.points for f in firsts]  # a textured frame has its corners (refine=lk)
        counts = [0 if p is None else len(p) for p in tracked]
        points = np.zeros((len(todo), max(counts), 2), np.float32)
        for i, p in enumerate(tracked):
            points[i, : counts[i]] = p

        def stack(images: list) -> torch.Tensor:
            return torch.from_numpy(np.stack(images)).to(dev, non_blocking=True)

        allowed, usable, mask = self._batch_masks()
        result = batched.polish(stack([f.aligned for f in firsts]), stack([f.aligned for f in seconds]),
                                torch.from_numpy(seeds[todo]).to(dev), torch.from_numpy(points).to(dev),
                                torch.as_tensor(counts, device=dev), c.polish, allowed)
        zncc = batched.detail_zncc(batched.fine_detail(stack([f.gray for f in firsts])), batched.fine_detail(stack([f.gray for f in seconds])),
                                   result.H, self._positions_t, self.patch, usable, mask)
        back = torch.cat([result.H.flatten(1), result.found[:, None].double(), result.inliers[:, None].double(), zncc[:, None]], 1).cpu().numpy()
        for i, k in enumerate(todo):
            H, found, inliers, score = back[i, :9].reshape(3, 3), back[i, 9] > 0, back[i, 10], float(back[i, 11])
            if not found or (c.min_zncc is not None and score < c.min_zncc):
                continue
            checks[k] = PairCheck(True, Polish(H, True, float(inliers) / counts[i]), score, True, None)
        return checks

    def _batch_masks(self) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor | None]:
        """On the device, once a video: the pixels a cheap polish's track may touch (the mask eroded
        by its window's half; None: all), the usable pixels of the correlation check, the mask."""
        if self._batch_masks_t is None:
            use = torch.from_numpy(self._valid_pixels()).to(self.device)
            if self.work_mask is None:
                self._batch_masks_t = (None, use, None)
            else:
                eroded = erode_mask(self.work_mask, self.config.polish.window // 2 + 1)
                self._batch_masks_t = (torch.from_numpy(eroded).to(self.device), use, torch.from_numpy(self.work_mask).to(self.device))
        return self._batch_masks_t
