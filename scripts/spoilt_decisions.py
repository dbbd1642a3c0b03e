#!/usr/bin/env python3
"""The decision on a spoilt pair between what its frames confirmed and the carried motion: how a
rule fit on development flights would do on test flights, before any of it is built.

    python scripts/spoilt_decisions.py collect DEV.json FLIGHT.mp4 [FLIGHT.mp4 ...]
    python scripts/spoilt_decisions.py collect TEST.json FLIGHT.mp4 [FLIGHT.mp4 ...]
    python scripts/spoilt_decisions.py fit DEV.json TEST.json

``collect`` runs the default estimator (``lstm``) over simulated flights (a ``.gt.json`` beside
each) and keeps every pair that touches a frame it calls spoilt and that its frames confirmed
(the polish or the fallback), where the carried motion was on offer: the check's correlation,
the patches' agreement, the polish's weight, the distance between the confirmed answer and the
carried motion (working px), whether both frames are spoilt, whether the fallback placed it, and
the corner error of each of the two answers (1280x720-equivalent px).

``fit`` chooses, on the development pairs, the one-feature threshold and a logistic regression
(carry where it predicts the carried motion is the better answer) that fail the fewest pairs,
and prints, by flight profile, what each would fail on both sets beside the default (always
the confirmed answer) and carrying always.  Offline: each pair is scored as if the other
decisions stayed as they were (a carried pair also changes the motion carried after it).
models/README.md, "The carry head", "What would come next".
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

FAILURE_PX = 10.0
FEATURES = ("zncc", "agreement", "polish_weight", "log_distance", "both_spoilt", "fallback")


def collect(out: Path, videos: list[Path]) -> None:
    import torch

    torch.set_num_threads(1)
    rows = [row for video in videos for row in flight_decisions(video)]
    out.write_text(json.dumps(rows))
    print(f"{len(rows)} spoilt pairs confirmed from their frames in {len(videos)} flights -> {out}")


def flight_decisions(video: Path) -> list[dict]:
    """The default estimator over one flight, with its decisions watched (see the module doc)."""
    from mosaic_cli.bench import decode_frames
    from mosaic_cli.estimators import make_estimator
    from mosaic_cli.geometry import corner_error

    truth = json.loads(video.with_suffix(".gt.json").read_text())
    motions, size = np.array(truth["pairwise"], float), tuple(truth["size"])
    est = make_estimator("lstm")
    frames, _, info = decode_frames(video, est.input_width)
    full = tuple(info.source_size)
    est.reset(full)
    work = (frames[0].shape[1], frames[0].shape[0])
    S = np.diag([work[0] / full[0], work[0] / full[0], 1.0])
    decided, rows = est._decide, []

    def decide(prev, cur, seed, agreement, check):
        pair = len(decisions)  # pairs are decided one at a time, in order
        decisions.append(pair)
        carried, can_carry = est._motion.copy(), est._can_carry()
        result = decided(prev, cur, seed, agreement, check)
        if (prev.spoilt or cur.spoilt) and result.path in ("learned", "fallback") and can_carry:
            polished = check.polished
            rows.append({
                "flight": video.name, "pair": pair, "profile": truth["profile"], "zncc": float(check.zncc),
                "agreement": float(agreement),
                "polish_weight": float(est._polish_weight(polished)) if polished is not None else 0.0,
                "log_distance": float(np.log1p(corner_error(S @ result.H @ np.linalg.inv(S), carried, work))),
                "both_spoilt": float(prev.spoilt and cur.spoilt), "fallback": float(result.path == "fallback"),
                "error_confirmed": float(corner_error(result.H, motions[pair], size)),
                "error_carried": float(corner_error(np.linalg.inv(S) @ carried @ S, motions[pair], size)),
            })
        return result

    decisions: list[int] = []
    est._decide = decide  # type: ignore[method-assign]
    for frame in frames:
        est.feed(frame)
    est.finish()
    return rows


def load(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rows = json.loads(path.read_text())
    X = np.array([[r[f] for f in FEATURES] for r in rows], float).reshape(-1, len(FEATURES))
    confirmed = np.array([r["error_confirmed"] > FAILURE_PX for r in rows], bool)
    carried = np.array([r["error_carried"] > FAILURE_PX for r in rows], bool)
    return X, confirmed, carried, np.array([r["profile"] for r in rows])


def fit(dev: Path, test: Path) -> None:
    Xd, confirmed_d, carried_d, profile_d = load(dev)
    Xt, confirmed_t, carried_t, profile_t = load(test)

    def show(name: str, carry_d: np.ndarray, carry_t: np.ndarray) -> None:
        for tag, carry, confirmed, carried, profile in (("dev", carry_d, confirmed_d, carried_d, profile_d),
                                                        ("test", carry_t, confirmed_t, carried_t, profile_t)):
            failed = np.where(carry, carried, confirmed)
            parts = ", ".join(f"{p} {int(failed[profile == p].sum())} of {int((profile == p).sum())}" for p in sorted(set(profile)))
            print(f"  {name:34s} {tag:4s}: {parts}")

    show("default (the confirmed answer)", np.zeros(len(Xd), bool), np.zeros(len(Xt), bool))
    show("carry always", np.ones(len(Xd), bool), np.ones(len(Xt), bool))
    best = None
    for j in range(Xd.shape[1]):
        for sign in (1.0, -1.0):
            for t in np.unique(Xd[:, j]):
                failed = int(np.where(sign * Xd[:, j] < sign * t, carried_d, confirmed_d).sum())
                if best is None or failed < best[0]:
                    best = (failed, j, sign, float(t))
    assert best is not None
    _, j, sign, t = best
    show(f"carry where {FEATURES[j]} {'<' if sign > 0 else '>'} {t:.4f}", sign * Xd[:, j] < sign * t, sign * Xt[:, j] < sign * t)
    # Logistic regression on the pairs where the choice matters: is the carried motion the better answer?
    matters = confirmed_d != carried_d
    target = (carried_d < confirmed_d).astype(float)
    mean, std = Xd.mean(0), Xd.std(0) + 1e-9
    design = lambda X: np.c_[np.ones(len(X)), (X - mean) / std]  # noqa: E731
    Z, w = design(Xd), np.zeros(len(FEATURES) + 1)
    for _ in range(5000):
        p = 1.0 / (1.0 + np.exp(-Z @ w))
        w -= 0.5 * (Z[matters].T @ (p[matters] - target[matters]) / max(int(matters.sum()), 1) + 1e-3 * w)
    print("  logistic weights (standardised features):", ", ".join(f"{n} {v:+.2f}" for n, v in zip(("bias", *FEATURES), w)))
    show("carry where the logistic says so", design(Xd) @ w > 0, design(Xt) @ w > 0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect")
    c.add_argument("out", type=Path)
    c.add_argument("videos", nargs="+", type=Path)
    f = sub.add_parser("fit")
    f.add_argument("dev", type=Path)
    f.add_argument("test", type=Path)
    args = ap.parse_args()
    if args.command == "collect":
        collect(args.out, args.videos)
    else:
        fit(args.dev, args.test)


if __name__ == "__main__":
    main()
