"""Simulated drone flights with exact ground truth: a virtual nadir camera over a large
aerial image (or a procedural one), rendered anti-aliased and encoded as H.264.

    from mosaic_cli.simulate import load_map, plan_flight, write_flight, load_ground_truth
    map_rgb = load_map(None)                      # procedural 4096x4096 map
    plan = plan_flight(map_rgb.shape[1::-1], "paper", frames=300)
    gt = write_flight("flight.mp4", map_rgb, plan)  # + flight.gt.json
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry.lens import Lens, check_lens_covers, fisheye_lens, radial_lens
from mosaic_cli.geometry.lens_files import read_lens
from mosaic_cli.simulate.bursts import BurstSpec, apply_bursts, frames_to_plan, plan_bursts
from mosaic_cli.simulate.groundtruth import GroundTruth, ground_truth_path, load_ground_truth
from mosaic_cli.simulate.maps import load_map, procedural_map
from mosaic_cli.simulate.overlay import OverlayBurner, OverlaySpec, overlay_mask_path, write_mask
from mosaic_cli.simulate.render import MapPyramid, render_frames, render_view
from mosaic_cli.simulate.trajectory import (
    PROFILES,
    FlightPlan,
    NoiseVibration,
    Profile,
    RollingShutter,
    add_rolling_shutter,
    centre_motion,
    plan_flight,
)
from mosaic_cli.video.writer import check_encoder

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
    "RollingShutter",
    "NoiseVibration",
    "parse_vibration",
    "parse_lens",
    "Profile",
    "PROFILES",
    "MapPyramid",
    "centre_motion",
    "simulate_flight",
    "SimulateOptions",
    "check_outputs",
    "plan_simulated_flight",
    "BurstSpec",
    "OverlaySpec",
    "overlay_mask_path",
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
    overlays: OverlaySpec | None = None,
    lens: Lens | None = None,
) -> GroundTruth:
    """Render ``plan`` over ``map_rgb`` into an H.264 video at ``out_path`` and write its
    ground truth to ``<stem>.gt.json`` beside it; both appear atomically (the JSON last).
    ``overlays`` burns a logo, a timestamp or letterbox bars into every frame; the exact
    pixels drawn go to ``<stem>.mask.png`` (a ``--mask`` image: white where none was drawn).
    ``lens``: each frame seen through it (the truth's homographies stay the pinhole frames'; it
    records the lens)."""
    from mosaic_cli.atomic import check_writable
    from mosaic_cli.progress import progress_task
    from mosaic_cli.video import VideoWriter

    if plan.size[0] % 2 or plan.size[1] % 2:
        # H.264 in 4:2:0 needs even sides; a padded video would not match its ground truth.
        raise BadInput(f"--size must have even sides for an H.264 flight, got {plan.size[0]}x{plan.size[1]}")
    out = check_writable(out_path)
    gt_path = check_writable(ground_truth_path(out))
    rate = float(plan.fps if fps is None else fps)
    gt = GroundTruth.from_plan(plan, fps=rate, map_name=map_name).with_lens(None if lens is None else lens.at(plan.size))
    if crf is None:  # the profile's own quality: degraded flights are low-bitrate too
        crf = PROFILES[plan.profile].crf if plan.profile in PROFILES else 18
    burner = OverlayBurner(overlays, plan.size, rate) if overlays is not None and overlays.any else None
    with VideoWriter(out, plan.size, rate, crf=crf, preset=preset) as writer:
        with progress_task(f"simulate ({plan.profile})", plan.frames, disable=not show_progress) as advance:
            for t, frame in enumerate(render_frames(map_rgb, plan, lens)):
                writer.write(burner.draw(frame, t) if burner else frame)
                advance(1)
    if burner is not None:
        write_mask(overlay_mask_path(out), burner.use_mask())
    gt.save(gt_path)
    return gt


VIDEO_OUTPUTS = (".mp4", ".mov", ".mkv")


@dataclass
class SimulateOptions:
    """The flight ``mosaic simulate`` renders (and ``mosaic bench`` times the estimators on)."""

    profile: str = "paper"  # one of PROFILES
    frames: int = 300
    size: tuple[int, int] = (1280, 720)  # (w, h)
    fps: float = 30.0
    seed: int = 0  # path, map and effects
    crf: int | None = None  # None: the profile's own (degraded flights are low-bitrate too)
    preset: str = "medium"  # x264's
    overlays: OverlaySpec = field(default_factory=OverlaySpec)  # burned in, with their exact mask
    bursts: BurstSpec | None = None  # frames without a motion cue; None: the profile's own
    rolling: RollingShutter = field(default_factory=RollingShutter)  # readout and vibration; default: global shutter
    lens: Lens | None = None  # the frames seen through it (parse_lens); None: a pinhole

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if self.profile not in PROFILES:
            raise BadInput(f"--profile must be one of {', '.join(PROFILES)}, got {self.profile!r}")
        if self.frames < 2:
            raise BadInput(f"--frames must be at least 2, got {self.frames}")
        if not 0 < self.fps <= 1000:
            raise BadInput(f"--fps must be in (0, 1000], got {self.fps}")
        if self.seed < 0:
            raise BadInput(f"--seed must be 0 or more, got {self.seed}")
        check_encoder(self.crf, self.preset)
        if self.lens is not None:
            if self.rolling.readout > 0:
                raise BadInput("--lens and --rolling-shutter: one at a time (a lens's rows are not yet exposed at their own times)")
            try:
                check_lens_covers(self.lens.at(self.size))
            except ValueError as exc:
                raise BadInput(f"--lens: {exc}") from None


# The simulator's wide-angle lens: about 71 degrees across (900 px at 1280 wide, as issue 41's
# trial), and its fisheye: about 120 degrees across (equidistant: half the width at 60 degrees).
WIDE_FOCAL = 900.0 / 1280.0
FISHEYE_DEGREES = 120.0


def parse_lens(text: str | None, size: tuple[int, int]) -> Lens | None:
    """``--lens``: None or "none" (a pinhole); ``K1[,K2][,f=PX]`` (OpenCV's radial model, focal
    length PX at ``size``, default 71 degrees across); ``fisheye[:K1[,K2[,K3[,K4]]]][,f=PX]``
    (OpenCV's equidistant model, default 120 degrees across); or a lens FILE
    (:func:`~mosaic_cli.geometry.lens_files.read_lens`), rescaled to ``size``."""
    if text is None or text.strip().lower() in ("", "none"):
        return None
    text = text.strip()
    fisheye = text.lower().startswith("fisheye")
    body = text[len("fisheye"):].lstrip(":") if fisheye else text
    items = [v.strip() for v in body.split(",") if v.strip()]
    try:
        focal = [float(v[2:]) for v in items if v.lower().startswith("f=")]
        values = [float(v) for v in items if not v.lower().startswith("f=")]
    except ValueError:
        values, focal = None, []
    if values is None or (not fisheye and not values):
        if Path(text).is_file():
            try:
                return read_lens(text).at(size)
            except ValueError as exc:
                raise BadInput(f"--lens {text}: {exc}") from None
        raise BadInput(f"--lens must be K1[,K2][,f=PX], fisheye[:K1,...][,f=PX], a lens file or none, got {text!r}")
    if len(focal) > 1 or (focal and not (np.isfinite(focal[0]) and focal[0] > 0)) or not all(np.isfinite(values)):
        raise BadInput(f"--lens {text!r}: one positive focal length f=PX, finite coefficients")
    if fisheye:
        if len(values) > 4:
            raise BadInput(f"--lens {text!r}: a fisheye has at most 4 coefficients")
        f = focal[0] if focal else size[0] / 2 / np.radians(FISHEYE_DEGREES / 2)
        return fisheye_lens(size, f, tuple(values))
    if len(values) > 2:
        raise BadInput(f"--lens {text!r}: K1[,K2] (two radial coefficients at most)")
    return radial_lens(size, focal[0] if focal else WIDE_FOCAL * size[0], values[0], values[1] if len(values) > 1 else 0.0)


def parse_vibration(text: str | None) -> tuple:
    """``--vibration``: the :class:`RollingShutter` fields after the readout.

    ``HZ,PX`` (one tone, as always) -> (hz, px); None or "none" -> (0, 0).  Broadband vibration:
    items joined by ``+``, each a tone ``HZ,PX`` or band-limited noise ``noise:LO-HI,PX[,DEG]``
    (between LO and HI Hz, PX 1280-wide px RMS on both shifts, DEG degrees RMS of rotation,
    default 0), e.g. ``12,2+31,1`` or ``noise:5-40,2.5,0.25`` -> (hz, px, bands, tones, noise)
    with the first tone in (hz, px)."""
    from mosaic_cli.simulate.trajectory import ROW_BANDS, NoiseVibration

    if text is None or text.strip().lower() in ("", "none", "0"):
        return 0.0, 0.0
    usage = "--vibration must be HZ,PX (e.g. 12,3), tones joined by + (12,2+31,1) or noise:LO-HI,PX[,DEG] (noise:5-40,2.5,0.25)"
    tones: list[tuple[float, float]] = []
    noise = None
    for item in text.strip().lower().split("+"):
        item = item.strip()
        try:
            if item.startswith("noise:"):
                band, *rest = item[len("noise:"):].split(",")
                low, high = (float(v) for v in band.split("-"))
                if noise is not None or len(rest) not in (1, 2):
                    raise ValueError
                values = [float(v) for v in rest]
                if not all(np.isfinite(values)):
                    raise ValueError
                noise = NoiseVibration(low, high, *values)
            else:
                hz, px = (float(v) for v in item.split(","))
                if not (np.isfinite(hz) and np.isfinite(px)):
                    raise ValueError
                tones.append((hz, px))
        except ValueError:
            raise BadInput(f"{usage}, got {text!r}") from None
    if noise is None and len(tones) == 1:
        return tones[0]
    first = tones[0] if tones else (0.0, 0.0)
    return first[0], first[1], ROW_BANDS, tuple(tones[1:]), noise


def check_outputs(out_path: str | Path, map_path: str | Path | None, options: SimulateOptions) -> None:
    """The map exists; the video, its ground truth (and overlay mask) can be written, in an
    output folder made if missing (a flight is often written to a data folder of its own)."""
    from mosaic_cli.atomic import check_writable

    out = Path(out_path)
    if out.suffix.lower() not in VIDEO_OUTPUTS:
        raise BadInput(f"output {out} must end in .mp4, .mov or .mkv")
    if map_path is not None and not Path(map_path).exists():
        raise BadInput(f"{map_path}: no such file")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise BadInput(f"output folder {out.parent} is a file") from None
    except OSError as exc:
        raise BadInput(f"cannot make the output folder {out.parent} ({(exc.strerror or str(exc)).lower()})") from None
    check_writable(out)
    check_writable(ground_truth_path(out))
    if options.overlays.any:
        check_writable(overlay_mask_path(out))


def simulate_flight(out_path: str | Path, map_path: str | Path | None = None, options: SimulateOptions | None = None,
                    show_progress: bool = True) -> GroundTruth:
    """Everything ``mosaic simulate`` does: load (or make) the map, plan, render, encode."""
    o = options or SimulateOptions()
    map_rgb = load_map(map_path, seed=o.seed)
    plan = plan_simulated_flight((map_rgb.shape[1], map_rgb.shape[0]), o)
    name = "procedural" if map_path is None else Path(map_path).name
    return write_flight(out_path, map_rgb, plan, fps=o.fps, crf=o.crf, map_name=name, preset=o.preset, show_progress=show_progress,
                        overlays=o.overlays, lens=o.lens)


def plan_simulated_flight(map_size: tuple[int, int], options: SimulateOptions) -> FlightPlan:
    """The flight of ``options`` over a map of ``map_size``: :func:`plan_flight`, then its bursts
    (the profile's, or ``options.bursts``), drawn from the seed alone."""
    o = options
    spec = o.bursts if o.bursts is not None else BurstSpec(PROFILES[o.profile].bursts)
    plan = plan_flight(map_size, o.profile, frames_to_plan(o.frames, spec), o.size, o.seed, o.fps)
    plan = add_rolling_shutter(plan, o.rolling)  # the flown frames, before bursts drop or repeat some
    if not spec.any:
        return plan
    bursts = plan_bursts(o.frames, spec, o.seed)
    plan = apply_bursts(plan, bursts, o.frames, o.seed)
    plan.bursts = bursts
    return plan
