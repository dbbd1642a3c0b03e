"""How tight the overlay detector's mask is, per overlay, against the simulator's exact pixels
(docs/measurements/stitch.md, "Burned-in overlays").

    python scripts/bench_overlay_mask.py                       # seeds 1-6, logo+timestamp and all
    python scripts/bench_overlay_mask.py --seeds 1 --overlays all --repeat 1

Each seed's survey flight (1280x720, 600 frames, over the NEON orthophoto in ../shared/data
when present, a procedural map otherwise; the same plans as scripts/bench_overlay.py) is
rendered with overlays burned in, and the burner is replayed frame by frame for each overlay's
own pixels (``OverlayBurner.kinds``: every pixel it drew in some frame).  Then
``frame_mask`` (sampling plus detection, as every command runs it) and, per overlay:

* overlay px: what it drew; missed: of those, not masked (the panorama can show them);
* hidden ground: masked pixels that no overlay drew, each counted for the overlay nearest to it
  (``elsewhere`` beyond 32 px of any);
* IoU: the masked pixels counted for the overlay against its drawn ones.

And the detector's cost: sampling plus detection per frame of the clip, and the detection
alone per sampled frame (median of ``--repeat``; CPU time, ffmpeg's included, is the figure to
read on a loaded machine).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_stitch import ORTHOPHOTO  # noqa: E402

from mosaic_cli.overlay import MaskOptions, OverlayOptions, detect_overlays, frame_mask, sample_frames  # noqa: E402
from mosaic_cli.simulate import OverlaySpec, load_map, plan_flight, write_flight  # noqa: E402
from mosaic_cli.simulate.overlay import OverlayBurner  # noqa: E402
from mosaic_cli.video import probe  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_WORKDIR = ROOT / ".dev" / "bench_overlay"
SIZE = (1280, 720)
NEAR = 32  # px: hidden ground farther than this from every overlay is counted as "elsewhere"


def burned_flight(workdir: Path, frames: int, seed: int, overlays: str) -> tuple[Path, dict[str, np.ndarray]]:
    """The burned-in flight (cached; the file scripts/bench_overlay.py renders) and each
    overlay's drawn pixels."""
    known = ORTHOPHOTO.exists()
    ground = load_map(ORTHOPHOTO if known else None, seed=seed)
    plan = plan_flight((ground.shape[1], ground.shape[0]), "survey", frames, SIZE, seed)
    spec = OverlaySpec.parse(overlays)
    path = workdir / f"survey_{SIZE[0]}x{SIZE[1]}_{frames}_s{seed}_{overlays.replace(',', '+')}.mp4"
    if not path.exists():
        write_flight(path, ground, plan, map_name=ORTHOPHOTO.name if known else "procedural", preset="veryfast",
                     show_progress=False, overlays=spec)
    burner = OverlayBurner(spec, SIZE, plan.fps)
    blank = np.zeros((SIZE[1], SIZE[0], 3), np.uint8)
    for t in range(plan.frames):
        burner.draw(blank, t)
    written = cv2.imread(str(path.with_name(path.stem + ".mask.png")), cv2.IMREAD_GRAYSCALE)
    assert np.array_equal(written == 0, burner.drawn), "the replayed burner disagrees with the written mask"
    return path, burner.kinds()


def score(masked: np.ndarray, kinds: dict[str, np.ndarray]) -> dict[str, dict]:
    """Per overlay: drawn, missed, hidden ground (nearest overlay), IoU; and ``elsewhere``."""
    names = list(kinds)
    drawn = np.zeros_like(masked)
    for m in kinds.values():
        drawn |= m
    # Distance of every pixel to each overlay's drawn pixels: the nearest one owns it.
    distances = np.stack([cv2.distanceTransform(np.where(kinds[k], 0, 255).astype(np.uint8), cv2.DIST_L2, 5) for k in names])
    nearest = distances.argmin(axis=0)
    far = distances.min(axis=0) > NEAR
    out = {}
    for i, k in enumerate(names):
        own = (nearest == i) & ~far
        counted = masked & own
        hidden = counted & ~drawn
        missed = kinds[k] & ~masked
        union = np.count_nonzero(counted | kinds[k])
        out[k] = {"overlay px": int(kinds[k].sum()), "masked px": int(counted.sum()), "missed px": int(missed.sum()),
                  "hidden ground px": int(hidden.sum()), "IoU": float(np.count_nonzero(counted & kinds[k]) / max(union, 1))}
    out["elsewhere"] = {"hidden ground px": int(np.count_nonzero(masked & far & ~drawn))}
    union = np.count_nonzero(masked | drawn)
    out["all"] = {"overlay px": int(drawn.sum()), "masked px": int(masked.sum()), "missed px": int(np.count_nonzero(drawn & ~masked)),
                  "hidden ground px": int(np.count_nonzero(masked & ~drawn)), "IoU": float(np.count_nonzero(masked & drawn) / max(union, 1)),
                  "masked %": 100.0 * float(masked.mean()), "overlay %": 100.0 * float(drawn.mean())}
    return out


