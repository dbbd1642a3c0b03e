"""Are the outputs unchanged?  ``track``, ``stitch`` and ``stabilize`` run on one small simulated
clip with the working tree's code and with the code of a git revision, their JSON compared.

    python -m benchmarks compare --rev eef602d
    python -m benchmarks compare --rev eef602d --estimator orb --frames 120 --size 480x270

The clip (``mosaic simulate -p survey`` over a real aerial still of ../shared/data when there,
a procedural map otherwise) is made once, by the working tree's simulator.  REV is checked out
with ``git worktree add --detach`` into a temporary folder (removed afterwards) and run from
there with ``PYTHONPATH`` pointing at it; both run ``python -m mosaic_cli`` with this Python.
Compared: the track JSON's ``pairwise`` homographies, the stitch ``--transforms`` JSON (its
canvas size, the frames used and each frame's ``H``) and the stabilize ``--warps`` JSON
(``warps``); each homography normalised to H[2,2] = 1.  Exit 0 when every output agrees
within --atol, 1 otherwise.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import ORTHOPHOTO, ROOT, make_parser

SUITE = "compare"
MAP = ORTHOPHOTO


def mosaic(checkout: Path, *args: str | Path) -> float:
    """``python -m mosaic_cli ARGS`` with the code of ``checkout``; its seconds."""
    env = dict(os.environ, PYTHONPATH=str(checkout))
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "mosaic_cli", *map(str, args)], cwd=checkout, env=env,
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{checkout}: mosaic {' '.join(map(str, args))} failed ({done.returncode}):\n{done.stderr}")
    return time.perf_counter() - start


COMMANDS = ("track", "stitch", "stabilize")


def run_all(checkout: Path, clip: Path, out: Path, estimator: list[str], commands=COMMANDS) -> dict[str, float]:
    out.mkdir(parents=True, exist_ok=True)
    args = {
        "track": ("track", clip, "-o", out / "track.json"),
        "stitch": ("stitch", clip, "-o", out / "pano.png", "--transforms", out / "stitch.json"),
        "stabilize": ("stabilize", clip, out / "stab.mp4", "--warps", out / "warps.json"),
    }
    return {c: mosaic(checkout, *args[c], *estimator, "-q") for c in commands}


def _unit(H) -> np.ndarray:
    H = np.asarray(H, dtype=np.float64)
    return H / H[..., 2:3, 2:3]


def difference(a, b) -> float:
    """Largest absolute difference of two stacks of homographies (inf when their shapes differ)."""
    a, b = _unit(a) if len(a) else np.zeros((0, 3, 3)), _unit(b) if len(b) else np.zeros((0, 3, 3))
    if a.shape != b.shape:
        return float("inf")
    return float(np.abs(a - b).max(initial=0.0))


def compare(mine: Path, theirs: Path, commands=COMMANDS) -> list[tuple[str, str, float, str]]:
    """(command, output, max abs difference, note) for each command's output."""
    rows = []
    if "track" in commands:
        t1, t2 = (json.loads((d / "track.json").read_text()) for d in (mine, theirs))
        n1, n2 = len(t1["pairwise"]), len(t2["pairwise"])
        rows.append(("track", "track pairwise", difference(t1["pairwise"], t2["pairwise"]), f"{n1} pairs" + ("" if n1 == n2 else f" against {n2}")))
    if "stitch" in commands:
        s1, s2 = (json.loads((d / "stitch.json").read_text()) for d in (mine, theirs))
        i1, i2 = [f["index"] for f in s1["frames"]], [f["index"] for f in s2["frames"]]
        same = i1 == i2 and s1["canvas_size"] == s2["canvas_size"]
        note = f"{len(i1)} frames, canvas {s1['canvas_size']}" + ("" if same else f"; theirs {len(i2)} frames {i2}, canvas {s2['canvas_size']}")
        d = difference([f["H"] for f in s1["frames"]], [f["H"] for f in s2["frames"]]) if same else float("inf")
        rows.append(("stitch", "stitch transforms H", d, note))
    if "stabilize" in commands:
        w1, w2 = (json.loads((d / "warps.json").read_text()) for d in (mine, theirs))
        rows.append(("stabilize", "stabilize warps", difference(w1["warps"], w2["warps"]), f"{len(w1['warps'])} warps"))
    return rows


def main(argv: list[str] | None = None) -> int | None:
    parser = make_parser(SUITE, None, __doc__)
    parser.add_argument("--rev", required=True, help="git revision to compare with (e.g. eef602d)")
    parser.add_argument("--frames", type=int, default=90)
    parser.add_argument("--size", default="320x180")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--estimator", help="-e for all three commands (default: each command's default)")
    parser.add_argument("--atol", type=float, default=1e-9, help="largest difference counted as the same")
    parser.add_argument("--commands", nargs="+", choices=COMMANDS, default=list(COMMANDS), help="which outputs to compare")
    parser.add_argument("--keep", type=Path, help="keep the clip and both runs' outputs in this folder")
    args = parser.parse_args(argv)
    estimator = ["-e", args.estimator] if args.estimator else []
    rev = subprocess.run(["git", "rev-parse", "--short", args.rev], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="mosaic-compare-") as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        clip = work / "clip.mp4"
        mosaic(ROOT, "simulate", *([MAP] if MAP.exists() else []), "-p", "survey", "-n", args.frames, "--size", args.size,
               "--seed", args.seed, "-o", clip, "-q")
        checkout = Path(tmp) / f"checkout-{rev}"
        subprocess.run(["git", "worktree", "add", "--detach", "-q", str(checkout), rev], cwd=ROOT, check=True)
        try:
            seconds_mine = run_all(ROOT, clip, work / "worktree", estimator, args.commands)
            seconds_theirs = run_all(checkout, clip, work / f"rev-{rev}", estimator, args.commands)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(checkout)], cwd=ROOT, check=False)
        rows = compare(work / "worktree", work / f"rev-{rev}", args.commands)
    print(f"working tree ({_head()}) against {rev}: {args.frames} frames of {args.size}, survey seed {args.seed}, "
          f"estimator {args.estimator or 'default'}")
    for command, name, diff, note in rows:
        verdict = "same" if diff <= args.atol else "DIFFERENT"
        print(f"  {name:22s} max abs difference {diff:.3g}  {verdict}  ({note}; {seconds_mine[command]:.1f} s here, {seconds_theirs[command]:.1f} s at {rev})")
    raise SystemExit(0 if all(d <= args.atol for _, _, d, _ in rows) else 1)


def _head() -> str:
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True, text=True).stdout
    return head + ("+changes" if dirty.strip() else "")
