"""``mosaic track VIDEO -o OUT.json``: the pairwise homographies themselves."""

from __future__ import annotations

from pathlib import Path

import typer

from mosaic_cli.atomic import check_writable
from mosaic_cli.cli import app
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import DEFAULT_ESTIMATOR, make_estimator
from mosaic_cli.live.source import DEFAULT_TIMEOUT, is_live_source
from mosaic_cli.live.track import is_jsonl, track_stream
from mosaic_cli.overlay import MaskOptions, frame_mask, load_mask
from mosaic_cli.progress import console
from mosaic_cli.track import save_track, track_video
from mosaic_cli.video import probe
from mosaic_cli.video.reader import reading_policy


@app.command()
def track(
    video: str = typer.Argument(..., help="Video file (mp4, mov, mkv, avi, ...), folder of numbered images, - (standard input) or a stream URL (udp://, tcp://, rtp://, rtsp://, srt://, http(s)://)."),
    out: str = typer.Option(..., "-o", "--out", help="Output .json (documented format), .npy (pairwise array), or .jsonl / - (standard output): JSON Lines, one pair a line as it is estimated."),
    estimator: str | None = typer.Option(None, "--estimator", "-e", help=f"orb, orb-ransac, orb-paper, identity, lstm or cnn (options may follow: cnn:patches=5). Default: {DEFAULT_ESTIMATOR} (with --weights: the network they hold)."),
    work_width: int = typer.Option(320, "--work-width", help="Width the classical estimators (orb, orb-ransac, identity) work at, pixels; the learned ones work at the size their weights were trained for."),
    weights: Path | None = typer.Option(None, "--weights", help="A trained checkpoint (.safetensors) to run."),
    device: str = typer.Option("auto", "--device", help="auto, cpu or cuda (learned estimators)."),
    patches: int | None = typer.Option(None, "--patches", help="Learned: patches per frame pair, 1 (centre, the paper), 5 or 9, with a robust consensus."),
    reset_every: int | None = typer.Option(None, "--reset-every", help="LSTM: restart its state every K frame pairs (default: carried through the video)."),
    refine: str | None = typer.Option(None, "--refine", help="Polish of each estimate: lk (default), ecc or none (learned and orb)."),
    chunk: int | None = typer.Option(None, "--chunk", help="Learned: frame pairs per network batch (default 16; larger on a GPU)."),
    threads: int | None = typer.Option(None, "--threads", help="Learned, on the CPU: threads for the network (default: torch's, one per core; 1 is cheaper on a busy machine)."),
    mask: Path | None = typer.Option(None, "--mask", help="Image (the video's size or aspect): white = use, black = ignore, e.g. burned-in overlays the detector misses."),
    overlay_detect: bool = typer.Option(True, "--overlay-detect/--no-overlay-detect", help="Find burned-in logos, text and letterbox bars (fixed in the frame while the ground moves) and keep them out of estimation."),
    max_frames: int | None = typer.Option(None, "--max-frames", help="Stop after this many frames."),
    strict: bool = typer.Option(False, "--strict", help="A video that decodes to fewer frames than its container announces (truncated, damaged) is an error, not a warning."),
    timeout: float = typer.Option(DEFAULT_TIMEOUT, "--timeout", help="Live input: end the run when the stream sends nothing for this many seconds."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """Estimate the homography between every pair of consecutive frames.

    pairwise[t] maps pixel (x, y) of frame t (OpenCV pixel centres, full resolution) to frame t+1.
    """
    if max_frames is not None and max_frames < 2:
        raise BadInput("--max-frames must be at least 2")
    if threads is not None and threads < 1:
        raise BadInput(f"--threads must be at least 1, got {threads}")
    if timeout <= 0:
        raise BadInput(f"--timeout must be positive, got {timeout}")
    streaming = is_live_source(video) or is_jsonl(out)
    if not is_jsonl(out):
        check_writable(out)
        if Path(out).suffix.lower() not in (".json", ".npy"):
            raise BadInput(f"output {out} must end in .json or .npy (or .jsonl, or be -, for JSON Lines)")
    elif out != "-":
        check_writable(out)
    live = is_live_source(video)
    mask_options = MaskOptions(file=mask, detect=overlay_detect)
    info = None if live else probe(video)  # the input's one probe, passed down
    if mask is not None and info is not None:  # a bad --mask fails before the estimator loads its weights
        load_mask(mask, info.source_size)
    est = make_estimator(estimator, work_width=work_width, weights=str(weights) if weights else None, device=device,
                         patches=patches, reset_every=reset_every, refine=refine, chunk=chunk)
    if threads is not None:
        import torch

        torch.set_num_threads(threads)
    masked = None
    if not live:  # a live input's mask is made when its first frame gives the size (live_mask)
        masked = frame_mask(video, mask_options, info, show_progress=not quiet)
        est.set_mask(masked.use)
    if streaming:
        result = track_stream(video, est, out, timeout=timeout, max_frames=max_frames, show_progress=not quiet,
                              mask=mask_options if live else None, info=info)
        if masked is not None:
            result.meta["mask"] = masked.to_json()
        if not is_jsonl(out):
            save_track(result, out)
    else:
        with reading_policy(strict):
            result = track_video(video, est, max_frames=max_frames, show_progress=not quiet, info=info)
        result.meta["mask"] = masked.to_json()
        save_track(result, out)
    if not quiet:
        if masked is not None and masked.use is not None:
            console.print(masked.describe())
        elif masked is None and result.meta["mask"]["excluded"] > 0:
            console.print(f"{100 * result.meta['mask']['excluded']:.1f}% of the frame masked (--mask)")
        console.print(
            f"{result.frames} frames, {result.meta['ms_per_frame']:.1f} ms/frame, "
            f"median confidence {float(_median(result.confidence)):.2f} -> {'standard output' if out == '-' else out}"
        )


def _median(values) -> float:
    import numpy as np

    return float(np.median(values)) if len(values) else 0.0
