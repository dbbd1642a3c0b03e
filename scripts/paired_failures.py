#!/usr/bin/env python3
"""Two estimators of one ``mosaic bench --flights ... --json REPORT`` run, compared pair by pair.

    python scripts/paired_failures.py REPORT.json A B [A B ...]

For each pair of labels: on the pairs that touch a burst and on the others, how many each one
fails (corner error over 10 px, 1280x720-equivalent), how many only A fails and only B fails
(the discordant pairs, which alone decide a paired comparison), the ratio of the failure counts
A / B, and the standard error of the paired difference of the failure rates,
sqrt(b + c - (b - c)^2 / n) / n with b, c the discordant counts and n the pairs.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

FAILURE_PX = 10.0


def pairs_of(entry: dict) -> tuple[np.ndarray, np.ndarray]:
    errors, burst = [], []
    for flight in sorted(entry["per_pair"]):
        row = entry["per_pair"][flight]
        e = np.array([np.inf if v is None else v for v in row["corner_errors"]], float)
        errors.append(e)
        burst.append(np.array(row.get("touches_burst", [0] * len(e)), bool))
    return np.concatenate(errors), np.concatenate(burst)


def compare(report: dict, a: str, b: str) -> dict:
    ea, burst = pairs_of(report["estimators"][a])
    eb, burst_b = pairs_of(report["estimators"][b])
    if len(ea) != len(eb) or not np.array_equal(burst, burst_b):
        raise SystemExit(f"{a} and {b} did not score the same pairs")
    out = {}
    for name, mask in (("burst", burst), ("other", ~burst)):
        fa, fb = ea[mask] > FAILURE_PX, eb[mask] > FAILURE_PX
        n = int(mask.sum())
        only_a, only_b = int((fa & ~fb).sum()), int((fb & ~fa).sum())
        se = math.sqrt(max(only_a + only_b - (only_a - only_b) ** 2 / n, 0.0)) / n if n else float("nan")
        out[name] = {"pairs": n, "failed_a": int(fa.sum()), "failed_b": int(fb.sum()), "only_a": only_a, "only_b": only_b,
                     "ratio": float(fa.sum() / fb.sum()) if fb.sum() else float("inf"), "se_rate_difference": se}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("report")
    ap.add_argument("labels", nargs="+", help="pairs of estimator labels: A B [A B ...]")
    ap.add_argument("--json", help="also write the comparisons here")
    args = ap.parse_args()
    if len(args.labels) % 2:
        raise SystemExit("labels come in pairs: A B [A B ...]")
    report = json.loads(open(args.report).read())
    results = []
    for a, b in zip(args.labels[::2], args.labels[1::2]):
        result = compare(report, a, b)
        results.append({"a": a, "b": b, **result})
        for name in ("burst", "other"):
            r = result[name]
            print(f"{name:5s} pairs {r['pairs']:5d}: {a} failed {r['failed_a']:4d} ({r['failed_a'] / max(r['pairs'], 1):6.1%}), "
                  f"{b} failed {r['failed_b']:4d} ({r['failed_b'] / max(r['pairs'], 1):6.1%}); ratio {r['ratio']:.2f}; "
                  f"only A {r['only_a']}, only B {r['only_b']}; SE of the rate difference {r['se_rate_difference']:.2%}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)


if __name__ == "__main__":
    main()
