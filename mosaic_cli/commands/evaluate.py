"""``mosaic eval PRED --gt flight.gt.json`` / ``--annotations ann.txt``: score pairwise homographies."""

from __future__ import annotations

from pathlib import Path

import typer

from mosaic_cli.cli import app
from mosaic_cli.errors import BadInput
from mosaic_cli.progress import console


@app.command("eval")
def evaluate_command(
    prediction: Path = typer.Argument(..., help="Pairwise homographies: a `mosaic track` .json or an (N-1, 3, 3) .npy."),
    gt: Path | None = typer.Option(None, "--gt", help="Ground truth of a simulated flight (<stem>.gt.json)."),
    annotations: Path | None = typer.Option(None, "--annotations", "-a", help="Landmarks, one 'f1 x1 y1 f2 x2 y2' per line."),
    size: str | None = typer.Option(None, "--size", help="Frame size WxH of the video (for .npy predictions scored on annotations)."),
    every: int = typer.Option(30, "--every", help="Frames between landmark pairs made from the ground truth."),
    json_out: Path | None = typer.Option(None, "--json", help="Also write the metrics to this JSON file."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Print nothing (use with --json)."),
) -> None:
    """Score pairwise homographies against ground truth or landmark annotations.

    MACE by the paper's protocol (landmarks every 30 frames, chained estimates), corner error
    and failure rate (corner error > 10 px), all in 1280x720-equivalent pixels.  A track of
    another frame count or frame size than the ground truth is refused."""
    from rich.table import Table

    from mosaic_cli.atomic import check_writable, write_json
    from mosaic_cli.evaluate import check_same_video, evaluate, landmarks_from_ground_truth, load_prediction, mace_pairs, read_annotations
    from mosaic_cli.inputs import parse_size
    from mosaic_cli.simulate import load_ground_truth

    if gt is None and annotations is None:
        raise BadInput("give --gt GROUND_TRUTH.json and/or --annotations ANNOTATIONS.txt")
    if json_out is not None:
        check_writable(json_out)
        if json_out.suffix.lower() != ".json":
            raise BadInput(f"--json {json_out} must end in .json")
    pred, pred_size = load_prediction(prediction)
    ann = read_annotations(annotations) if annotations is not None else None
    if gt is not None:
        truth = load_ground_truth(gt)
        check_same_video(pred, pred_size, truth)
        if ann is None and every != 30:
            ann = landmarks_from_ground_truth(truth, every=every)
            ann = ann[ann[:, 3] <= len(pred)]
        metrics = evaluate(pred, truth, ann)
    else:
        wh = parse_size(size, "--size") if size is not None else pred_size
        if wh is None:
            raise BadInput("a .npy prediction scored on annotations needs --size WxH (the video's frame size)")
        _, errors = mace_pairs(pred, ann, wh)
        metrics = {"mace": float(errors.mean()), "landmark_pairs": int(len(errors)), "landmarks": int(len(ann)),
                   "pairs": int(len(pred)), "frames": int(len(pred) + 1), "units": "1280x720-equivalent px"}
    metrics["prediction"] = str(prediction)
    if json_out is not None:
        write_json(json_out, metrics)
    if not quiet:
        table = Table(title=f"{prediction.name}", title_justify="left")
        table.add_column("metric")
        table.add_column("value", justify="right")
        rows = [
            ("MACE (px)", "mace", "{:.2f}"),
            ("corner error, median (px)", "corner_error", "{:.2f}"),
            ("corner error, mean (px)", "corner_error_mean", "{:.2f}"),
            ("failure rate (> 10 px)", "failure_rate", "{:.1%}"),
            ("pairs scored", "pairs", "{}"),
            ("landmark pairs", "landmark_pairs", "{}"),
        ]
        for label, key, fmt in rows:
            if key in metrics and metrics[key] is not None:
                table.add_row(label, fmt.format(metrics[key]))
        from rich.console import Console

        Console().print(table)
        console.print("[dim]pixels are 1280x720-equivalent[/dim]")
