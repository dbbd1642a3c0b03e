"""The model card's ablation table from a ``mosaic bench --flights ... --json`` report.

    python scripts/ablation_table.py REPORT.json [--name LABEL=NAME ...] [--ratio-to LABEL]

One row per estimator, in the report's order (or the order of --name): MACE over all flights
and, per profile, MACE and failure rate; median corner error, failure rate, the share of pairs
the classical fallback made (learned estimators) and CPU ms per frame (p50); --ratio-to adds each
MACE as a multiple of that estimator's (per profile too).  A second table gives the CPU ms per
frame (p50) of each profile.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path)
    parser.add_argument("--name", action="append", default=[], help="LABEL=NAME: the row name of a bench label")
    parser.add_argument("--ratio-to", help="bench label whose MACE the others are divided by")
    args = parser.parse_args()

    report = json.loads(args.report.read_text())
    estimators = report["estimators"]
    names: dict[str, str] = {}
    for item in args.name:
        label, _, name = item.rpartition("=")
        names[label] = name
    labels = [label for label in names if label in estimators] or list(estimators)
    profiles = report["source"]["profiles"]
    base = estimators.get(args.ratio_to) if args.ratio_to else None

    def mace(entry: dict, ref: dict | None) -> str:
        text = f"{entry['mace']:.2f}"
        return f"{text} ({entry['mace'] / ref['mace']:.2f}x)" if ref and ref["mace"] > 0 else text

    head = ["method", "MACE, all", *[f"{p}: MACE / failed" for p in profiles], "median corner error (px)", "failure rate",
            "fallback pairs", "CPU ms/frame (p50)"]
    print("| " + " | ".join(head) + " |")
    print("| --- |" + " ---: |" * (len(head) - 1))
    for label in labels:
        e = estimators[label]
        paths = e.get("paths")
        fallback = f"{100 * paths.get('fallback', 0) / max(1, sum(paths.values())):.1f}%" if paths else "-"
        cells = [names.get(label, f"`{label}`"), mace(e, base)]
        cells += [f"{mace(e['profiles'][p], base['profiles'][p] if base else None)} / {100 * e['profiles'][p]['failure_rate']:.1f}%"
                  for p in profiles]
        cells += [f"{e['corner_error']:.2f}", f"{100 * e['failure_rate']:.1f}%", fallback, f"{e['cpu_ms_per_frame']['p50']:.2f}"]
        print("| " + " | ".join(cells) + " |")
    print()
    print("| CPU ms/frame (p50) | " + " | ".join(profiles) + " |")
    print("| --- |" + " ---: |" * len(profiles))
    for label in labels:
        e = estimators[label]
        print(f"| {names.get(label, f'`{label}`')} | " + " | ".join(f"{e['profiles'][p]['cpu_ms_per_frame']['p50']:.2f}" for p in profiles) + " |")
    source = report["source"]
    print(f"\n{source['frames']} frames, {len(source['flights'])} flights in {source['path']}; "
          f"{report['units']}")


if __name__ == "__main__":
    main()
