"""Flights that come back over their own ground: forward then backward, twice in a row with
a cut, a cut to unrelated ground.  Exact truth from the simulator: the backward pass's
map -> frame homographies are the forward pass's, reversed."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from conftest import textured_image
from mosaic_cli.estimators.orb import OrbConfig, OrbEstimator
from mosaic_cli.geometry import corner_error, frame_corners, project
from mosaic_cli.simulate import plan_flight, render_frames
from mosaic_cli.stitch import RegistrationOptions, StitchOptions, stitch
from mosaic_cli.video import VideoWriter

SIZE = (256, 144)
MAP_SIZE = (1024, 1024)


@pytest.fixture(scope="module")
def ground() -> np.ndarray:
    return textured_image(*MAP_SIZE, seed=5)


@pytest.fixture(scope="module")
def forward(ground):
    """A straight-ish fast flight, 150 frames: its frames and their exact map -> frame."""
    plan = plan_flight(MAP_SIZE, "fast", frames=150, size=SIZE, seed=2)
    return list(render_frames(ground, plan)), plan.map_to_frame


def write(path: Path, frames) -> Path:
    with VideoWriter(path, SIZE, 30.0, crf=16, preset="veryfast") as writer:
        for frame in frames:
            writer.write(frame)
    return path


def orb():
    return OrbEstimator(SIZE[0], OrbConfig(refine=None))


def load(path: Path):
    data = json.loads(Path(path).read_text())
    return tuple(data["canvas_size"]), [f["index"] for f in data["frames"]], [np.array(f["H"]) for f in data["frames"]]


def placement_errors(indices, frame_to_pano, truth, gap: int = 60) -> np.ndarray:
    """Corner error of frame i placed relative to frame j through the panorama, against the
    exact homography, for used frames at least ``gap`` frames apart."""
    return np.array([
        corner_error(np.linalg.inv(frame_to_pano[b]) @ frame_to_pano[a], truth[j] @ np.linalg.inv(truth[i]), SIZE)
        for a, i in enumerate(indices)
        for b, j in enumerate(indices)
        if j - i >= gap
    ])


def test_forward_then_backward_keeps_its_scale_and_drift_control_is_not_worse(tmp_path, forward):
    frames, m = forward
    video = write(tmp_path / "fb.mp4", frames + frames[::-1])
    truth = np.concatenate([m, m[::-1]])
    errors, canvases = {}, {}
    for drift_control in (True, False):
        json_path = tmp_path / f"t{drift_control}.json"
        options = StitchOptions(registration=RegistrationOptions(enabled=drift_control))
        result = stitch(video, tmp_path / "p.png", orb(), options, transforms=json_path, show_progress=False)
        canvases[drift_control], indices, H = load(json_path)
        errors[drift_control] = placement_errors(indices, H, truth)
        if drift_control:
            assert result.registration.loops >= 5  # the backward pass was registered on the forward one
            # Each backward keyframe lands on the forward frame of the same ground.
            first_half = [k for k, i in enumerate(indices) if i < len(frames)]
            centre = np.array([(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])
            for b, j in enumerate(indices):
                if j >= len(frames):
                    twin = len(truth) - 1 - j  # the same frame, flown forward
                    ground_point = project(np.linalg.inv(truth[j]), centre[None])
                    a = min(first_half, key=lambda k: abs(indices[k] - twin))
                    in_a = project(truth[indices[a]], ground_point)
                    landed_a = project(H[a], in_a)[0]
                    landed_b = project(H[b], centre[None])[0]
                    assert np.linalg.norm(landed_a - landed_b) < 2.0
    assert len(errors[True]) >= 20
    # Measured in the reference keyframe's pixels the refinement shrank the far keyframes:
    # a median of 1.0 px and a worst pair of 5.8 px here.
    assert np.median(errors[True]) < 0.6 and errors[True].max() < 3.0
    assert np.median(errors[True]) <= np.median(errors[False])
    extent = np.array(canvases[True], float) / np.array(canvases[False], float)
    assert np.all(np.abs(extent - 1) < 0.03)
