"""``mosaic bench``: latency per stage, throughput and accuracy of the estimators."""

from __future__ import annotations

from pathlib import Path

import typer

from mosaic_cli.cli import app
from mosaic_cli.errors import BadInput
from mosaic_cli.progress import console


@app.command()
def bench(
    video: Path | None = typer.Option(None, "--video", help="Benchmark on this video (latency only, unless a <stem>.gt.json sits beside it)."),
    map_image: Path | None = typer.Option(None, "--map", help="Simulate the flight over this aerial image (default: procedural map)."),
    estimators: str | None = typer.Option(None, "--estimators", "-e", help="Comma-separated: lstm,cnn,orb,orb-ransac,identity (default: lstm,cnn,orb,identity; learned ones without weights are skipped)."),
    profile: str = typer.Option("paper", "--profile", "-p", help="Flight profile of the simulated clip."),
    frames: int = typer.Option(300, "--frames", "-n", help="Frames to simulate (or to read from --video)."),
    size: str = typer.Option("1280x720", "--size", help="Frame size of the simulated clip, WxH."),
    work_width: int = typer.Option(320, "--work-width", help="Width the classical estimators work at."),
    device: str = typer.Option("auto", "--device", help="auto, cpu or cuda (learned estimators)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulated flight."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the full report as JSON."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress and no table (use with --json)."),
) -> None:
    """Time and score the estimators on a simulated flight (or a video).

    Per estimator: decode / preprocess / estimate latency (p50, p95 ms per frame), frames per
    second and accuracy (MACE, corner error, failure rate, 1280x720-equivalent px); GPU batch
    throughput when a GPU is present.  With --video: latency only (scored too when the video
    has a <stem>.gt.json beside it)."""
    from rich.console import Console

    from mosaic_cli.atomic import check_writable, write_json
    from mosaic_cli.bench import render_table, run_bench
    from mosaic_cli.commands.simulate import parse_size
    from mosaic_cli.simulate import PROFILES

    if profile not in PROFILES:
        raise BadInput(f"unknown profile {profile!r}: choose one of {', '.join(PROFILES)}")
    if json_out is not None:
        check_writable(json_out)
    if video is not None and not video.exists():
        raise BadInput(f"{video}: no such file or folder")
    if map_image is not None and not map_image.exists():
        raise BadInput(f"{map_image}: no such file")
    names = estimators.split(",") if estimators is not None else None
    report = run_bench(video, map_image, names, profile, frames, parse_size(size), work_width, device, seed, show_progress=not quiet)
    if json_out is not None:
        write_json(json_out, report)
    if not quiet:
        out = Console()
        if not out.is_terminal:
            out = Console(width=max(out.width, 132))  # logs and pipes: keep the table on one line per row
        out.print(render_table(report))
        for note in report["notes"]:
            console.print(f"[yellow]note:[/yellow] {note}")
        console.print("[dim]pixels are 1280x720-equivalent; ms/frame = decode + preprocess + estimate[/dim]")
