"""``mosaic eval PRED --gt flight.gt.json`` / ``--annotations ann.txt``: score pairwise homographies."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mosaic_cli.commands.options import (
    INPUT_OUTPUT,
    SCORING,
    check_json_report,
    quiet_option,
)
from mosaic_cli.evaluate import LANDMARK_EVERY, EvalOptions, score
from mosaic_cli.inputs import parse_size
from mosaic_cli.progress import console

Quiet = quiet_option("Print nothing (use with --json).")

# The metrics in the table, in order: label, key, format.
ROWS = [
    ("MACE (px)", "mace", "{:.2f}"),
    ("corner error, median (px)", "corner_error", "{:.2f}"),
    ("corner error, mean (px)", "corner_error_mean", "{:.2f}"),
    ("failure rate (> 10 px)", "failure_rate", "{:.1%}"),
    ("pairs scored", "pairs", "{}"),
    ("landmark pairs", "landmark_pairs", "{}"),
]


def evaluate(
    prediction: Annotated[Path, typer.Argument(help="Pairwise homographies: a `mosaic track` .json or an (N-1, 3, 3) .npy.")],
    gt: Annotated[Path | None, typer.Option("--gt", help="Ground truth of a simulated flight (<stem>.gt.json).", rich_help_panel=INPUT_OUTPUT)] = None,
    annotations: Annotated[Path | None, typer.Option("--annotations", "-a", help="Landmarks, one 'f1 x1 y1 f2 x2 y2' per line.", rich_help_panel=INPUT_OUTPUT)] = None,
    size: Annotated[str | None, typer.Option("--size", help="Frame size WxH of the video (for .npy predictions scored on annotations).", rich_help_panel=SCORING)] = None,
    every: Annotated[int, typer.Option("--every", help="Frames between landmark pairs made from the ground truth.", rich_help_panel=SCORING)] = LANDMARK_EVERY,
    json_out: Annotated[Path | None, typer.Option("--json", help="Also write the metrics to this JSON file.", rich_help_panel=INPUT_OUTPUT)] = None,
    quiet: Quiet = False,
) -> None:
    """Score pairwise homographies against ground truth or landmark annotations.

    MACE by the paper's protocol (landmarks every 30 frames, chained estimates), corner error
    and failure rate (corner error > 10 px), all in 1280x720-equivalent pixels.  A track of
    another frame count or frame size than the ground truth is refused."""
    from rich.console import Console
    from rich.table import Table

    from mosaic_cli.atomic import write_json

    options = EvalOptions(gt=gt, annotations=annotations, size=parse_size(size, "--size") if size is not None else None, every=every)
    check_json_report(json_out)
    metrics = score(prediction, options)
    if json_out is not None:
        write_json(json_out, metrics)
    if quiet:
        return
    table = Table(title=f"{prediction.name}", title_justify="left")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for label, key, fmt in ROWS:
        if metrics.get(key) is not None:
            table.add_row(label, fmt.format(metrics[key]))
    Console().print(table)
    console.print("[dim]pixels are 1280x720-equivalent[/dim]")
