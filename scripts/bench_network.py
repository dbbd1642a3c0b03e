"""Cost of the homography network presets on this machine: parameters, MB, GMAC per frame pair,
and CPU latency per pair, measured the way the learned estimator runs the net (backbone on a
chunk of pairs in one channels-last batch, then the head stepped over the chunk) and one pair
per call; optionally the whole learned estimator against ORB on the same in-memory frames.

    python scripts/bench_network.py                       # both presets, both heads, 1 thread
    python scripts/bench_network.py --threads 2 --repeats 15
    python scripts/bench_network.py --estimators          # + end-to-end ms/frame vs ORB (compact)
    python scripts/bench_network.py --device cuda --chunk 64

Timings are medians over interleaved repeats (the configurations take turns, so background load
hits them alike).  Weights are random: speed does not depend on them.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from mosaic_cli.model import HomographyNet, NetConfig, count_parameters, macs_per_pair


def time_net(model: HomographyNet, batch: int, device: torch.device, chunked: bool) -> float:
    """Milliseconds per pair for one call on ``batch`` consecutive pairs."""
    x = torch.rand(batch, 2, model.config.patch, model.config.patch, device=device) * 2 - 1
    if device.type == "cpu":
        x = x.contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        feats = model.features(x)
        model.step(feats[None] if chunked else feats[:, None])
        if device.type == "cuda":
            torch.cuda.synchronize()
    return 1000.0 * (time.perf_counter() - start) / batch


def bench_networks(args, device: torch.device) -> None:
    configs = [NetConfig(preset=p, head=h) for p in args.presets for h in ("cnn", "lstm")]
    models = []
    for c in configs:
        m = HomographyNet(c).to(device).eval()
        if device.type == "cpu":
            m = m.to(memory_format=torch.channels_last)
        models.append(m)
    modes = [(args.chunk, True), (1, True)]
    times = {(i, b): [] for i in range(len(models)) for b, _ in modes}
    for rep in range(args.repeats + 1):  # the first round warms up
        for i, m in enumerate(models):
            if m.config.preset == "paper" and rep > max(3, args.repeats // 3):
                continue  # 8x slower; a few repeats are enough
            for batch, chunked in modes:
                t = time_net(m, batch, device, chunked)
                if rep:
                    times[(i, batch)].append(t)
    print(f"device {device}, {torch.get_num_threads()} thread(s), medians of interleaved repeats")
    print(f"{'preset':8} {'head':5} {'params':>8} {'MB fp32':>8} {'GMAC/pair':>10} {f'ms/pair x{args.chunk}':>12} {'ms/pair x1':>11}")
    for i, (c, m) in enumerate(zip(configs, models)):
        n = count_parameters(m)
        print(
            f"{c.preset:8} {c.head:5} {n / 1e6:7.2f}M {n * 4 / 1e6:8.1f} {macs_per_pair(c) / 1e9:10.3f} "
            f"{statistics.median(times[(i, args.chunk)]):12.2f} {statistics.median(times[(i, 1)]):11.2f}"
        )


def panning_frames(n: int, size=(320, 180), seed=0) -> list[np.ndarray]:
    """A textured map seen by a camera panning 3 px per frame (RGB frames at ``size``)."""
    rng = np.random.default_rng(seed)
    w, h = size[0] + 3 * n + 8, size[1] + 2 * n + 8
    img = np.zeros((h, w), np.float32)
    for cell, weight in ((64, 1.0), (16, 0.7), (4, 0.4)):
        img += weight * cv2.resize(rng.random((h // cell + 2, w // cell + 2)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    return [img[2 * t : 2 * t + size[1], 3 * t : 3 * t + size[0]] for t in range(n)]


def bench_estimators(args, device: torch.device) -> None:
    from mosaic_cli.estimators import OrbEstimator, estimate_stream
    from mosaic_cli.estimators.learned import LearnedConfig, make_learned_estimator
    from mosaic_cli.model import save_weights

    frames = panning_frames(args.frames)
    size = (frames[0].shape[1], frames[0].shape[0])
    estimators = {"orb": OrbEstimator(320)}
    with tempfile.TemporaryDirectory() as tmp:
        for head, variant in (("lstm", "lstm-reg-all"), ("cnn", "reg-all")):
            model = HomographyNet(NetConfig(preset="compact", head=head))
            path = Path(tmp) / f"{head}.safetensors"
            save_weights(path, model, model.config, variant)
            estimators[f"compact-{head}"] = make_learned_estimator(head, weights=path, device=str(device), config=LearnedConfig(chunk=args.chunk))
    times = {name: [] for name in estimators}
    for rep in range(args.repeats + 1):
        for name, est in estimators.items():
            start = time.perf_counter()
            n = sum(1 for _ in estimate_stream(est, frames, size))
            if rep:
                times[name].append(1000.0 * (time.perf_counter() - start) / (n + 1))
    print(f"\nwhole estimator on {len(frames)} in-memory 320x180 frames (no decoding), ms per frame:")
    for name, ts in times.items():
        print(f"  {name:14} median {statistics.median(ts):6.2f}   min {min(ts):6.2f}   max {max(ts):6.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--presets", nargs="+", default=["compact", "paper"])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--chunk", type=int, default=16, help="pairs per backbone batch")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--estimators", action="store_true", help="also time the whole estimator vs ORB")
    parser.add_argument("--frames", type=int, default=65)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    device = torch.device(args.device)
    bench_networks(args, device)
    if args.estimators:
        bench_estimators(args, device)


if __name__ == "__main__":
    main()
