"""Simulated drone flights with exact ground truth: a virtual nadir camera over a large
aerial image (or a procedural one), rendered anti-aliased and encoded as H.264.

    from mosaic_cli.simulate import load_map, plan_flight, write_flight, load_ground_truth
    map_rgb = load_map(None)                      # procedural 4096x4096 map
    plan = plan_flight(map_rgb.shape[1::-1], "paper", frames=300)
    gt = write_flight("flight.mp4", map_rgb, plan)  # + flight.gt.json
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.simulate.groundtruth import GroundTruth, ground_truth_path, load_ground_truth
from mosaic_cli.simulate.maps import load_map, procedural_map
from mosaic_cli.simulate.render import MapPyramid, render_frames, render_view
from mosaic_cli.simulate.trajectory import PROFILES, FlightPlan, Profile, centre_motion, plan_flight

__all__ = [
    "procedural_map",
    "load_map",
    "plan_flight",
    "render_frames",
    "render_view",
    "write_flight",
    "load_ground_truth",
    "ground_truth_path",
    "GroundTruth",
    "FlightPlan",
    "Profile",
    "PROFILES",
    "MapPyramid",
    "centre_motion",
    "simulate_flight",
]


def write_flight(
    out_path: str | Path,
    map_rgb: np.ndarray,
    plan: FlightPlan,
    fps: float | None = None,
    crf: int | None = None,
    map_name: str = "procedural",
    preset: str = "medium",
    show_progress: bool = True,
) -> GroundTruth:
    """Render ``plan`` over ``map_rgb`` into an H.264 video at ``out_path`` and write its
    ground truth to ``<stem>.gt.json`` beside it; both appear atomically (the JSON last)."""
    from mosaic_cli.atomic import check_writable
    from mosaic_cli.progress import progress_task
    from mosaic_cli.video import VideoWriter

    if plan.size[0] % 2 or plan.size[1] % 2:
        # H.264 in 4:2:0 needs even sides; a padded video would not match its ground truth.
        raise BadInput(f"--size must have even sides for an H.264 flight, got {plan.size[0]}x{plan.size[1]}")
    out = check_writable(out_path)
    gt_path = check_writable(ground_truth_path(out))
    rate = float(plan.fps if fps is None else fps)
    gt = GroundTruth.from_plan(plan, fps=rate, map_name=map_name)
    if crf is None:  # the profile's own quality: degraded flights are low-bitrate too
        crf = PROFILES[plan.profile].crf if plan.profile in PROFILES else 18
    with VideoWriter(out, plan.size, rate, crf=crf, preset=preset) as writer:
        with progress_task(f"simulate ({plan.profile})", plan.frames, disable=not show_progress) as advance:
            for frame in render_frames(map_rgb, plan):
                writer.write(frame)
                advance(1)
    gt.save(gt_path)
    return gt


def simulate_flight(
    out_path: str | Path,
    map_path: str | Path | None = None,
    profile: str = "paper",
    frames: int = 300,
    size: tuple[int, int] = (1280, 720),
    fps: float = 30.0,
    seed: int = 0,
    crf: int | None = None,
    preset: str = "medium",
    show_progress: bool = True,
) -> GroundTruth:
    """Everything ``mosaic simulate`` does: load (or make) the map, plan, render, encode."""
    map_rgb = load_map(map_path, seed=seed)
    plan = plan_flight((map_rgb.shape[1], map_rgb.shape[0]), profile, frames, size, seed, fps)
    name = "procedural" if map_path is None else Path(map_path).name
    return write_flight(out_path, map_rgb, plan, fps=fps, crf=crf, map_name=name, preset=preset, show_progress=show_progress)
