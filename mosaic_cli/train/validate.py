"""Validation during training: the paper's MACE on flights with known homographies.

``--val VAL_DIR`` holds videos written by ``mosaic simulate`` (``X.mp4`` with ``X.gt.json``
beside it).  The network runs as ``mosaic track`` runs it (the centre patch of each gray
working frame, the LSTM state carried through the whole flight), its pairwise homographies
are scored against landmarks derived from the ground truth every 30 frames, and the errors
are averaged over the (f1, f2) pairs of all flights together, as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mosaic_cli.errors import BadInput
from mosaic_cli.evaluate import landmarks_from_ground_truth, mace_pairs
from mosaic_cli.geometry import to_resolution
from mosaic_cli.model.dlt import offsets_to_homography
from mosaic_cli.model.network import HomographyNet
from mosaic_cli.simulate import ground_truth_path, load_ground_truth
from mosaic_cli.train.data import VIDEO_SUFFIXES
from mosaic_cli.video import open_video


@dataclass(frozen=True)
class ValFlight:
    video: Path
    gt: object  # mosaic_cli.simulate.GroundTruth
    landmarks: np.ndarray  # (n, 6) f1 x1 y1 f2 x2 y2


def find_flights(folder: str | Path) -> list[ValFlight]:
    """Every video in ``folder`` with a ``.gt.json`` beside it (others are ignored)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise BadInput(f"--val {folder}: no such folder")
    flights = []
    for video in sorted(p for p in folder.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES):
        if ground_truth_path(video).is_file():
            gt = load_ground_truth(video)
            landmarks = landmarks_from_ground_truth(gt)
            if len(landmarks):
                flights.append(ValFlight(video, gt, landmarks))
    if not flights:
        raise BadInput(f"--val {folder}: no video with a .gt.json beside it and 30+ frames (make some with mosaic simulate)")
    return flights


@torch.no_grad()
def flight_pairwise(net: HomographyNet, video: Path, device: torch.device, work_width: int, chunk: int = 32) -> np.ndarray:
    """Pairwise homographies (N-1, 3, 3), frame t -> t+1 in full-resolution pixels, from the
    network on the centre patch of every working frame, streaming ``chunk`` pairs at a time."""
    net.eval()
    P = net.config.patch
    out: list[np.ndarray] = []
    with open_video(video, width=work_width, gray=True) as stream:
        full_size = stream.info.source_size
        state, prev, pairs, work_size = None, None, [], None
        for frame in stream:
            h, w = frame.shape
            if h < P or w < P:
                raise BadInput(f"{video}: {w}x{h} working frames are smaller than the {P}px patch")
            work_size = (w, h)
            x0, y0 = (w - P) // 2, (h - P) // 2
            patch = frame[y0:y0 + P, x0:x0 + P]
            if prev is not None:
                pairs.append(np.stack([prev, patch]))
            prev = patch
            if len(pairs) == chunk:
                state = _run(net, pairs, (x0, y0), device, state, out)
                pairs = []
        if pairs:
            _run(net, pairs, (x0, y0), device, state, out)
    if not out:
        return np.zeros((0, 3, 3))
    H_work = np.concatenate(out)
    return to_resolution(H_work, work_size, full_size)


def _run(net, pairs, top_left, device, state, out):
    x = torch.from_numpy(np.stack(pairs)).to(device).float().div_(127.5).sub_(1.0)[None]  # (1, T, 2, P, P)
    offsets, state = net(x, state)
    position = torch.tensor(top_left, device=device, dtype=torch.float32)
    H = offsets_to_homography(offsets[0].float(), position, net.config.patch)
    out.append(H.double().cpu().numpy())
    return state


def validation_mace(net: HomographyNet, flights: list[ValFlight], device: torch.device,
                    work_size: tuple[int, int]) -> float:
    """MACE (1280x720-equivalent px) over all landmark pairs of all flights."""
    errors = []
    for flight in flights:
        pairwise = flight_pairwise(net, flight.video, device, work_size[0])
        n = len(pairwise)
        landmarks = flight.landmarks[flight.landmarks[:, 3] <= n]
        if len(landmarks):
            errors.append(mace_pairs(pairwise, landmarks, flight.gt.size)[1])
    return float(np.mean(np.concatenate(errors))) if errors else float("nan")
