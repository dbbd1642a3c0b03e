#!/usr/bin/env python3
"""The sequence model's memory probe (issue 38), over every flight with bursts in a folder.

    python scripts/memory_probe.py FOLDER [--weights W] [--json OUT]

The network alone (the centre patch, as the estimator reads it; no polish, no fallback, no
checks), three ways: the state carried through each whole flight; restarted just before each
burst's first pair; restarted as often at ordinary places, half way between bursts.  A state
that carries the motion makes the burst pairs clearly worse when it is restarted before them,
and changes little on ordinary pairs (evaluate.memory_probe).  Failure: corner error over 10 px
(1280x720-equivalent).
"""

from __future__ import annotations

import argparse
import json

from mosaic_cli.evaluate import memory_probe
from mosaic_cli.inputs import find_flights
from mosaic_cli.simulate import load_ground_truth


def gate_statistics(weights: str | None) -> dict:
    """What the sequence head's parameters say about its memory: for the carry head, its cell's
    forget and input gates (torch's order i, f, g, o), the mean |w| of its recurrent weights and
    the blend gate's bias; for the paper's LSTM head, the same of its LSTM."""
    import torch

    from mosaic_cli.estimators.weights import default_weights
    from mosaic_cli.model import load_weights

    net, _ = load_weights(weights or default_weights("lstm"))
    cell = net.carry.cell if net.carry is not None else net.lstm
    h = cell.hidden_size
    suffix = "" if net.carry is not None else "_l0"
    bias = (getattr(cell, f"bias_ih{suffix}") + getattr(cell, f"bias_hh{suffix}")).detach()
    out = {
        "head": net.config.head,
        "forget_gate_bias_mean": float(bias[h:2 * h].mean()),
        "forget_gate_sigmoid_of_bias_median": float(torch.sigmoid(bias[h:2 * h]).median()),
        "input_gate_sigmoid_of_bias_median": float(torch.sigmoid(bias[:h]).median()),
        "recurrent_weight_mean_abs": float(getattr(cell, f"weight_hh{suffix}").detach().abs().mean()),
    }
    if net.carry is not None:
        out["blend_gate_bias"] = float(net.carry.gate[2].bias.detach())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("--weights", default=None, help="a sequence model's weights (default: the shipped lstm)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    print("gates:", gate_statistics(args.weights))
    total: dict[str, int] = {}
    for video in find_flights(args.folder, "FOLDER"):
        if not load_ground_truth(video).bursts:
            continue
        counts = memory_probe(video, args.weights).failures()
        print(video.stem, counts)
        for k, v in counts.items():
            total[k] = total.get(k, 0) + v
    b, o = total.get("burst_pairs", 0), total.get("ordinary_pairs", 0)
    print(f"burst pairs {b}: failed {total.get('burst_failed_carried', 0)} carried, "
          f"{total.get('burst_failed_restarted', 0)} restarted just before the burst")
    print(f"ordinary pairs after a restart {o}: failed {total.get('ordinary_failed_carried', 0)} carried, "
          f"{total.get('ordinary_failed_restarted', 0)} restarted")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"gates": gate_statistics(args.weights), **total}, fh, indent=1)


if __name__ == "__main__":
    main()
