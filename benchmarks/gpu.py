"""Everything a session with a lent GPU does, in one call that ends well inside 10 minutes.

    bash scripts/prepare_gpu_session.sh          # here, once: wheels and stills into .gpu/
    # then one device call:  bash scripts/gpu_session.sh   (carry: [".gpu"])

Stages, each timed into session.log, a summary table printed last (``--stages``: ``training``,
``throughput`` or ``all``; the two travel differently, see scripts/gpu_session.sh):

1. env        the GPU, torch, CUDA
2. data       training flights rendered from the carried stills on the machine's cores (the
              simulator's renderer, OpenCV only: no video encoder there), written as folders of
              320x180 frames; validation flights with bursts over a still kept out of training
3. tests      pytest -m cuda: the CUDA path against the CPU's, AMP steps, one-process nccl DDP
4. bench      mosaic bench --device cuda: lstm, cnn and orb-paper, per-frame latency per stage
5. speed      BASE samples/s and LSTM windows/s with the batches cut on the GPU (--data device)
6. train      the BASE from the shipped cnn, then LSTM-REG-T with bursts from the shipped lstm,
              each for the time left, validated on the burst flights (the network alone)
7. throughput a 720p and a 4K clip rendered there over two real stills (x264 through PyAV: that
              machine has no ffmpeg binary, so mosaic reads and writes video with its PyAV
              backend), the probes (lscpu, nvidia-smi, NVDEC), then, side by side, the wall times
              of track, stabilize and stitch with --device cuda and --device cpu (all cores, and
              track on one thread too) and the plain x264 transcode with the same settings, into
              gpu_throughput.json (issue 39: docs/measurements/gpu_throughput.json); then, while
              time is left, the default track and stabilize under ``python -m benchmarks profile``
              (every thread's time) into logs.tar.gz

Back under $OUT (at most 8 files of 16 MB): gpu_throughput.json (throughput), cnn.safetensors, lstm.safetensors,
bench.json, tests.xml, logs.tar.gz (every run's log.csv / val.csv, the speed probes, env.json),
session.log.  A file over 15 MiB (lstm's weights are 17.4 MB) comes back in parts, NAME.part1,
NAME.part2: `cat NAME.part* > NAME`.
Score the weights on the CPU afterwards: mosaic bench --flights ... -e lstm:weights=$OUT/lstm.safetensors.

``--tiny --device cpu`` runs every stage on tiny data on a CPU, as tests/test_gpu_session.py does,
so that the script cannot rot between the sessions that get a GPU.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import csv
import json
import os
import shutil
import subprocess
import sys
import tarfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from benchmarks.common import ROOT, make_parser, stage_seconds

SUITE = "gpu"

STILLS = ROOT / ".gpu" / "stills"
TRAIN_PROFILES = ("paper", "fast", "hard", "survey", "extreme")


@dataclass
class Plan:
    """What each stage does, at full size (a GPU) or tiny (the CPU rehearsal)."""

    device: str
    minutes: float  # the whole session's budget; training gets what the other stages leave
    tiny: bool
    frames: int = 300
    size: tuple[int, int] = (320, 180)
    val_size: tuple[int, int] = (640, 360)
    base_batch: int = 256
    lstm_batch: int = 64
    probe_minutes: float = 0.35
    work: list[str] = field(default_factory=list)  # --work-size / --patch for tiny runs

    @classmethod
    def make(cls, device: str, minutes: float, tiny: bool) -> Plan:
        if tiny:
            return cls(device, minutes, True, frames=36, size=(128, 96), val_size=(128, 96), base_batch=4, lstm_batch=2,
                       probe_minutes=0.05, work=["--work-size", "64x48", "--patch", "32", "--threads", "1"])
        return cls(device, minutes, False)


class Session:
    def __init__(self, out: Path, work: Path, plan: Plan):
        self.out, self.work, self.plan = out, work, plan
        self.started = time.monotonic()
        self.rows: list[tuple[str, str, str]] = []  # (stage, seconds, result)
        self.logs: list[Path] = []
        self.log = open(out / "session.log", "a")

    def say(self, text: str) -> None:
        line = f"[{time.monotonic() - self.started:7.1f} s] {text}"
        print(line, flush=True)
        self.log.write(line + "\n")
        self.log.flush()

    def left(self) -> float:
        return 60 * self.plan.minutes - (time.monotonic() - self.started)

    def run(self, *args: str, timeout: float | None = None, check: bool = True) -> subprocess.CompletedProcess:
        """A command, its output into session.log; a stage that fails is reported, the session goes on."""
        self.say("$ " + " ".join(args))
        proc = subprocess.run(list(args), cwd=ROOT, capture_output=True, text=True, timeout=timeout)
        self.log.write(proc.stdout[-20000:] + proc.stderr[-20000:])
        if check and proc.returncode:
            raise RuntimeError(f"{args[2] if len(args) > 2 else args[0]} exited {proc.returncode}: {proc.stderr.strip()[-400:]}")
        return proc

    def stage(self, name: str, fn) -> object:
        t0 = time.monotonic()
        try:
            result = fn()
            summary = str(result) if result is not None else "ok"
        except Exception as exc:  # noqa: BLE001 - one stage failing must not lose the others' results
            result, summary = None, f"FAILED: {exc.__class__.__name__}: {str(exc)[:300]}"
        seconds = time.monotonic() - t0
        self.rows.append((name, f"{seconds:.1f}", summary))
        self.say(f"{name}: {summary} ({seconds:.1f} s)")
        return result


def mosaic(*args: str) -> tuple[str, ...]:
    return (sys.executable, "-m", "mosaic_cli", *args)


# ----------------------------------------------------------------------------- stages


def environment(s: Session) -> str:
    import torch

    info = {"torch": torch.__version__, "cuda": torch.version.cuda, "python": sys.version.split()[0],
            "device": s.plan.device, "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "cpus": os.cpu_count()}
    (s.work / "env.json").write_text(json.dumps(info, indent=1))
    s.logs.append(s.work / "env.json")
    return f"{info['gpu'] or 'no GPU'}, torch {info['torch']}, CUDA {info['cuda']}, {info['cpus']} CPUs"


def stills(tiny: bool) -> list[Path | None]:
    """The carried stills (None: a procedural map, for the rehearsal or where none were carried)."""
    found = sorted(STILLS.glob("*.jpg")) if STILLS.is_dir() and not tiny else []
    return list(found) or [None, None]


def render_flight(job: tuple) -> str:
    """One flight as a folder of gray frames (and, for validation, its ground truth beside it)."""
    still, profile, frames, size, seed, folder, with_truth = job
    from mosaic_cli.simulate import SimulateOptions, load_map, plan_simulated_flight, render_frames
    from mosaic_cli.simulate.groundtruth import GroundTruth, ground_truth_path

    cv2.setNumThreads(1)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    map_rgb = load_map(still, seed=seed)
    plan = plan_simulated_flight((map_rgb.shape[1], map_rgb.shape[0]),
                                 SimulateOptions(profile=profile, frames=frames, size=size, seed=seed))
    for t, frame in enumerate(render_frames(map_rgb, plan)):
        cv2.imwrite(str(folder / f"{t:05d}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY))
    if with_truth:
        GroundTruth.from_plan(plan, map_name=Path(still).name if still else "procedural").save(ground_truth_path(folder))
    return str(folder)


def make_data(s: Session) -> str:
    p = s.plan
    maps = stills(p.tiny)
    train_maps, val_map = (maps[:-1], maps[-1]) if len(maps) > 1 else (maps, maps[0])  # the last still is kept out
    jobs, seed = [], 100
    for k, still in enumerate(train_maps):
        for profile in TRAIN_PROFILES[: 2 if p.tiny else None]:
            seed += 1
            jobs.append((str(still) if still else None, profile, p.frames, p.size, seed, str(s.work / "clips" / f"m{k}_{profile}"), False))
    for k in range(1 if p.tiny else 2):
        seed += 1
        jobs.append((str(val_map) if val_map else None, "bursts", p.frames if p.tiny else 150, p.val_size, seed,
                     str(s.work / "val" / f"bursts{k}"), True))
    workers = max(1, min(len(jobs), (os.cpu_count() or 2)))
    with concurrent.futures.ProcessPoolExecutor(workers) as pool:
        done = list(pool.map(render_flight, jobs))
    frames = sum(len(list(Path(d).glob("*.png"))) for d in done)
    return f"{len(done)} flights, {frames} frames rendered on {workers} processes"


# The files whose CUDA-marked tests compare the device's work with the CPU's: the estimator and
# training (test_cuda), the render's warps (test_device_warp, test_stabilize_device_render), stitch's warps and blend (test_stitch_device).
CUDA_TESTS = ("tests/test_cuda.py", "tests/test_device_warp.py", "tests/test_stabilize_device_render.py", "tests/test_stitch_device.py")


def cuda_tests(s: Session) -> str:
    xml = s.out / "tests.xml"
    proc = s.run(sys.executable, "-m", "pytest", "-q", "-m", "cuda", "-p", "no:cacheprovider", *CUDA_TESTS,
                 f"--junitxml={xml}", timeout=max(60.0, 0.25 * s.left()), check=False)
    last = (proc.stdout.strip().splitlines() or ["no output"])[-1]
    if proc.returncode not in (0, 5):
        raise RuntimeError(last)
    return last


def bench(s: Session) -> str:
    video = sorted((s.work / "val").glob("bursts*"))[0]
    out = s.out / "bench.json"
    s.run(*mosaic("bench", "--video", str(video), "-e", "lstm,cnn,orb-paper", "--device", s.plan.device, "--frames", "150",
                  "--json", str(out), "-q"), timeout=max(60.0, 0.3 * s.left()))
    report = json.loads(out.read_text())
    parts = []
    for name, e in report["estimators"].items():
        st = e["stages"]
        warm = f", warm-up {e['warmup_ms']:.0f} ms" if e.get("warmup_ms") is not None else ""
        parts.append(f"{name} {e['ms_per_frame']:.2f} ms/frame (estimate p50 {st['estimate']['p50']:.2f} p95 {st['estimate']['p95']:.2f}{warm})")
    return "; ".join(parts)


def train_args(s: Session, variant: str, init: str, out: Path, batch: int, steps: int, minutes: float, extra=()) -> tuple[str, ...]:
    p = s.plan
    tiny_init = () if p.tiny else ("--init", init)  # the shipped weights read 128 px patches; the rehearsal's are 32
    return mosaic("train", str(s.work / "clips"), "--variant", variant, *tiny_init, "--data", "device", "--device", p.device,
                  "--batch-size", str(batch), "--steps", str(steps), "--max-minutes", f"{minutes:.3f}", "--photometric", "band",
                  "--flip", "--num-workers", "8" if not p.tiny else "0", "--checkpoint-every", "100000", "-o", str(out), "-q",
                  *p.work, *extra)


def rate_of(run: Path) -> float:
    """Samples (windows) per second over the second half of a run's log.csv."""
    rows = list(csv.DictReader(open(run / "log.csv")))
    rates = [float(r["samples_per_s"]) for r in rows[len(rows) // 2:] if float(r["samples_per_s"]) > 0]
    return float(np.median(rates)) if rates else 0.0


def speed(s: Session) -> dict:
    p = s.plan
    rates = {}
    for variant, init, batch in (("base", "models/cnn.safetensors", p.base_batch), ("lstm-reg-t", "models/lstm.safetensors", p.lstm_batch)):
        run = s.work / f"probe-{variant}"
        s.run(*train_args(s, variant, init, run, batch, 10**6, p.probe_minutes, ("--bursts", "0.5") if variant != "base" else ()),
              timeout=120 + 60 * p.probe_minutes * 4)
        rates[variant] = rate_of(run)
        s.logs.append(run / "log.csv")
    return rates


def train(s: Session, rates: dict | None) -> str:
    p = s.plan
    budget = max(0.2, s.left() / 60 - 0.75)  # minutes for both runs; the rest for packing up
    base_min, lstm_min = (0.05, 0.05) if p.tiny else (0.4 * budget, 0.6 * budget)
    rates = rates or {"base": 100.0, "lstm-reg-t": 10.0}
    results = []
    base_run, lstm_run = s.work / "base", s.work / "lstm"
    # Steps sized to the measured rate, so that the paper's learning-rate decays fall inside the time.
    base_steps = max(2, int(rates["base"] * 60 * base_min / p.base_batch * 0.9))
    s.run(*train_args(s, "base", "models/cnn.safetensors", base_run, p.base_batch, base_steps, base_min, ("--lr", "3e-4")),
          timeout=120 + 60 * base_min * 1.5)
    deliver(base_run / "weights.safetensors", s.out / "cnn.safetensors")
    results.append(f"base {base_steps} steps x {p.base_batch} at {rate_of(base_run):.0f} samples/s")
    lstm_steps = max(2, int(rates["lstm-reg-t"] * 60 * lstm_min / p.lstm_batch * 0.9))
    val = ("--val", str(s.work / "val"), "--val-every", str(max(1, lstm_steps // 2)))
    s.run(*train_args(s, "lstm-reg-t", "models/lstm.safetensors", lstm_run, p.lstm_batch, lstm_steps, lstm_min,
                      ("--lr", "1e-4", "--bursts", "0.5", *val)), timeout=180 + 60 * lstm_min * 1.5)
    deliver(lstm_run / "weights.safetensors", s.out / "lstm.safetensors")
    results.append(f"lstm-reg-t {lstm_steps} steps x {p.lstm_batch} at {rate_of(lstm_run):.0f} windows/s")
    for run in (base_run, lstm_run):
        s.logs += [f for f in (run / "log.csv", run / "val.csv") if f.is_file()]
    return "; ".join(results)


FOOTAGE = ROOT / ".gpu" / "footage"
# (name, frame size, the still flown over: a prefix of a file in .gpu/footage), as ``python -m benchmarks speed``
CLIPS = (("1280x720", (1280, 720), "720p"), ("3840x2160", (3840, 2160), "4k"))
X264 = {"preset": "veryfast", "crf": "18"}  # python -m benchmarks speed's transcode settings, and stabilize's here


def transcode(source: str, target: str) -> int:
    """The plain x264 transcode, in-process with PyAV (every frame decoded on frame threads and
    encoded as ``python -m benchmarks speed``'s ``ffmpeg -c:v libx264 -preset veryfast -crf 18``): the
    floor of any stabiliser that re-encodes.  Returns the frames written."""
    import av

    frames = 0
    with av.open(source) as src, av.open(target, "w") as dst:
        video = src.streams.video[0]
        video.thread_type = "AUTO"
        out = dst.add_stream("libx264", rate=video.average_rate, options=dict(X264))
        out.width, out.height, out.pix_fmt = video.codec_context.width, video.codec_context.height, "yuv420p"
        out.time_base = video.time_base  # the source's timestamps, kept: x264's B-frames need them rising
        for frame in src.decode(video):
            dst.mux(out.encode(frame))
            frames += 1
        dst.mux(out.encode(None))
    return frames


def nvdec_probe(clip: Path, frames: int = 120) -> dict:
    """Whether NVDEC decodes H.264 here (PyAV's h264_cuvid, which needs the driver's libnvcuvid),
    and at what rate, against the software decoder on frame threads, over the same frames."""
    import av

    result: dict = {}
    for name in ("h264", "h264_cuvid"):
        try:
            with av.open(str(clip)) as src:
                stream = src.streams.video[0]
                codec = av.CodecContext.create(name, "r")
                if stream.codec_context.extradata:
                    codec.extradata = stream.codec_context.extradata
                codec.thread_type = "AUTO"
                start, n = time.perf_counter(), 0
                for packet in src.demux(stream):
                    for _ in codec.decode(packet):
                        n += 1
                    if n >= frames:
                        break
                result[name] = {"frames": n, "fps": round(n / (time.perf_counter() - start), 1)}
        except Exception as exc:  # noqa: BLE001 - what fails is the finding
            result[name] = {"error": f"{exc.__class__.__name__}: {str(exc)[:200]}"}
    return result


BUILD_PROBE = """
import json, sys, time
t0 = time.perf_counter()
import torch
t1 = time.perf_counter()
from mosaic_cli.estimators.learned import make_learned_estimator
t2 = time.perf_counter()
estimator = make_learned_estimator("lstm", device=sys.argv[1])
t3 = time.perf_counter()
import numpy as np
estimator.reset((1280, 720))
rng = np.random.default_rng(0)
frames = [rng.integers(0, 255, (720, 1280), dtype=np.uint8) for _ in range(17)]
for frame in frames:
    estimator.feed(frame)
t4 = time.perf_counter()
for frame in frames[:16]:
    estimator.feed(frame)
t5 = time.perf_counter()
print(json.dumps({"import_torch_s": t1 - t0, "import_mosaic_s": t2 - t1, "build_s": t3 - t2, "first_chunk_s": t4 - t3,
                  "second_chunk_s": t5 - t4, "precision": estimator.precision, "threads": torch.get_num_threads()}))
"""


def build_probe(s: Session, device: str) -> dict:
    """Where a command's start-up goes, in a process of its own: torch's import, mosaic's, the
    default estimator's build (weights; on a CPU its int8 network) and its first two chunks of 16
    pairs (the first: CUDA's kernels and cuDNN's plans, or the CPU's first int8 calls)."""
    try:
        proc = s.run(sys.executable, "-c", BUILD_PROBE, device, timeout=180, check=False)
        if proc.returncode:
            return {"error": proc.stderr.strip()[-300:]}
        return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in json.loads(proc.stdout.strip().splitlines()[-1]).items()}
    except (subprocess.TimeoutExpired, ValueError, IndexError) as exc:
        return {"error": str(exc)[:300]}


def threads_probe(s: Session, clip: Path, threads: str) -> str:
    """The estimation alone on the CPU with a pool of 1..N threads, with and without a file's
    lookahead (``python -m benchmarks estimators threads``): what every core gives once the decode is left out."""
    try:
        proc = s.run(sys.executable, "-m", "benchmarks", "estimators", "threads", str(clip), "--threads", threads,
                     "--rounds", "2", timeout=240, check=False)
        return (proc.stdout.strip() or proc.stderr.strip()[-300:])[-2000:]
    except subprocess.TimeoutExpired as exc:
        return f"timed out: {exc}"[:300]


def probes() -> dict:
    found = {}
    for name, cmd in (("lscpu", ["lscpu"]), ("nvidia-smi", ["nvidia-smi", "--query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm", "--format=csv"])):
        try:
            found[name] = subprocess.run(cmd, capture_output=True, text=True, timeout=30).stdout.strip()
        except (OSError, subprocess.TimeoutExpired) as exc:
            found[name] = f"not run: {exc}"
    return found


def footage(tiny: bool, key: str) -> Path | None:
    found = sorted(FOOTAGE.glob(f"{key}_*")) if FOOTAGE.is_dir() and not tiny else []
    return found[0] if found else None


def agreement(folder: Path, size: str, pair: tuple[str, str] = ("cuda", "cpu")) -> dict:
    """How far one device's outputs are from the other's (the GPU's from the CPU's): the tracks'
    corner differences (px, at the frame size, mean over the corners), the share of pairs that
    took the same path, the stabilised videos' and the panoramas' mean absolute grey difference.
    (The CPU rehearsal compares the CPU's with themselves: the code runs, the figures are zero.)"""
    from mosaic_cli.geometry import corner_error

    found: dict = {}
    try:
        tracks = [json.loads((folder / f"track_{size}_{d}.json").read_text()) for d in pair]
        diffs = corner_error(np.array(tracks[0]["pairwise"]), np.array(tracks[1]["pairwise"]), tuple(tracks[0]["size"]))
        same_path = float(np.mean([a == b for a, b in zip(tracks[0]["path"], tracks[1]["path"])]))
        found["track"] = {"corner_px_median": float(np.median(diffs)), "corner_px_p99": float(np.percentile(diffs, 99)),
                          "same_path": same_path}
    except Exception as exc:  # noqa: BLE001
        found["track"] = {"error": str(exc)[:200]}
    try:
        import av

        def grays(path: Path):
            with av.open(str(path)) as src:
                for frame in src.decode(video=0):
                    yield frame.to_ndarray(format="gray").astype(np.int16)

        a_b = [float(np.abs(a - b).mean()) for a, b in zip(grays(folder / f"stable_{size}_{pair[0]}.mp4"), grays(folder / f"stable_{size}_{pair[1]}.mp4"))]
        found["stabilize"] = {"mean_abs_grey": float(np.mean(a_b)) if a_b else None, "frames": len(a_b)}
    except Exception as exc:  # noqa: BLE001
        found["stabilize"] = {"error": str(exc)[:200]}
    try:
        a, b = (cv2.imread(str(folder / f"pano_{size}_{d}.png"), cv2.IMREAD_GRAYSCALE) for d in pair)
        found["stitch"] = ({"mean_abs_grey": float(np.abs(a.astype(np.int16) - b).mean()), "size": list(a.shape[::-1])}
                           if a.shape == b.shape else {"sizes": [list(a.shape[::-1]), list(b.shape[::-1])]})
    except Exception as exc:  # noqa: BLE001
        found["stitch"] = {"error": str(exc)[:200]}
    return found


def throughput(s: Session) -> str:
    """track, stabilize and stitch on the GPU and on every core, against the plain transcode, at
    720p and 4K: one JSON of wall times (issue 39's goals are ratios of these)."""
    p = s.plan
    folder = s.work / "throughput"
    folder.mkdir(exist_ok=True)
    report = {"machine": "", "commit": os.environ.get("MOSAIC_COMMIT", "unknown"), "runs": [], "probes": probes()}
    cpu_model = next((ln.split(":", 1)[1].strip() for ln in report["probes"]["lscpu"].splitlines() if ln.startswith("Model name")), "CPU")
    gpu = report["probes"]["nvidia-smi"].splitlines()[1:2] if p.device == "cuda" else []
    report["machine"] = f"{gpu[0] if gpu else 'no GPU'}; {os.cpu_count()} cores of {cpu_model}"
    out = s.out / "gpu_throughput.json"

    def save() -> None:  # after every run: what a run cut short by the time limit measured comes back
        out.write_text(json.dumps(report, indent=1))

    devices = ("cuda", "cpu") if p.device == "cuda" else ("cpu",)
    # A rehearsal times one tiny clip: the second size runs the same code again, 30 s of the suite.
    clips = CLIPS if not p.tiny else (("160x96", (160, 96), "720p"),)
    frames = 300 if not p.tiny else 16
    plans = []  # (size, the runs of that clip)
    for size, (w, h), key in clips:
        clip = folder / f"flight_{size}.mp4"
        still = footage(p.tiny, key)
        t0 = time.monotonic()
        s.run(*mosaic("simulate", *([str(still)] if still else []), "-p", "shaky", "-n", str(frames), "--size", f"{w}x{h}",
                      "--seed", "3", "--preset", "veryfast", "-o", str(clip), "-q"), timeout=600)
        s.say(f"rendered {clip.name} over {still.name if still else 'a procedural map'} in {time.monotonic() - t0:.1f} s")
        if key == "720p":
            report["nvdec"] = nvdec_probe(clip)
            for device in devices:
                report.setdefault("build", {})[device] = build_probe(s, device)
            report["threads"] = threads_probe(s, clip, f"1,4,{os.cpu_count() or 1}")
            save()
        runs: list[tuple] = [  # (command, device, threads, its arguments, the row's other fields)
            ("transcode", "cpu", None, (sys.executable, "-m", "benchmarks", "gpu", "--transcode", str(clip), str(folder / f"transcode_{size}.mp4")), {})]
        for device in devices:
            runs.append(("track", device, None, mosaic("track", str(clip), "-o", str(folder / f"track_{size}_{device}.json"), "--device", device), {}))
        for device in devices:  # what the overlay detection adds (the first session's "overlays" was 3-13 s)
            runs.append(("track", device, None, mosaic("track", str(clip), "-o", str(folder / f"trackO_{size}_{device}.json"), "--device", device,
                                                        "--no-overlay-detect"), {"options": "--no-overlay-detect"}))
        runs.append(("track", "cpu", 1, mosaic("track", str(clip), "-o", str(folder / f"track_{size}_cpu1.json"), "--device", "cpu", "--threads", "1"), {}))
        # On the session's device: what larger chunks give, and the polish one pair at a time
        # with OpenCV instead of batched in torch (the default on a GPU).
        for k, choice in enumerate(("lstm:chunk=64", "lstm:polish-with=opencv")):
            runs.append(("track", p.device, None, mosaic("track", str(clip), "-o", str(folder / f"trackE{k}_{size}_{p.device}.json"), "--device", p.device,
                                                         "-e", choice), {"options": f"-e {choice}"}))
        for device in devices:
            runs.append(("stabilize", device, None, mosaic("stabilize", str(clip), str(folder / f"stable_{size}_{device}.mp4"), "--device", device,
                                                          "--preset", X264["preset"], "--crf", X264["crf"]), {}))
        for device in devices:
            runs.append(("stitch", device, None, mosaic("stitch", str(clip), "-o", str(folder / f"pano_{size}_{device}.png"), "--device", device), {}))
        plans.append((size, runs))
    profiles: list[tuple[str, tuple[str, ...]]] = []  # (name, mosaic's arguments): profiled after round 1
    for size, runs in plans:
        for command, device, threads, args, extra in runs:
            if (command, device, threads, extra) in (("stabilize", p.device, None, {}), ("track", p.device, None, {})):
                profiles.append((f"{command}_{size}_{device}", args[3:]))  # (after python -m mosaic_cli)
    # Round 1 in order, round 2 (while time is left: its runs are repeats, skipped silently) in
    # reverse, so that a drifting machine weighs on every command alike; the medians are the figures.
    rounds = [(1, plans)] + ([] if p.tiny else [(2, [(size, runs[::-1]) for size, runs in plans[::-1]])])  # a rehearsal times once
    for round_, order in rounds:
        for size, runs in order:
            for command, device, threads, args, extra in runs:
                if s.left() < (30 if round_ == 1 else 90):
                    if round_ == 1:
                        report["runs"].append({"command": command, "device": device, "size": size, "threads": threads, "frames": frames,
                                               "wall_s": None, "note": "not run: the session's time ran out", **extra})
                    continue
                t0 = time.perf_counter()
                row = {"command": command, "device": device, "size": size, "threads": threads, "frames": frames, "round": round_, **extra}
                try:
                    proc = s.run(*args, timeout=max(30.0, min(300.0, s.left() - 20)), check=False)
                    wall = time.perf_counter() - t0
                    row["wall_s"] = round(wall, 3) if not proc.returncode else None
                    if command != "transcode" and not proc.returncode:
                        row["stages"] = stage_seconds(proc.stderr)
                    if proc.returncode:
                        row["note"] = f"exited {proc.returncode}: {proc.stderr.strip()[-300:]}"
                except subprocess.TimeoutExpired:
                    wall, row["wall_s"], row["note"] = time.perf_counter() - t0, None, "timed out"
                report["runs"].append(row)
                s.say(f"  {command} {device}{'' if threads is None else f' x{threads}'} {size}: "
                      f"{row.get('note') or f'{wall:.2f} s, {frames / wall:.0f} frames/s'}")
                save()
            if round_ == 1:
                report.setdefault("agreement", {})[size] = agreement(folder, size, ("cuda", "cpu") if "cuda" in devices else ("cpu", "cpu"))
                report["runs"].append({"command": "vidstab", "device": "cpu", "size": size, "threads": None, "frames": frames, "wall_s": None,
                                       "note": "not run: the machine has no ffmpeg binary, and PyAV's libavfilter has no vid.stab"})
                save()
        if round_ == 1:  # where each thread's time goes (python -m benchmarks profile), before the repeats
            for name, args in profiles:
                if s.left() < 120:
                    break
                text = s.work / f"profile_{name}.txt"
                proc = s.run(sys.executable, "-m", "benchmarks", "profile", "--top", "40", "--out", str(text), "--", *args,
                             timeout=max(30.0, min(200.0, s.left() - 60)), check=False)
                if text.is_file():
                    s.logs.append(text)
                s.say(f"  profiled {name}: {'ok' if text.is_file() else proc.stderr.strip()[-200:]}")
    done = [r for r in report["runs"] if r["wall_s"] is not None]
    return f"{len(done)} of {len(report['runs'])} runs timed into {out.name}"


PART_BYTES = 15 * 2**20  # the device tool returns files of at most 16 MB


def deliver(source: Path, target: Path, part_bytes: int = PART_BYTES) -> list[Path]:
    """``source`` copied to ``target``, or, when larger than ``part_bytes``, cut into
    ``target.part1``, ``target.part2``, ... that ``cat`` joins again."""
    if source.stat().st_size <= part_bytes:
        shutil.copy(source, target)
        return [target]
    parts = []
    with open(source, "rb") as f:
        while chunk := f.read(part_bytes):
            parts.append(target.with_name(f"{target.name}.part{len(parts) + 1}"))
            parts[-1].write_bytes(chunk)
    return parts


def pack(s: Session) -> str:
    with tarfile.open(s.out / "logs.tar.gz", "w:gz") as tar:
        for f in s.logs:
            if f.is_file():
                tar.add(f, arcname=f"{f.parent.name}-{f.name}" if f.parent != s.work else f.name)
    return f"{len(s.logs)} logs"


def main(argv: list[str] | None = None) -> int | None:
    ap = make_parser(SUITE, None, __doc__)
    ap.add_argument("--out", type=Path, default=Path(os.environ.get("OUT", "gpu-out")))
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--minutes", type=float, default=7.0, help="the whole session's budget")
    ap.add_argument("--tiny", action="store_true", help="tiny data, for a rehearsal on a CPU")
    ap.add_argument("--stages", choices=("training", "throughput", "all"), default="training",
                    help="training: data, tests, bench, speed, train; throughput: the timed commands; all: both")
    ap.add_argument("--transcode", nargs=2, metavar=("IN", "OUT"), help=argparse.SUPPRESS)  # the timed transcode's own process
    args = ap.parse_args(argv)
    if args.transcode:
        transcode(*args.transcode)
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    work = args.work or Path(os.environ.get("TMPDIR", "/tmp")) / f"mosaic-gpu-{os.getpid()}"
    work.mkdir(parents=True, exist_ok=True)
    s = Session(args.out, work, Plan.make(args.device, args.minutes, args.tiny))
    s.stage("env", lambda: environment(s))
    if args.stages in ("throughput", "all"):  # first: its figures are the ones only this machine gives
        s.stage("throughput", lambda: throughput(s))
    s.stage("tests", lambda: cuda_tests(s))  # the device's work against the CPU's, whichever stages run
    if args.stages in ("training", "all"):
        s.stage("data", lambda: make_data(s))
        s.stage("bench", lambda: bench(s))
        rates = s.stage("speed", lambda: speed(s))
        s.stage("train", lambda: train(s, rates if isinstance(rates, dict) else None))
    s.stage("pack", lambda: pack(s))
    width = max(len(r[0]) for r in s.rows)
    s.say("summary")
    for name, seconds, summary in s.rows:
        s.say(f"  {name:<{width}}  {seconds:>7} s  {summary}")
    failed = [r[0] for r in s.rows if r[2].startswith("FAILED")]
    return 1 if failed else 0
