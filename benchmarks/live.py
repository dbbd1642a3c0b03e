"""Benchmark live processing: a simulated flight served in real time over loopback TCP.

The bundled ffmpeg sends the flight as MPEG-TS at its frame rate (``-re``, H.264 as simulated,
x264 veryfast) to mosaic, which listens on 127.0.0.1.  Every figure is end to end on this
machine; say how loaded it was beside it.

    python -m benchmarks live track      [--estimator lstm] [--frames 600]
        lag of each JSON Lines pair (seen in the file) behind the frame's due arrival time
    python -m benchmarks live stitch     [--estimator lstm] [--frames 900] [--no-preview] [--hog N]
        scan lag of each frame behind the sender, backlog when the stream ends, preview cost,
        placement error of the final panorama
    python -m benchmarks live stabilize  [--estimator lstm] [--frames 600] [--clips 2] [--latency 1] [--hog N]
                                            [--model tilt,similarity] [--profile shaky-tilt]
        frames in / out / received, latency p50/p95/max from arrival off the decoder to the
        encoded frame's last UDP datagram received (and to the hand-over to the encoder), the
        time of each stage, residual jitter against the offline L1 path on the same frames
        (ground truth from simulate -p shaky), for each correction model (--model, comma-separated;
        default: the command's default), the models in turn on each clip
    --hog N runs N busy processes at the benchmark's priority during the run: a loaded machine
    python -m benchmarks live horizon    [--estimator lstm] [--frames 600] [--size 1280x720] [--seed 0]
        the online path over an offline track against the offline L1 path of that track, for
        several horizons and predicted tails (how the defaults were chosen)
    python -m benchmarks live stalls     [--estimator lstm] [--frames 600] [--clips 2] [--recover 0.15]
        the live schedule on a test clock over an offline track, with solves that stall now and
        then: residual jitter against the offline L1 path, frames settled at their deadline
    python -m benchmarks live listen     [--clips 5] [--cold]
        seconds from starting `mosaic track|stabilize|stitch tcp://...?listen=1` to its socket
        listening (a sender that connects sooner is refused), median and max of --clips starts;
        --cold empties the page cache before each start (root), as after a boot
    python -m benchmarks live memory     [--frames 54000]
        resident memory of live track and stabilize over a long stream (a 320x180 flight looped,
        sent as fast as mosaic takes it), sampled every second
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import imageio_ffmpeg
import numpy as np

from benchmarks.common import ROOT, make_parser, placement_errors
from mosaic_cli.estimators import make_estimator
from mosaic_cli.simulate import load_ground_truth

SUITE = "live"

FFMPEG = imageio_ffmpeg.get_ffmpeg_exe()
WORKDIR = ROOT / ".dev" / "bench_live"


def flight(profile: str, frames: int, size: str = "1280x720", seed: int = 0, fps: float = 30.0) -> Path:
    path = WORKDIR / (f"{profile}_{size}_{frames}_s{seed}" + (f"_{fps:g}fps" if fps != 30.0 else "") + ".mp4")
    if not path.exists():
        WORKDIR.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-m", "mosaic_cli", "simulate", "-o", str(path), "-p", profile, "-n", str(frames),
                        "--size", size, "--fps", f"{fps:g}", "--preset", "veryfast", "--seed", str(seed), "-q"], check=True)
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_listening(port: int, limit: float = 120.0, poll: float = 0.02) -> None:
    needle = f":{port:04X}"
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
            fields = line.split()
            if fields[1].upper().endswith(needle) and fields[3] == "0A":
                return
        time.sleep(poll)
    raise SystemExit(f"nothing listened on {port}")


class Sender:
    """ffmpeg -re serving ``video`` to ``url``; ``started`` and ``ended`` in time.monotonic()."""

    def __init__(self, video: Path, url: str):
        self.started = time.monotonic()
        self.proc = subprocess.Popen([FFMPEG, "-v", "error", "-re", "-readrate_initial_burst", "0", "-i", str(video), "-c", "copy", "-f", "mpegts", url])
        self.ended: float | None = None
        threading.Thread(target=self._wait, daemon=True).start()

    def _wait(self) -> None:
        self.proc.wait()
        self.ended = time.monotonic()


def load_note() -> str:
    return f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"


def percentiles(values) -> str:
    v = np.asarray(values, dtype=float)
    return f"p50 {np.percentile(v, 50):.2f} s, p95 {np.percentile(v, 95):.2f} s, max {v.max():.2f} s"


# -- track --------------------------------------------------------------------------------

def bench_track(args) -> dict:
    video = flight("paper", args.frames)
    port, out = free_port(), WORKDIR / "track.jsonl"
    out.unlink(missing_ok=True)
    proc = subprocess.Popen([sys.executable, "-m", "mosaic_cli", "track", f"tcp://127.0.0.1:{port}?listen=1", "-o", str(out),
                             "-e", args.estimator, "-q"])
    wait_listening(port)
    sender = Sender(video, f"tcp://127.0.0.1:{port}")
    seen: list[float] = []
    offset = 0
    while proc.poll() is None or (out.exists() and out.stat().st_size > offset):
        if out.exists():
            with open(out) as fh:
                fh.seek(offset)
                for line in fh:
                    if line.endswith("\n"):
                        seen.append(time.monotonic())
                        offset += len(line)
        time.sleep(0.01)
    fps = 30.0
    due = sender.started + (np.arange(len(seen)) + 2) / fps  # pair t is complete when frame t+1 has arrived
    lag = np.array(seen) - due
    row = {"estimator": args.estimator, "frames in": args.frames, "pairs out": len(seen), "lag": percentiles(lag),
           "lag first 10%": float(np.mean(lag[: len(lag) // 10])), "lag last 10%": float(np.mean(lag[-len(lag) // 10:])),
           "load": load_note()}
    print(f"track ({args.estimator}) 1280x720 30 fps over TCP: {args.frames} frames in, {len(seen)} pairs out; "
          f"lag behind the frame's due arrival {row['lag']} (first tenth {row['lag first 10%']:.2f} s, last tenth "
          f"{row['lag last 10%']:.2f} s); {row['load']}", flush=True)
    print(f"  reproduce: python -m benchmarks live track --estimator {args.estimator} --frames {args.frames}")
    return row


# -- stitch -------------------------------------------------------------------------------

def bench_stitch(args) -> dict:
    import mosaic_cli.stitch.live as live_stitch
    from mosaic_cli.stitch import StitchOptions
    from mosaic_cli.stitch.live import PreviewOptions, stitch_live

    video = flight("survey", args.frames)
    gt = load_ground_truth(video.with_suffix(".gt.json"))
    port = free_port()
    url = f"tcp://127.0.0.1:{port}?listen=1"
    result: dict = {}
    preview = None if args.no_preview else PreviewOptions(WORKDIR / "live_preview.png", args.every)

    # When the scan was done with each frame (its progress call), however stitch_live is built.
    scanned: list[float] = []
    scan_flight = live_stitch.scan_flight

    def timed_scan(frames, estimator, scanner, advance):
        def timed(n=1, status=None):
            scanned.extend([time.monotonic()] * n)
            advance(n, status=status)
        return scan_flight(frames, estimator, scanner, timed)

    live_stitch.scan_flight = timed_scan  # type: ignore[assignment]

    def run() -> None:
        estimator = make_estimator(args.estimator)
        result["r"] = stitch_live(url, WORKDIR / "live_pano.png", estimator, StitchOptions(),
                                  transforms=WORKDIR / "live_pano.json", preview=preview, show_progress=False)

    # Stitching runs in this process's main thread (it installs its stop handlers there); the
    # sender starts once the socket listens.
    def start_sender() -> None:
        wait_listening(port)
        result["sender"] = Sender(video, url.split("?")[0])

    threading.Thread(target=start_sender, daemon=True).start()
    loads = [os.getloadavg()[0]]
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.hog)]
    try:
        run()
        finished = time.monotonic()
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
    loads.append(os.getloadavg()[0])
    r, sender = result["r"], result["sender"]
    while sender.ended is None:
        time.sleep(0.05)
    # Lag of each frame: done by the scan, behind the time the sender was due to send it (-re
    # with no initial burst: frame k leaves at k / fps).
    lag = np.array(scanned) - (sender.started + (np.arange(len(scanned)) + 1) / 30.0)
    indices = [i for i, _ in r.transforms]
    errors = placement_errors(indices, [H for _, H in r.transforms], gt.map_to_frame, gt.size, 60)
    row = {"estimator": args.estimator, "frames in": args.frames, "frames scanned": r.frames, "keyframes": len(indices),
           "scan lag": percentiles(lag), "scan lag p95": float(np.percentile(lag, 95)),
           "scan backlog at stream end s": float(lag[-1]), "final stages s": finished - scanned[-1],
           "previews": r.previews, "preview s each": r.preview_seconds / max(r.previews, 1),
           "median placement error px": float(np.median(errors)) if len(errors) else None,
           "load during": f"{loads[0]:.1f} -> {loads[1]:.1f}", "hogs": args.hog, "load": load_note()}
    print(f"stitch --live ({args.estimator}) 1280x720 30 fps survey over TCP: {r.frames}/{args.frames} frames, "
          f"{len(indices)} keyframes; scan lag behind the sender {row['scan lag']}; scan done "
          f"{row['scan backlog at stream end s']:.2f} s after the last frame was due, final stages "
          f"{row['final stages s']:.1f} s; {r.previews} previews at {row['preview s each']:.3f} s each; "
          f"median placement error {row['median placement error px']:.2f} px over {len(errors)} pairs; load average "
          f"{row['load during']} (start -> end of the run) on {os.cpu_count()} cores", flush=True)
    print(f"  reproduce: python -m benchmarks live stitch --estimator {args.estimator} --frames {args.frames}"
          + (" --no-preview" if args.no_preview else f" --every {args.every:g}") + (f" --hog {args.hog}" if args.hog else ""))
    return row


# -- stabilize ----------------------------------------------------------------------------

def bench_stabilize(args) -> list[dict]:
    from mosaic_cli.live.stabilize import stabilize_live
    from mosaic_cli.stabilize import StabilizeOptions, stabilize
    from mosaic_cli.stabilize.metrics import ground_truth_jitter

    rows = []
    models = args.model.split(",") if args.model else [StabilizeOptions().model]
    for seed, model in ((seed, model) for seed in range(args.clips) for model in models):
        video = flight(args.profile, args.frames, size=args.size, seed=seed, fps=args.fps)
        gt = load_ground_truth(video.with_suffix(".gt.json"))
        options = StabilizeOptions(estimator=args.estimator, latency=args.latency, model=model, preset=args.preset)  # the offline run ignores the latency
        port, out_port = free_port(), free_port()
        url = f"tcp://127.0.0.1:{port}?listen=1"
        received, left = WORKDIR / "received.ts", WORKDIR / "received_times.npy"
        receiver = subprocess.Popen([sys.executable, "-m", "benchmarks", "live", "receive", "--port", str(out_port), "--ts", str(received),
                                     "--times", str(left)])
        holder: dict = {}
        threading.Thread(target=lambda port=port, holder=holder, video=video, url=url: (wait_listening(port), holder.update(s=Sender(video, url.split("?")[0]))),
                         daemon=True).start()
        loads = [os.getloadavg()[0]]
        # --hog N: N busy processes at mosaic's own priority for the whole run, a loaded machine
        # on demand (on top of whatever else runs).
        hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.hog)]
        try:
            live = stabilize_live(url, f"udp://127.0.0.1:{out_port}", options, show_progress=False)
        finally:
            for hog in hogs:
                hog.kill()
                hog.wait()
        loads.append(os.getloadavg()[0])
        receiver.wait()
        count = _count_frames(received)
        out_times = np.load(left)
        timeline = live.timeline
        arrived = timeline.times("arrived")
        n = min(len(arrived), len(out_times))
        leave = out_times[:n] - arrived[:n]
        offline = stabilize(video, WORKDIR / "offline.mp4", options, show_progress=False)
        shaky = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, gt.size, gt.fps)
        j_live = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, gt.size, gt.fps, live.warps)
        j_off = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, gt.size, gt.fps, offline.warps)
        row = {"clip": video.name, "estimator": args.estimator, "model": model, "frames in": live.frames_in, "frames out": live.frames_out,
               "frames received": count, "encoded frames timed": n, "latency to encoder": percentiles(live.latencies),
               "latency to encoded output": percentiles(leave), "latency p95": float(np.percentile(leave, 95)),
               "jitter input": shaky, "jitter live": j_live, "jitter offline": j_off, "ratio": j_live / j_off,
               "load during": f"{loads[0]:.1f} -> {loads[1]:.1f}", "hogs": args.hog, "breakdown": breakdown(live, out_times),
               "notes": live.notes, "late frames": np.flatnonzero(live.lateness).tolist(),
               "later than the bound": np.flatnonzero(leave > args.latency + 1.0 / gt.fps).tolist(), "load": load_note()}
        rows.append(row)
        print(f"stabilize --latency {args.latency:g} --model {model} ({args.estimator}) {video.name}: {live.frames_in} frames in, {live.frames_out} out, "
              f"{count} received over UDP; latency arrival -> encoded output received {row['latency to encoded output']} "
              f"(arrival -> hand-over to the encoder {row['latency to encoder']}); residual jitter live "
              f"{j_live:.3f} px, offline L1 {j_off:.3f} px (x{row['ratio']:.2f}), input {shaky:.3f} px; load average "
              f"{row['load during']} (start -> end of the live run) on {os.cpu_count()} cores", flush=True)
        for line in row["breakdown"] + [f"frames left at their deadline: {row['late frames']}"] + live.notes:
            print("   ", line)
    print(f"  reproduce: python -m benchmarks live stabilize --estimator {args.estimator} --frames {args.frames} "
          f"--clips {args.clips}" + (f" --latency {args.latency:g}" if args.latency != 1.0 else "")
          + (f" --hog {args.hog}" if args.hog else "") + (f" --model {args.model}" if args.model else "")
          + (f" --profile {args.profile}" if args.profile != "shaky" else "")
          + (f" --size {args.size}" if args.size != "1280x720" else "") + (f" --preset {args.preset}" if args.preset else "") + (f" --fps {args.fps:g}" if args.fps != 30.0 else ""))
    return rows


def breakdown(live, out_times: np.ndarray) -> list[str]:
    """Where the time went, stage by stage (p50 / p95 / max of each wait), and CPU per frame."""
    timeline = live.timeline
    lines = []
    stages = list(timeline.stages)
    times = {stage: timeline.times(stage) for stage in stages}
    times["encoded"] = out_times
    order = stages + ["encoded"]
    for first, then in zip(order, order[1:]):
        a, b = times[first], times[then]
        n = min(len(a), len(b))
        if n:
            w = 1000 * (b[:n] - a[:n])
            lines.append(f"{first:>9} -> {then:<9} p50 {np.percentile(w, 50):7.1f} ms  p95 {np.percentile(w, 95):7.1f} ms  "
                         f"max {w.max():7.1f} ms")
    lines.append(f"solves {live.solves} ({live.rejoined} joined to frames settled meanwhile, {live.stale} unused), frames "
                 f"settled at their deadline {live.late} ({live.held} past the plan's end), shortest lookahead "
                 f"{live.lookahead_min} of {live.horizon.lookahead}")
    frames = max(live.frames_in, 1)
    cpu = ", ".join(f"{job} {1000 * seconds / frames:.1f} ms" for job, seconds in timeline.cpu.items())
    lines.append(f"CPU a frame (this process's threads): {cpu}")
    for job, count in timeline.counts.items():
        if job.startswith("solve"):
            lines.append(f"{job}: {count} solves, {1000 * timeline.cpu[job] / max(count, 1):.1f} ms each")
    if timeline.gc_pauses:
        g = 1000 * np.array(timeline.gc_pauses)
        lines.append(f"GC: {len(g)} collections, p95 {np.percentile(g, 95):.1f} ms, max {g.max():.1f} ms")
    return lines


def bench_listen(args) -> list[dict]:
    """How soon each live command listens: a fresh process each time, polled every 10 ms."""
    rows = []
    for command in ("track", "stabilize", "stitch"):
        waits = []
        for _ in range(args.clips):
            port = free_port()
            url = f"tcp://127.0.0.1:{port}?listen=1"
            out = {"track": ["-o", str(WORKDIR / "listen.json")], "stabilize": [str(WORKDIR / "listen.mp4")],
                   "stitch": ["-o", str(WORKDIR / "listen.png")]}[command]
            if args.cold:
                drop_file_cache()
            start = time.monotonic()
            proc = subprocess.Popen([sys.executable, "-m", "mosaic_cli", command, url, *out, "-q"], stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL)
            try:
                wait_listening(port, limit=60.0, poll=0.01)
                waits.append(time.monotonic() - start)
            finally:
                proc.terminate()  # SIGTERM: mosaic stops its listening ffmpeg too (SIGKILL would leave it)
                try:
                    proc.wait(30)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        row = {"command": command, "median_s": float(np.median(waits)), "max_s": float(np.max(waits)), "starts": len(waits),
               "cold": args.cold, "load": load_note()}
        rows.append(row)
        print(f"mosaic {command} listens {row['median_s']:.2f} s after it starts{' cold' if args.cold else ''} "
              f"(median of {len(waits)}, max {row['max_s']:.2f} s); {row['load']}", flush=True)
    print(f"  reproduce: python -m benchmarks live listen --clips {args.clips}{' --cold' if args.cold else ''}")
    return rows


def drop_file_cache() -> None:
    """Empty the kernel's page cache (root only), so that the next start reads Python, torch and
    ffmpeg from the disk as the first run after a boot does."""
    os.sync()
    try:
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
    except OSError as exc:
        raise SystemExit(f"--cold needs to drop the page cache (root): {exc}") from None


def receive(args) -> None:
    """Receive MPEG-TS over UDP; save it, and the time.monotonic() at which each encoded video
    frame (one PES packet) had fully arrived: its last datagram."""
    import select

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 * 2**20)
    sock.bind(("127.0.0.1", args.port))
    times: list[float] = []
    started = False
    with open(args.ts, "wb") as out:
        while True:
            ready, _, _ = select.select([sock], [], [], 20.0 if not started else 5.0)
            if not ready:
                break
            data = sock.recv(65536)
            now = time.monotonic()
            started = True
            out.write(data)
            for i in range(0, len(data) - 187, 188):
                packet = data[i:i + 188]
                if packet[0] != 0x47:
                    continue
                start = bool(packet[1] & 0x40)
                adaptation = (packet[3] >> 4) & 3
                payload = 4 + (1 + packet[4] if adaptation & 2 else 0)
                video_start = start and packet[payload:payload + 3] == b"\x00\x00\x01" and 0xE0 <= packet[payload + 3] <= 0xEF
                pid = ((packet[1] & 0x1F) << 8) | packet[2]
                if video_start:
                    times.append(now)
                    video_pid = pid
                elif times and pid == video_pid:
                    times[-1] = now
    np.save(args.times, np.array(times))


def _count_frames(video: Path) -> int:
    run = subprocess.run([FFMPEG, "-hide_banner", "-i", str(video), "-map", "0:v:0", "-f", "null", "-"], capture_output=True)
    lines = [ln for ln in run.stderr.decode().replace("\r", "\n").splitlines() if ln.startswith("frame=")]
    return int(lines[-1].split("=")[1].split()[0]) if lines else 0


# -- memory -------------------------------------------------------------------------------

def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def bench_memory(args) -> list[dict]:
    clip = flight("shaky", 300, size="320x180")
    rows = []
    for name, command in (("track", ["track", "-", "-o", str(WORKDIR / "long.jsonl"), "-e", "orb", "-q"]),
                          ("stabilize --latency 1", ["stabilize", "-", str(WORKDIR / "long_steady.mp4"), "-e", "orb",
                                                     "--latency", "1", "-q"]),
                          ("stitch --live", ["stitch", "-", "-o", str(WORKDIR / "long_pano.png"), "--live", "-e", "orb",
                                             "-q"])):
        if args.only and not name.startswith(args.only):
            continue
        sender = subprocess.Popen([FFMPEG, "-v", "error", "-stream_loop", "-1", "-i", str(clip), "-frames:v", str(args.frames),
                                   "-c:v", "libx264", "-preset", "ultrafast", "-f", "mpegts", "pipe:1"],
                                  stdout=subprocess.PIPE)
        proc = subprocess.Popen([sys.executable, "-m", "mosaic_cli", *command], stdin=sender.stdout)
        sender.stdout.close()
        samples = []
        start = time.monotonic()
        while proc.poll() is None:
            value = rss_mb(proc.pid)
            if value is not None:
                samples.append((time.monotonic() - start, value))
            time.sleep(1.0)
        proc.wait()
        sender.wait()
        t, mb = np.array(samples).T
        n = len(mb)
        marks = {f"{int(100 * q)}%": float(mb[min(n - 1, int(q * n))]) for q in (0.1, 0.5, 0.99)}
        row = {"command": name, "frames": args.frames, "seconds": float(t[-1]), "rss MB": marks, "peak MB": float(mb.max()),
               "load": load_note()}
        rows.append(row)
        print(f"memory, live {name}, {args.frames} frames of 320x180 (= {args.frames / 30 / 60:.0f} min at 30 fps) in "
              f"{t[-1]:.0f} s: resident {marks['10%']:.0f} MB at 10% of the run, {marks['50%']:.0f} MB at 50%, "
              f"{marks['99%']:.0f} MB at the end, peak {mb.max():.0f} MB; {row['load']}", flush=True)
    print(f"  reproduce: python -m benchmarks live memory --frames {args.frames}")
    return rows


# -- horizon ------------------------------------------------------------------------------

def bench_horizon(args) -> list[dict]:
    """The online path over an offline track of a shaky flight, against the offline L1 path of
    the same track: residual jitter (ground truth) for several horizons and predicted tails."""
    from mosaic_cli.stabilize.crop import output_warps
    from mosaic_cli.stabilize.metrics import ground_truth_jitter
    from mosaic_cli.stabilize.online import Horizon, OnlineL1Path
    from mosaic_cli.stabilize.path import camera_motion, motion_model
    from mosaic_cli.stabilize.smoothing import L1Smoother
    from mosaic_cli.track import load_track

    video = flight("shaky", args.frames, size=args.size, seed=args.seed)
    track_file = video.with_suffix(f".{args.estimator}.json")
    if not track_file.exists():
        subprocess.run([sys.executable, "-m", "mosaic_cli", "track", str(video), "-o", str(track_file), "-e", args.estimator, "-q"],
                       check=True)
    track, gt = load_track(track_file), load_ground_truth(video.with_suffix(".gt.json"))
    size, model = gt.size, motion_model("similarity")

    def jitter(views: np.ndarray) -> float:
        return ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, size, gt.fps, output_warps(views, size))

    offline = jitter(L1Smoother().smooth(camera_motion(track.pairwise, size, model, track.confidence), size, model, None))
    rows = []
    # (step, lookahead, predicted, solver): how the defaults were chosen; the default with the
    # offline windows' interior point solver; then the shorter lookaheads a loaded machine
    # adapts to (docs/measurements/live.md), predicted frames kept at the horizon's.
    runs = [(9, 10, 0, "highs-ds"), (5, 14, 0, "highs-ds"), (5, 17, 0, "highs-ds"), (5, 17, 8, "highs-ds"),
            (5, 17, 17, "highs-ds"), (5, 17, 34, "highs-ds"), (5, 17, 17, "highs-ipm"),
            (5, 14, 17, "highs-ds"), (5, 11, 17, "highs-ds"), (5, 8, 17, "highs-ds"), (5, 4, 17, "highs-ds")]
    for step, lookahead, predicted, solver in runs:
        path = OnlineL1Path(model, size, None, Horizon(step, lookahead), L1Smoother(method=solver), predicted=predicted)
        path.push()
        views = []
        clock = time.process_time()
        for H, c in zip(track.pairwise, track.confidence):
            path.push(H, c)
            views.append(path.settle())
        views.append(path.settle(final=True))
        cpu_ms = 1000 * (time.process_time() - clock) / track.frames
        ratio = jitter(np.concatenate(views)) / offline
        rows.append({"step": step, "lookahead": lookahead, "predicted": predicted, "solver": solver, "ratio": ratio,
                     "cpu ms": cpu_ms})
        print(f"{video.name} ({args.estimator}): step {step}, lookahead {lookahead}, predicted {predicted}, {solver}: "
              f"jitter {ratio:.2f}x the offline L1 path's ({offline:.3f} px); {cpu_ms:.1f} ms CPU a frame", flush=True)
    print(f"  reproduce: python -m benchmarks live horizon --estimator {args.estimator} --frames {args.frames} "
          f"--size {args.size} --seed {args.seed}")
    return rows


# -- stalls -------------------------------------------------------------------------------

def bench_stalls(args) -> list[dict]:
    """The live schedule on a test clock over an offline track of a shaky flight, with solves
    that stall now and then: residual jitter against the offline L1 path of the same track.
    Frames arrive at 30 fps; the tracker answers 4 frames at a time 50 ms after the last; a
    solve takes 20 ms, or ``stall`` s with probability ``p``; the renderer takes each frame as
    soon as it is settled or due.  No thread and no real time: the same run every time."""
    import random

    from mosaic_cli.live.schedule import LiveSchedule
    from mosaic_cli.stabilize.crop import output_warps
    from mosaic_cli.stabilize.metrics import ground_truth_jitter
    from mosaic_cli.stabilize.online import Horizon, OnlineL1Path
    from mosaic_cli.stabilize.path import camera_motion, motion_model
    from mosaic_cli.stabilize.smoothing import L1Smoother
    from mosaic_cli.track import load_track

    rows = []
    for seed in range(args.clips):
        video = flight("shaky", args.frames, size=args.size, seed=seed)
        track_file = video.with_suffix(f".{args.estimator}.json")
        if not track_file.exists():
            subprocess.run([sys.executable, "-m", "mosaic_cli", "track", str(video), "-o", str(track_file), "-e",
                            args.estimator, "-q"], check=True)
        track, gt = load_track(track_file), load_ground_truth(video.with_suffix(".gt.json"))
        size, model, fps, n = gt.size, motion_model("similarity"), 30.0, track.frames
        offline = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, size, gt.fps, output_warps(
            L1Smoother().smooth(camera_motion(track.pairwise, size, model, track.confidence), size, model, None), size))
        for p, stall in ((0.0, 0.0), (0.03, 0.7), (0.15, 0.3), (0.15, 0.7), (0.05, 1.5)):
            clock = [0.0]
            path = OnlineL1Path(model, size, None, Horizon.for_latency(1.0, fps, 3), recover=args.recover)
            schedule = LiveSchedule(path, size, fps, 1.0, True, 10_000, clock=lambda clock=clock: clock[0])
            rng = random.Random(1)
            arrived = tracked = 0
            solving = None
            out = 0
            step = 1 / 600
            while out < n:
                now = clock[0]
                while arrived < n and arrived / fps <= now:
                    schedule.add_frame(np.zeros((1, 1), np.uint8), now)
                    arrived += 1
                while tracked < n:
                    last = min(n - 1, -(-tracked // 4) * 4)  # the chunk of 4 pairs this frame is in
                    if arrived <= last or now < last / fps + 0.05:
                        break
                    schedule.add_motion(*((None, 1.0) if tracked == 0 else (track.pairwise[tracked - 1],
                                                                           track.confidence[tracked - 1])))
                    tracked += 1
                if tracked == n and not schedule.tracked_all:
                    schedule.end_motion()
                if solving is None:
                    due = (schedule.tracked_all and path.settled < path.frames) or (
                        path.frames - path.settled >= path.horizon.step + schedule.lookahead())
                    if due:
                        job = schedule.next_window()
                        took = stall if rng.random() < p else 0.02
                        solving = (job, path.solve(job[0]), now + took, took)
                elif now >= solving[2]:
                    (window, final), params, _, took = solving
                    schedule.solved(window, params, final, took)
                    solving = None
                while schedule._frames and (schedule._frames[0].warp is not None
                                            or now >= schedule.deadline(schedule._frames[0])):
                    schedule.next_frame()
                    out += 1
                if schedule.tracked_all and solving is None and path.settled >= path.frames and schedule._frames:
                    schedule.next_frame()
                    out += 1
                clock[0] += step
            jitter = ground_truth_jitter(gt.map_to_frame, gt.smooth_map_to_frame, size, gt.fps, np.array(schedule.warps))
            row = {"clip": video.name, "stall probability": p, "stall s": stall, "ratio": jitter / offline,
                   "late": schedule.late, "past the plan": path.held, "joined": path.rejoined, "unused": schedule.stale}
            rows.append(row)
            print(f"{video.name} ({args.estimator}): solves stalling {stall:g} s with probability {p:g}: jitter "
                  f"{jitter / offline:.2f}x the offline L1 path's ({offline:.3f} px); {schedule.late} of {n} frames settled "
                  f"at their deadline ({path.held} past the plan's end); {path.rejoined} plans joined, {schedule.stale} "
                  f"unused", flush=True)
    print(f"  reproduce: python -m benchmarks live stalls --estimator {args.estimator} --frames {args.frames} "
          f"--clips {args.clips} --recover {args.recover:g}")
    return rows


def main(argv: list[str] | None = None) -> int | None:
    parser = make_parser(SUITE, None, __doc__)
    parser.add_argument("what", choices=["track", "stitch", "stabilize", "listen", "memory", "horizon", "stalls", "receive"])
    parser.add_argument("--recover", type=float, default=0.15, help="stalls: OnlineL1Path.recover")
    parser.add_argument("--latency", type=float, default=1.0, help="stabilize: --latency")
    parser.add_argument("--only", default=None, help="memory: only the command starting with this (track, stabilize, stitch)")
    parser.add_argument("--no-preview", action="store_true", help="stitch: no --preview")
    parser.add_argument("--every", type=float, default=2.0, help="stitch: seconds between previews")
    parser.add_argument("--hog", type=int, default=0, help="stabilize: busy processes at the same priority during the run")
    parser.add_argument("--port", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--ts", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--times", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--size", default="1280x720", help="horizon, stabilize: the flight's size")
    parser.add_argument("--fps", type=float, default=30.0, help="stabilize: the flight's frame rate")
    parser.add_argument("--preset", default=None, help="stabilize: x264's preset (default: the command's)")
    parser.add_argument("--seed", type=int, default=0, help="horizon: the flight's seed")
    parser.add_argument("--estimator", default="lstm")
    parser.add_argument("--model", default=None, help="stabilize: correction models, comma-separated (default: the command's)")
    parser.add_argument("--profile", default="shaky", help="stabilize: the simulated flight (shaky, shaky-tilt)")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--clips", type=int, default=2)
    parser.add_argument("--cold", action="store_true", help="listen: empty the page cache before each start (root)")
    parser.add_argument("--json", type=Path, default=None, help="Also write the rows here.")
    args = parser.parse_args(argv)
    if args.what == "receive":  # the stabilize benchmark's receiver, in a process of its own
        receive(args)
        return
    WORKDIR.mkdir(parents=True, exist_ok=True)
    defaults = {"track": 600, "stitch": 900, "stabilize": 600, "memory": 54000, "horizon": 600, "stalls": 600, "listen": 0}
    args.frames = args.frames or defaults[args.what]
    rows = {"track": bench_track, "stitch": bench_stitch, "stabilize": bench_stabilize, "memory": bench_memory,
            "horizon": bench_horizon, "stalls": bench_stalls, "listen": bench_listen}[args.what](args)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=str) + "\n")
