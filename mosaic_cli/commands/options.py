"""The flags several commands share, declared once, and how a command turns them into library calls.

Each alias is a typer option with its name and help, used as a parameter's annotation
(``weights: Weights = None``); the default stays with the parameter.  The values are checked by
the options dataclasses the commands build (see docs/architecture.md), not here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mosaic_cli.estimators import DEFAULT_ESTIMATOR, DEFAULT_WORK_WIDTH, options_help

# -- the panels of the help (typer's rich_help_panel): each option under one, so that --help
# reads as groups (what goes in and out, the estimator, drift control ...), not one long box --

INPUT_OUTPUT = "Input and output"
ESTIMATOR = "Estimator"
OVERLAYS = "Overlays and mask"
DRIFT_CONTROL = "Drift control"
OUTPUT_QUALITY = "Output quality"
SMOOTHING = "Smoothing and crop"
LIVE = "Live input"
TELEMETRY = "Telemetry and maps"
PROGRESS_AND_RUN = "Progress and run"
SIMULATED_FLIGHT = "Simulated flight"
FLIGHT = "Flight"
SCORING = "Scoring"
MODEL = "Model"
TRAINING = "Training"
VALIDATION = "Validation"
CHECKPOINTS = "Checkpoints"
MACHINE = "Machine"

# -- the estimator (track, stitch, stabilize) -----------------------------------------------------

EstimatorName = Annotated[str | None, typer.Option(
    "--estimator", "-e",
    help=f"lstm, cnn, orb or orb-ransac (options may follow: cnn:patches=5). Default: {DEFAULT_ESTIMATOR} "
         f"(with --weights: the network they hold). {options_help()} The paper's baselines, orb-paper and identity, "
         "are for mosaic bench and eval.", rich_help_panel=ESTIMATOR)]
WorkWidth = Annotated[int | None, typer.Option(
    "--work-width",
    help=f"Width the classical estimators (orb, orb-ransac) work at, pixels (default {DEFAULT_WORK_WIDTH}; "
         "never wider than the video). The learned ones (lstm, cnn) work at the width their weights were trained at: "
         "another value is refused.", rich_help_panel=ESTIMATOR)]
Weights = Annotated[Path | None, typer.Option("--weights", help="A trained checkpoint (.safetensors) to run.", rich_help_panel=ESTIMATOR)]
Device = Annotated[str, typer.Option("--device", help="auto, cpu or cuda (learned estimators).", rich_help_panel=ESTIMATOR)]
Threads = Annotated[int | None, typer.Option(
    "--threads",
    help="Learned: threads that finish the frame pairs (polish, checks, fallback; default: one a core) and, on the CPU, "
         "run the network (default: 1; more can help on an idle machine with cores to spare). 1: one thread in all. "
         "The estimates are the same whatever the number.", rich_help_panel=ESTIMATOR)]

# -- the input ------------------------------------------------------------------------------------

Mask = Annotated[Path | None, typer.Option(
    "--mask", help="Image (the video's size or aspect): white = use, black = ignore, e.g. burned-in overlays the detector misses; "
                   "drawn on the frames as recorded (undistorted with them where a lens is applied).", rich_help_panel=OVERLAYS)]


def overlay_detect_option(kept_out_of: str):
    """``--overlay-detect/--no-overlay-detect``; ``kept_out_of`` says what the command keeps
    the overlays out of."""
    return Annotated[bool, typer.Option(
        "--overlay-detect/--no-overlay-detect",
        help=f"Find burned-in logos, text and letterbox bars (fixed in the frame while the ground moves) and keep them out of {kept_out_of}.", rich_help_panel=OVERLAYS)]


LensOption = Annotated[str | None, typer.Option(
    "--lens",
    help="The camera's lens, undistorted once as frames are decoded, so that every stage works on a pinhole view: none (default), "
         "auto (a radial lens estimated from the video's own frames, applied only where it clearly fits better; a video file only) "
         "or a FILE, also for a live input: mosaic's lens JSON, a Gyroflow lens profile or an OpenSfM/ODM cameras.json "
         "(docs/guide/stitch.md, Lenses).", rich_help_panel=INPUT_OUTPUT)]
MaxFrames = Annotated[int | None, typer.Option("--max-frames", help="Stop after this many frames.", rich_help_panel=INPUT_OUTPUT)]
Strict = Annotated[bool, typer.Option(
    "--strict",
    help="A video that decodes to fewer frames than its container announces (truncated, damaged) is an error, not a warning.", rich_help_panel=INPUT_OUTPUT)]
Timeout = Annotated[float, typer.Option(
    "--timeout", help="Live input: end the run when the stream sends nothing for this many seconds.", rich_help_panel=LIVE)]

def quiet_option(help: str):
    """``--quiet/-q``: what it silences differs from command to command."""
    return Annotated[bool, typer.Option("--quiet", "-q", help=help, rich_help_panel=PROGRESS_AND_RUN)]


# -- turning flags into library calls -------------------------------------------------------------


def mask_options(mask: Path | None, detect: bool):
    """``--mask`` and ``--overlay-detect/--no-overlay-detect`` as the pipelines take them."""
    from mosaic_cli.overlay import MaskOptions

    return MaskOptions(file=mask, detect=detect)


def use_threads(threads: int | None) -> None:
    """``--threads``: the learned estimator's threads, its per-pair pool's and torch's for the
    network (checked by the command's options; see :func:`mosaic_cli.device.ask_cpu_threads`)."""
    from mosaic_cli.device import ask_cpu_threads

    ask_cpu_threads(threads)


def check_json_report(path: Path | None) -> None:
    """``--json REPORT.json``: writable, and a .json file."""
    from mosaic_cli.atomic import check_writable
    from mosaic_cli.errors import BadInput

    if path is None:
        return
    check_writable(path)
    if path.suffix.lower() != ".json":
        raise BadInput(f"--json {path} must end in .json")
