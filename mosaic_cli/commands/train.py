"""``mosaic train CLIPS_DIR --out RUN_DIR``: learn the homography network from raw clips
(``--calibrate WEIGHTS``: add int8 ranges to existing weights instead, :mod:`mosaic_cli.train.calibrate`).

The procedure is :func:`mosaic_cli.train.loop.train`; this module only turns options into a
:class:`~mosaic_cli.train.config.TrainConfig`.  Options left out take the paper's value for the
variant (or, with ``--resume``, the run's saved value).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mosaic_cli.commands.options import (
    CHECKPOINTS,
    INPUT_OUTPUT,
    MACHINE,
    MODEL,
    TRAINING,
    VALIDATION,
    quiet_option,
)
from mosaic_cli.progress import console

Quiet = quiet_option("No progress bar.")


def train(
    clips: Annotated[Path | None, typer.Argument(help="Folder of training clips (video files and/or folders of frames), or one clip.")] = None,
    out: Annotated[Path | None, typer.Option("-o", "--out", help="Run folder: checkpoints, state, log.csv, weights.safetensors, frame cache (default: runs/VARIANT).", rich_help_panel=INPUT_OUTPUT)] = None,
    variant: Annotated[str | None, typer.Option("--variant", help="base, reg-p, reg-s, reg-t, reg-all, lstm, lstm-reg-t or lstm-reg-all (default: base).", rich_help_panel=MODEL)] = None,
    preset: Annotated[str | None, typer.Option("--preset", help="Network size: compact (CPU) or paper (Table 1) (default: compact).", rich_help_panel=MODEL)] = None,
    init: Annotated[Path | None, typer.Option("--init", help="Checkpoint to fine-tune from (e.g. a BASE run's weights.safetensors).", rich_help_panel=MODEL)] = None,
    freeze: Annotated[bool | None, typer.Option("--freeze/--no-freeze", help="LSTM from a CNN --init: keep backbone + first Linear fixed (default: freeze).", rich_help_panel=MODEL)] = None,
    steps: Annotated[int | None, typer.Option("--steps", help="Training steps (paper: 300k BASE, 90k fine-tunes); more on --resume extends.", rich_help_panel=TRAINING)] = None,
    batch_size: Annotated[int | None, typer.Option("--batch-size", help="Windows per step per process (paper: 64 BASE, 32 REG-*, 8 LSTM).", rich_help_panel=TRAINING)] = None,
    lr: Annotated[float | None, typer.Option("--lr", help="Initial learning rate of the trained parameters; x0.1 at 1/3 and 2/3 of --steps (default: 1e-3).", rich_help_panel=TRAINING)] = None,
    device: Annotated[str | None, typer.Option("--device", help="auto, cpu or cuda (default: auto).", rich_help_panel=MACHINE)] = None,
    amp: Annotated[bool | None, typer.Option("--amp/--no-amp", help="Mixed precision on CUDA (default: amp).", rich_help_panel=TRAINING)] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Random seed: initial weights, samples, dropout (default: 0).", rich_help_panel=TRAINING)] = None,
    val: Annotated[Path | None, typer.Option("--val", help="Folder of simulated flights (X.mp4 + X.gt.json) to report MACE on.", rich_help_panel=VALIDATION)] = None,
    val_every: Annotated[int | None, typer.Option("--val-every", help="Validate every N steps (default: 1000).", rich_help_panel=VALIDATION)] = None,
    checkpoint_every: Annotated[int | None, typer.Option("--checkpoint-every", help="Checkpoint every N steps (default: 500).", rich_help_panel=CHECKPOINTS)] = None,
    checkpoint_minutes: Annotated[float | None, typer.Option("--checkpoint-minutes", help="...and whenever this many minutes have passed (default: 15).", rich_help_panel=CHECKPOINTS)] = None,
    work_size: Annotated[str | None, typer.Option("--work-size", help="Working frame size WxH (default: 320x180).", rich_help_panel=MODEL)] = None,
    patch: Annotated[int | None, typer.Option("--patch", help="Patch side in working pixels (default: 128).", rich_help_panel=MODEL)] = None,
    lstm_start: Annotated[str | None, typer.Option("--lstm-start", help="An LSTM variant from a CNN --init: random (the paper: a new head) or cnn (the head starts as the CNN's, the LSTM passing its input through) (default: random).", rich_help_panel=MODEL)] = None,
    photometric: Annotated[str | None, typer.Option("--photometric", help="What the photometric loss compares: gray (the paper) or band (band-passed frames at unit contrast: blind to exposure, haze, vignetting) (default: gray).", rich_help_panel=TRAINING)] = None,
    flip: Annotated[bool | None, typer.Option("--flip/--no-flip", help="Mirror each window left-right and/or upside down, each half of the time (default: no-flip).", rich_help_panel=TRAINING)] = None,
    bursts: Annotated[float | None, typer.Option("--bursts", help="Share of the training windows (0-1) in which 1-3 frames are spoilt (glare, a gust's blur, near-black, featureless) for the network while the loss compares the clean frames: the LSTM learns to carry the motion through (default: 0).", rich_help_panel=TRAINING)] = None,
    max_minutes: Annotated[float | None, typer.Option("--max-minutes", help="Stop after this many minutes of steps (a checkpoint and the final weights are written, as at the last step); resume with a larger budget later.", rich_help_panel=TRAINING)] = None,
    data: Annotated[str | None, typer.Option("--data", help="stream: windows built by loader processes (--num-workers); device: the decoded clips held on the training device and every batch cut there (for GPUs; also works on a CPU with the memory for them). Default: stream.", rich_help_panel=MACHINE)] = None,
    num_workers: Annotated[int | None, typer.Option("--num-workers", help="Loader / decoder worker processes (default: 1).", rich_help_panel=MACHINE)] = None,
    threads: Annotated[int | None, typer.Option("--threads", help="Torch CPU threads per process (default: all cores; 1 under torchrun).", rich_help_panel=MACHINE)] = None,
    cache_gb: Annotated[float | None, typer.Option("--cache-gb", help="Disk budget of the decoded-frame cache in RUN_DIR/cache (default: 8).", rich_help_panel=MACHINE)] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue the run in --out from its last checkpoint.", rich_help_panel=CHECKPOINTS)] = False,
    calibrate: Annotated[Path | None, typer.Option("--calibrate", help="Instead of training: add int8 activation ranges, measured on CLIPS, to these existing weights (a checkpoint's, or weights trained before train wrote them); the weights are unchanged.", rich_help_panel=CHECKPOINTS)] = None,
    head_only: Annotated[bool, typer.Option("--head-only", help="With --calibrate: only measure the int8 LSTM's error on this machine and store it with the ranges the weights have (no CLIPS).", rich_help_panel=CHECKPOINTS)] = False,
    quiet: Quiet = False,
) -> None:
    """Train the homography network unsupervised on raw clips (photometric loss + the paper's priors).

    Ctrl-C (or SIGTERM) writes a checkpoint and stops; --resume continues at the same step.
    Under torchrun --nproc_per_node=N it trains as DistributedDataParallel.
    --calibrate WEIGHTS adds int8 ranges to existing weights instead of training.
    """
    from mosaic_cli.errors import BadInput

    if head_only and calibrate is None:
        raise BadInput("--head-only goes with --calibrate WEIGHTS")
    if calibrate is not None:
        from mosaic_cli.train.calibrate import calibrate_weights

        ranges = calibrate_weights(calibrate, clips, seed=seed or 0, head_only=head_only)
        if not quiet:
            error = ", ".join(f"{engine} {px:.3f} px" for engine, px in ranges.get("head_error", {}).items()) or "none (no LSTM)"
            what = "" if head_only else f"int8 ranges of {len(ranges['activations'])} activations from {ranges['pairs']} pairs of {clips}; "
            console.print(f"{calibrate}: {what}int8 LSTM error {error}")
        return
    if clips is None:
        raise BadInput("give CLIPS: the folder of training clips (or one clip)")
    from mosaic_cli.inputs import parse_size
    from mosaic_cli.train.loop import plan_run
    from mosaic_cli.train.loop import train as run_training

    options = {
        "variant": variant.lower() if variant else None,
        "preset": preset.lower() if preset else None,
        "init": str(init) if init else None,
        "freeze": freeze,
        "steps": steps,
        "batch_size": batch_size,
        "lr": lr,
        "device": device.lower() if device else None,
        "amp": amp,
        "seed": seed,
        "val": str(val) if val else None,
        "val_every": val_every,
        "checkpoint_every": checkpoint_every,
        "checkpoint_minutes": checkpoint_minutes,
        "work_size": parse_size(work_size, "--work-size") if work_size else None,
        "patch": patch,
        "lstm_start": lstm_start.lower() if lstm_start else None,
        "photometric": photometric.lower() if photometric else None,
        "flip": flip,
        "bursts": bursts,
        "data": data.lower() if data else None,
        "max_minutes": max_minutes,
        "num_workers": num_workers,
        "threads": threads,
        "cache_gb": cache_gb,
    }
    if out is None:
        out = Path("runs") / (options["variant"] or "base")
    config = plan_run(str(clips), str(out), options, resume)
    summary = run_training(config, resume=resume, show_progress=not quiet)
    if summary.weights is not None and not quiet:
        total = summary.last_terms.get("total", float("nan"))
        val_text = f", validation MACE {summary.val_mace:.2f} px" if summary.val_mace is not None else ""
        console.print(
            f"trained steps {summary.start_step + 1}-{summary.steps}: {summary.samples_per_s:.1f} samples/s, "
            f"last loss {total:.4g}{val_text} -> {summary.weights}"
        )
