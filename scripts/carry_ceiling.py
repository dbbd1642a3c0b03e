#!/usr/bin/env python3
"""How well any carry from the past motions could place a flight's spoilt pairs: the ceiling of a
carried motion, from the flights' ground truth alone.

    python scripts/carry_ceiling.py FLIGHTS_DIR [--report R.json --label ESTIMATOR] [--tracks DIR]

For every pair that touches a spoilt frame (glare, blur, dark, flat; drops and duplicates are
placed by the frames themselves), the motion is guessed from the TRUE motions of the clean pairs
before it, as if every one of them had been confirmed exactly:

- ``last``: the last clean pair's motion (the velocity rule, ``carry=velocity``, with a perfect seed);
- ``mean k``: the mean of the last k clean pairs' motions (a smoothed velocity);
- ``accel``: the last motion plus its change since the one before (constant acceleration).

Each guess is scored as ``mosaic bench`` scores an estimate: the mean corner error at 1280x720
(the flights' size), failed over 10 px.  With ``--report``, the estimator ``--label`` of that
``mosaic bench --flights FLIGHTS_DIR --json R.json`` run is scored on the same pairs, with how many
of its failures the perfect-seed rule also fails (the pairs no carry from the past could place).
With ``--tracks DIR`` (``DIR/NAME.json``: ``mosaic track FLIGHTS_DIR/NAME.mp4 -o DIR/NAME.json`` for
each flight), the same rules from the motions that track *confirmed* (path ``learned`` or
``fallback``) instead of the true ones, and the track's own estimates on those pairs: what
carrying every spoilt pair would have done beside what the track did (polish or carry, pair by
pair).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mosaic_cli.geometry import corner_error

FAILURE_PX = 10.0
PLACED_BY_FRAMES = ("drop", "duplicate")
HISTORY = 8
CONFIRMED = ("learned", "fallback")  # the paths of a track whose motion the frames confirmed


def guesses(history: list[np.ndarray]) -> dict[str, np.ndarray]:
    """The motions (true or confirmed) of the clean pairs before a spoilt one, newest first -> each
    rule's guess."""
    out = {"last": history[0]}
    for k in (2, 3, 5):
        if len(history) >= k:
            mean = np.mean(history[:k], axis=0)
            out[f"mean {k}"] = mean / mean[2, 2]
    if len(history) >= 2:
        out["accel"] = 2 * history[0] - history[1]
    return out


def flight_rows(truth_path: Path, track_path: Path | None = None) -> list[dict]:
    """One row per spoilt pair with a clean pair before it: each rule's corner error from the true
    past motions (``errors``), and with ``track_path`` from the track's confirmed ones
    (``tracked``, None where it confirmed no clean pair before) and the track's own (``track``)."""
    truth = json.loads(truth_path.read_text())
    motions = np.array(truth["pairwise"], float)
    size = tuple(truth["size"])
    events = {e["frame"]: e["kind"] for e in truth["bursts"]}
    spoilt = {f for f, kind in events.items() if kind not in PLACED_BY_FRAMES}
    track = json.loads(track_path.read_text()) if track_path is not None else None
    rows = []
    for i in range(len(motions)):
        if i not in spoilt and i + 1 not in spoilt:
            continue
        clean = [j for j in range(i - 1, -1, -1) if j not in events and j + 1 not in events]
        history = [motions[j] for j in clean[:HISTORY]]
        if not history:
            continue
        row = {"flight": truth_path.name.removesuffix(".gt.json"), "pair": i,
               "errors": {name: float(corner_error(guess, motions[i], size)) for name, guess in guesses(history).items()}}
        if track is not None:
            estimated = np.array(track["pairwise"], float)
            confirmed = [estimated[j] for j in clean if track["path"][j] in CONFIRMED][:HISTORY]
            row["tracked"] = ({name: float(corner_error(guess, motions[i], size)) for name, guess in guesses(confirmed).items()}
                              if confirmed else None)
            row["track"] = float(corner_error(estimated[i], motions[i], size))
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flights", type=Path)
    ap.add_argument("--report", type=Path, help="a mosaic bench --flights FLIGHTS --json report")
    ap.add_argument("--label", help="the estimator of --report to score on the same pairs")
    ap.add_argument("--tracks", type=Path, help="a folder of mosaic track JSON files, one per flight, named as the flights")
    args = ap.parse_args()
    if args.tracks:
        missing = [p.name for p in sorted(args.flights.glob("*.gt.json")) if not (args.tracks / p.name.replace(".gt.json", ".json")).is_file()]
        if missing:
            raise SystemExit(f"no track of {missing[0]} in {args.tracks} (mosaic track {args.flights}/"
                             f"{missing[0].replace('.gt.json', '.mp4')} -o {args.tracks}/{missing[0].replace('.gt.json', '.json')})")
    rows = [row for path in sorted(args.flights.glob("*.gt.json"))
            for row in flight_rows(path, args.tracks / path.name.replace(".gt.json", ".json") if args.tracks else None)]
    if not rows:
        raise SystemExit(f"no spoilt pair with a clean pair before it in {args.flights}")
    print(f"{len(rows)} spoilt pairs (a clean pair before them) in {args.flights}")
    for name in ("last", "mean 2", "mean 3", "mean 5", "accel"):
        scored = [r["errors"][name] for r in rows if name in r["errors"]]
        failed = sum(e > FAILURE_PX for e in scored)
        print(f"  {name:7s} (true past motions): {failed:4d} of {len(scored)} failed, median {np.median(scored):.2f} px")
    if args.report:
        per_pair = json.loads(args.report.read_text())["estimators"][args.label]["per_pair"]
        estimated = np.array([np.inf if (v := per_pair[r["flight"]]["corner_errors"][r["pair"]]) is None else v for r in rows])
        rule = np.array([r["errors"]["last"] for r in rows])
        fails, rule_fails = estimated > FAILURE_PX, rule > FAILURE_PX
        print(f"  {args.label}: {int(fails.sum())} of {len(rows)} failed; {int((fails & rule_fails).sum())} of them the "
              f"perfect-seed rule fails too, {int((fails & ~rule_fails).sum())} it places; "
              f"it places {int((~fails & rule_fails).sum())} the perfect-seed rule fails")
    if args.tracks:
        tracked = [r for r in rows if r["tracked"] is not None]
        print(f"  {len(tracked)} of them with a confirmed clean pair before them in {args.tracks}:")
        for name in ("last", "mean 2", "accel"):
            scored = [r["tracked"][name] for r in tracked if name in r["tracked"]]
            print(f"  {name:7s} (confirmed motions): {sum(e > FAILURE_PX for e in scored):4d} of {len(scored)} failed, "
                  f"median {np.median(scored):.2f} px")
        own = np.array([r["track"] for r in tracked]) > FAILURE_PX
        carry = np.array([r["tracked"]["last"] for r in tracked]) > FAILURE_PX
        print(f"  the track itself: {int(own.sum())} failed; carrying the last confirmed motion on every one of them "
              f"places {int((own & ~carry).sum())} of those and fails {int((~own & carry).sum())} the track placed")


if __name__ == "__main__":
    main()