def cpu_seconds() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def cost(path: Path, repeat: int) -> dict:
    info = probe(path)
    wall, cpu = [], []
    for _ in range(repeat):
        clock, used = time.perf_counter(), cpu_seconds()
        frame_mask(path, MaskOptions(), info)
        wall.append(time.perf_counter() - clock)
        cpu.append(cpu_seconds() - used)
    o = OverlayOptions()
    import mosaic_cli.overlay as overlay

    # As frame_mask reads them (the detector before tracing read them at its working width).
    width = overlay.sample_width(info.source_size, o) if hasattr(overlay, "sample_width") else min(o.width, info.source_size[0])
    frames = sample_frames(path, o.samples, width, info)
    alone, alone_cpu = [], []
    for _ in range(repeat):
        clock, used = time.perf_counter(), time.process_time()
        detect_overlays(frames, info.source_size, o)
        alone.append(time.perf_counter() - clock)
        alone_cpu.append(time.process_time() - used)
    n = info.frame_count
    return {"sample + detect ms per clip frame (wall)": 1000 * float(np.median(wall)) / n,
            "sample + detect ms per clip frame (CPU, ffmpeg included)": 1000 * float(np.median(cpu)) / n,
            "detect alone ms per sampled frame (wall)": 1000 * float(np.median(alone)) / len(frames),
            "detect alone ms per sampled frame (CPU)": 1000 * float(np.median(alone_cpu)) / len(frames)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR)
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    parser.add_argument("--overlays", nargs="+", default=["logo,timestamp", "all"])
    parser.add_argument("--repeat", type=int, default=3, help="timing repeats (0: no timing)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    for overlays in args.overlays:
        for seed in args.seeds:
            path, kinds = burned_flight(args.workdir, args.frames, seed, overlays)
            mask = frame_mask(path, MaskOptions())
            masked = np.zeros(next(iter(kinds.values())).shape, bool) if mask.use is None else mask.use == 0
            row = {"overlays": overlays, "seed": seed, "score": score(masked, kinds)}
            if args.repeat > 0:
                row["cost"] = cost(path, args.repeat)
            rows.append(row)
            s = row["score"]
            line = "  ".join(f"{k}: IoU {v['IoU']:.2f} hidden {v['hidden ground px']} missed {v['missed px']} of {v['overlay px']}"
                             for k, v in s.items() if k not in ("all", "elsewhere"))
            print(f"{overlays:15s} seed {seed}  masked {s['all']['masked %']:.2f}% for {s['all']['overlay %']:.2f}% drawn  "
                  f"IoU {s['all']['IoU']:.2f}  missed {s['all']['missed px']}  |  {line}  elsewhere {s['elsewhere']['hidden ground px']}"
                  + (f"  |  {row['cost']['sample + detect ms per clip frame (CPU, ffmpeg included)']:.2f} CPU ms/frame, detect "
                     f"{row['cost']['detect alone ms per sampled frame (CPU)']:.2f} CPU ms/sample" if "cost" in row else ""), flush=True)
    for overlays in args.overlays:
        group = [r["score"] for r in rows if r["overlays"] == overlays]
        kinds = [k for k in group[0] if k != "elsewhere"]
        print(f"{overlays}: mean over {len(group)} flights")
        for k in kinds:
            v = {f: float(np.mean([g[k][f] for g in group])) for f in group[0][k]}
            print(f"  {k:10s} overlay {v['overlay px']:8.0f} px  masked {v['masked px']:8.0f}  hidden ground {v['hidden ground px']:8.0f}  "
                  f"missed {v['missed px']:6.1f} (worst {max(g[k]['missed px'] for g in group)})  IoU {v['IoU']:.3f}")
        print(f"  elsewhere  hidden ground {np.mean([g['elsewhere']['hidden ground px'] for g in group]):.0f} px")
        costs = [r["cost"] for r in rows if r["overlays"] == overlays and "cost" in r]
        if costs:
            print("  " + ", ".join(f"{k} {np.median([c[k] for c in costs]):.2f}" for k in costs[0]))
    print(f"  reproduce: python scripts/bench_overlay_mask.py --frames {args.frames} --seeds {' '.join(map(str, args.seeds))} "
          f"--overlays {' '.join(args.overlays)} --repeat {args.repeat}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
