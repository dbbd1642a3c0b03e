"""``mosaic bench``: latency per stage, throughput and accuracy of the estimators."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mosaic_cli.commands.options import (
    ESTIMATOR,
    INPUT_OUTPUT,
    SIMULATED_FLIGHT,
    Device,
    Strict,
    Threads,
    check_json_report,
    quiet_option,
    use_threads,
)
from mosaic_cli.inputs import parse_size
from mosaic_cli.progress import console
from mosaic_cli.video.reader import reading_policy

Quiet = quiet_option("No progress and no table (use with --json).")


def bench(
    video: Annotated[Path | None, typer.Option("--video", help="Benchmark on this video (latency only, unless a <stem>.gt.json sits beside it).", rich_help_panel=INPUT_OUTPUT)] = None,
    flights: Annotated[Path | None, typer.Option("--flights", help="Score on every X.mp4 with an X.gt.json in this folder (MACE over all flights and per profile).", rich_help_panel=INPUT_OUTPUT)] = None,
    map_image: Annotated[Path | None, typer.Option("--map", help="Simulate the flight over this aerial image (default: procedural map).", rich_help_panel=INPUT_OUTPUT)] = None,
    estimators: Annotated[str | None, typer.Option("--estimators", "-e", help="Comma-separated: lstm,cnn,orb,orb-ransac,orb-paper,identity, each with options as NAME:OPTION=VALUE (cnn:refine=none, cnn:patches=5, lstm:reset-every=300, cnn:precision=fp32, lstm:weights=FILE; default: lstm,cnn,orb,orb-paper,identity; learned ones without weights are skipped).", rich_help_panel=ESTIMATOR)] = None,
    weights: Annotated[Path | None, typer.Option("--weights", help="A trained checkpoint (.safetensors) for the learned estimators (lstm, cnn).", rich_help_panel=ESTIMATOR)] = None,
    profile: Annotated[str, typer.Option("--profile", "-p", help="Flight profile of the simulated clip.", rich_help_panel=SIMULATED_FLIGHT)] = "paper",
    frames: Annotated[int, typer.Option("--frames", "-n", help="Frames to simulate (or to read from --video).", rich_help_panel=SIMULATED_FLIGHT)] = 300,
    size: Annotated[str, typer.Option("--size", help="Frame size of the simulated clip, WxH.", rich_help_panel=SIMULATED_FLIGHT)] = "1280x720",
    work_width: Annotated[int, typer.Option("--work-width", help="Width the classical estimators work at.", rich_help_panel=ESTIMATOR)] = 320,
    device: Device = "auto",
    seed: Annotated[int, typer.Option("--seed", help="Seed of the simulated flight.", rich_help_panel=SIMULATED_FLIGHT)] = 0,
    threads: Threads = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the full report as JSON.", rich_help_panel=INPUT_OUTPUT)] = None,
    strict: Strict = False,
    quiet: Quiet = False,
) -> None:
    """Time and score the estimators on a simulated flight, a video or a folder of flights.

    Per estimator: decode / preprocess / estimate latency (p50, p95 ms per frame), frames per
    second and accuracy (MACE, corner error, failure rate, 1280x720-equivalent px); GPU batch
    throughput when a GPU is present.  With --video: latency only (scored too when the video
    has a <stem>.gt.json beside it).  With --flights DIR: MACE pooled over all the flights'
    landmark pairs (the paper's protocol) and per flight profile, median corner error, failure
    rate and ms per frame (p50), every flight decoded once for all the estimators."""
    from rich.console import Console

    from mosaic_cli.atomic import write_json
    from mosaic_cli.bench import BenchOptions, render_flights_table, render_table, simulated_flight
    from mosaic_cli.bench import bench as run

    flight = simulated_flight(profile=profile, frames=frames, size=parse_size(size, "--size"), seed=seed)
    options = BenchOptions(estimators=estimators.split(",") if estimators is not None else None, video=video, flights=flights,
                           map_image=map_image, flight=flight, weights=str(weights) if weights is not None else None,
                           work_width=work_width, device=device, threads=threads)
    check_json_report(json_out)
    use_threads(options.threads)
    with reading_policy(strict):
        report = run(options, show_progress=not quiet)
    if json_out is not None:
        write_json(json_out, report)
    if quiet:
        return
    out = Console()
    if not out.is_terminal:
        out = Console(width=max(out.width, 132))  # logs and pipes: keep the table on one line per row
    out.print(render_flights_table(report) if flights is not None else render_table(report))
    for note in report["notes"]:
        console.print(f"[yellow]note:[/yellow] {note}")
    if flights is not None:
        console.print("[dim]pixels are 1280x720-equivalent; ms/frame = preprocess + estimate (decoding excluded: shared by all)[/dim]")
    else:
        console.print("[dim]pixels are 1280x720-equivalent; ms/frame = decode + preprocess + estimate[/dim]")
