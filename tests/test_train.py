"""``mosaic train``: data pipeline, schedule, learning, exact resume, DDP, fine-tuning, validation.

Every clip here is generated on the fly (a textured map seen by a panning camera), kept tiny
(64x48 working frames, 32 px patches) and trained with one thread so each test takes seconds.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from safetensors import safe_open
from torch.utils.data import default_collate

from conftest import textured_image, write_clip
from mosaic_cli.errors import BadInput
from mosaic_cli.model import HomographyNet, NetConfig, load_weights, quantize, read_metadata, save_weights
from mosaic_cli.train.config import TrainConfig
from mosaic_cli.train.data import (
    StepBatches,
    WindowDataset,
    build_frame_cache,
    discover_clips,
    fit_to_work_size,
    share_budget,
    to_model_input,
)
from mosaic_cli.train.loop import CALIBRATION_PAIRS, train
from mosaic_cli.train.objective import Objective
from mosaic_cli.train.schedule import StepSchedule

WORK = (64, 48)
PATCH = 32
SMALL = ["--work-size", "64x48", "--patch", "32", "--threads", "1", "-q"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def pan_frames(n: int, size=WORK, speed: float = 2.0, seed: int = 2, blur: float = 1.0) -> np.ndarray:
    """(n, h, w) gray frames of a camera panning over a texture by (speed, speed/2) px a frame."""
    tex = cv2.cvtColor(textured_image(600, 500, seed=seed), cv2.COLOR_RGB2GRAY)
    if blur:
        tex = cv2.GaussianBlur(tex, (0, 0), blur)
    out = []
    for t in range(n):
        M = np.array([[1, 0, 100 + speed * t], [0, 1, 100 + 0.5 * speed * t], [0, 0, 1.0]])
        out.append(cv2.warpPerspective(tex, M, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP))
    return np.array(out)


def write_png_folder(folder: Path, frames: np.ndarray) -> Path:
    folder.mkdir(parents=True)
    for k, f in enumerate(frames):
        cv2.imwrite(str(folder / f"frame_{k:04d}.png"), f)
    return folder


@pytest.fixture(scope="module")
def pan_clips(tmp_path_factory) -> Path:
    """A folder with one 60-frame panning mp4."""
    root = tmp_path_factory.mktemp("pan")
    write_clip(root / "pan.mp4", [cv2.cvtColor(f, cv2.COLOR_GRAY2RGB) for f in pan_frames(60)])
    return root


def run_cli(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mosaic_cli", *args], capture_output=True, text=True,
                          env=ENV, timeout=timeout)


def cli_in_process(capsys, *args: str) -> tuple[int, str]:
    """Run ``mosaic ARGS`` in this process: (exit code, stderr)."""
    from mosaic_cli.cli import main

    capsys.readouterr()
    try:
        main(list(args))
        code = 0
    except SystemExit as exc:
        code = exc.code or 0
    return code, capsys.readouterr().err


def read_log(run: Path) -> list[dict]:
    with open(run / "log.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def tensors(path: Path) -> dict[str, torch.Tensor]:
    with safe_open(str(path), framework="pt") as fh:
        return {k: fh.get_tensor(k) for k in fh.keys()}


# ----------------------------------------------------------------------------- schedule, config


def test_schedule_decays_at_the_papers_fractions_of_any_step_count():
    paper = StepSchedule(1e-3, 300_000)
    assert paper.milestone_steps == (100_000, 200_000)  # BASE: x0.1 every 100k of 300k
    assert StepSchedule(1e-3, 90_000).milestone_steps == (30_000, 60_000)  # fine-tunes: every 30k of 90k
    assert paper.lr_at(99_999) == pytest.approx(1e-3)
    assert paper.lr_at(100_000) == pytest.approx(1e-4)
    assert paper.lr_at(299_999) == pytest.approx(1e-5)
    short = StepSchedule(1e-3, 30)
    assert [short.lr_at(s) for s in (9, 10, 19, 20)] == pytest.approx([1e-3, 1e-4, 1e-4, 1e-5])


def test_config_takes_the_papers_batch_and_steps_per_variant():
    base = TrainConfig("c", "o").resolved()
    assert (base.batch_size, base.steps) == (64, 300_000)
    assert (TrainConfig("c", "o", variant="reg-all").resolved().batch_size, TrainConfig("c", "o", variant="reg-t").resolved().steps) == (32, 90_000)
    assert TrainConfig("c", "o", variant="lstm-reg-all").resolved().batch_size == 8
    with pytest.raises(BadInput, match="variant"):
        TrainConfig("c", "o", variant="nope").resolved()
    with pytest.raises(BadInput, match="patch"):
        TrainConfig("c", "o", work_size=(100, 60), patch=64).resolved()


# ----------------------------------------------------------------------------- data


def test_discover_clips_finds_videos_and_frame_folders(tmp_path, tiny_clip):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "one.mp4").write_bytes(tiny_clip.read_bytes())
    (tmp_path / "a" / "one.gt.json").write_text("{}")
    write_png_folder(tmp_path / "b" / "frames", pan_frames(3))
    (tmp_path / "notes.txt").write_text("x")
    found = discover_clips(tmp_path)
    assert found == [tmp_path / "a" / "one.mp4", tmp_path / "b" / "frames"]
    assert discover_clips(tmp_path / "b" / "frames") == [tmp_path / "b" / "frames"]
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(BadInput, match="no video files"):
        discover_clips(empty)
    with pytest.raises(BadInput, match="no such"):
        discover_clips(tmp_path / "missing")


def test_frame_cache_holds_the_exact_frames_and_windows_are_consecutive(tmp_path):
    frames = pan_frames(20)
    clip = write_png_folder(tmp_path / "clip", frames)  # lossless: the cache must equal the PNGs
    cached = build_frame_cache([clip], tmp_path / "cache", WORK, window=4, budget_bytes=1e9, workers=0,
                               show_progress=False)
    stored = np.load(cached[0].file, mmap_mode="r")
    np.testing.assert_array_equal(stored, frames)

    ds = WindowDataset(cached, window=4, positions=3, patch=PATCH, seed=7)
    reversed_count = 0
    for index in range(200):
        sample = ds[index]
        window = sample["frames"][:, 0].numpy()
        assert sample["frames"].shape == (4, 1, 48, 64) and sample["frames"].dtype == torch.uint8
        forward = [s for s in range(17) if np.array_equal(window, frames[s:s + 4])]
        backward = [s for s in range(17) if np.array_equal(window, frames[s:s + 4][::-1])]
        assert forward or backward, "a window must be 4 consecutive frames, forward or reversed"
        reversed_count += bool(backward) and not forward
        pos = sample["positions"].numpy()
        assert pos.shape == (3, 2)
        assert np.all(pos >= 0) and np.all(pos[:, 0] <= 64 - PATCH) and np.all(pos[:, 1] <= 48 - PATCH)
        torch.testing.assert_close(ds[index]["frames"], sample["frames"])  # a pure function of the index
    assert 60 < reversed_count < 140  # about half are time-reversed

    # A second build finds everything in the cache and decodes nothing.
    mtime = Path(cached[0].file).stat().st_mtime_ns
    again = build_frame_cache([clip], tmp_path / "cache", WORK, 4, 1e9, workers=0, show_progress=False)
    assert again == cached and Path(cached[0].file).stat().st_mtime_ns == mtime


def test_flip_mirrors_whole_windows_and_leaves_unflipped_runs_as_they_were(tmp_path):
    frames = pan_frames(20)
    clip = write_png_folder(tmp_path / "clip", frames)
    cached = build_frame_cache([clip], tmp_path / "cache", WORK, window=4, budget_bytes=1e9, workers=0,
                               show_progress=False)
    plain = WindowDataset(cached, window=4, positions=3, patch=PATCH, seed=7)
    flipped = WindowDataset(cached, window=4, positions=3, patch=PATCH, seed=7, flip=True)
    mirrors = {
        "none": lambda w: w, "left-right": lambda w: w[:, :, ::-1],
        "upside-down": lambda w: w[:, ::-1, :], "both": lambda w: w[:, ::-1, ::-1],
    }
    seen = dict.fromkeys(mirrors, 0)
    for index in range(200):
        a, b = plain[index], flipped[index]
        # The same window and patch positions: the flip is drawn after everything else.
        torch.testing.assert_close(a["positions"], b["positions"])
        window, mirrored = a["frames"][:, 0].numpy(), b["frames"][:, 0].numpy()
        found = [name for name, mirror in mirrors.items() if np.array_equal(mirrored, mirror(window))]
        assert found, "a flipped window must be the plain window mirrored as a whole"
        seen[found[0]] += 1
    assert all(20 < count < 80 for count in seen.values()), seen  # each about a quarter of the time


def test_frame_cache_stays_within_its_budget_with_segments_of_real_consecutive_frames(tmp_path):
    frames = pan_frames(300, speed=1.0)
    clip = write_png_folder(tmp_path / "long", frames)
    budget = 140 * WORK[0] * WORK[1]  # room for 140 of the 300 frames
    cached = build_frame_cache([clip], tmp_path / "cache", WORK, window=4, budget_bytes=budget, workers=0,
                               show_progress=False)
    entry = cached[0]
    stored = np.load(entry.file, mmap_mode="r")
    assert Path(entry.file).stat().st_size <= budget + 128
    assert 4 <= entry.frames <= 140 and len(entry.segments) >= 1
    for offset, length in entry.segments:
        seg = stored[offset:offset + length]
        starts = [s for s in range(300 - length + 1) if np.array_equal(seg[0], frames[s])]
        assert starts and np.array_equal(seg, frames[starts[0]:starts[0] + length])
    assert entry.segments[-1][0] + entry.segments[-1][1] == entry.frames


def test_budget_is_shared_out_by_water_filling():
    assert share_budget([10, 100, None], 90) == [10, 40, 40]
    assert share_budget([10, 20], 1000) == [10, 20]
    assert sum(share_budget([None, None, None], 100)) <= 100


def test_frames_of_another_aspect_are_scaled_to_cover_and_centre_cropped():
    frame = np.zeros((120, 120), np.uint8)
    frame[55:65, 55:65] = 255  # a square in the middle
    out = fit_to_work_size(frame, (64, 48))
    assert out.shape == (48, 64)
    ys, xs = np.nonzero(out > 127)
    # scale 64/120 keeps the square square and centred
    assert abs((xs.max() - xs.min()) - (ys.max() - ys.min())) <= 1
    assert abs(xs.mean() - 31.5) < 1 and abs(ys.mean() - 23.5) < 1


def test_step_batches_never_reuse_a_sample_across_steps_or_ranks():
    seen = []
    for rank in range(2):
        seen += [i for batch in StepBatches(3, 6, 4, rank, 2) for i in batch]
    assert len(seen) == len(set(seen)) == 2 * 3 * 4
    assert min(seen) == 3 * 2 * 4  # resuming at step 3 starts where step 3 started


@pytest.mark.slow
def test_an_unreadable_clip_is_skipped_and_no_usable_clip_is_a_clear_error(tmp_path, pan_clips, capsys):
    bad = tmp_path / "clips"
    bad.mkdir()
    (bad / "broken.mp4").write_bytes(b"not a video at all" * 100)
    (bad / "pan.mp4").write_bytes((pan_clips / "pan.mp4").read_bytes())
    code, err = cli_in_process(capsys, "train", str(bad), "-o", str(tmp_path / "run"), "--steps", "2",
                               "--batch-size", "2", "--num-workers", "0", *SMALL)
    assert code == 0, err
    assert "skipping" in err and "broken.mp4" in err
    assert (tmp_path / "run" / "weights.safetensors").is_file()

    (bad / "pan.mp4").unlink()
    code, err = cli_in_process(capsys, "train", str(bad), "-o", str(tmp_path / "run2"), "--steps", "2", *SMALL)
    assert code == 2
    assert err.strip().splitlines()[-1].startswith("mosaic: error: no usable clips")
    assert "Traceback" not in err
    assert not (tmp_path / "run2").exists()


@pytest.mark.skipif(quantize.engine() is None, reason="this PyTorch build has no int8 engine")
def test_calibrate_adds_int8_ranges_to_existing_weights_and_leaves_the_weights_as_they_were(tmp_path, pan_clips, capsys):
    weights = tmp_path / "w.safetensors"
    save_weights(weights, HomographyNet(NetConfig(head="cnn", patch=PATCH)).eval(), variant="base", work_size=WORK)
    before = tensors(weights)
    code, err = cli_in_process(capsys, "train", "--head-only", "--calibrate", str(weights), "-q")
    assert code == 2 and "has no int8 ranges" in err and err.count("\n") == 1
    code, err = cli_in_process(capsys, "train", str(pan_clips), "--calibrate", str(weights), "-q")
    assert code == 0, err
    ranges = read_metadata(weights)["int8"]
    assert ranges["pairs"] == CALIBRATION_PAIRS and ranges["activations"]
    assert all(lo < hi for lo, hi in ranges["activations"].values())
    after = tensors(weights)
    assert after.keys() == before.keys() and all(torch.equal(after[k], before[k]) for k in before)
    assert [p.name for p in tmp_path.iterdir()] == ["w.safetensors"]  # written in place (atomically: no part file left)


def test_bad_options_fail_before_any_work(tmp_path, pan_clips, capsys):
    cases = [
        (["train", str(tmp_path / "missing"), "-o", str(tmp_path / "r1")], "no such file"),
        (["train", str(pan_clips), "-o", str(tmp_path / "r2"), "--variant", "huge"], "unknown --variant"),
        (["train", str(pan_clips), "-o", str(tmp_path / "r3"), "--resume"], "no run to resume"),
        (["train", str(pan_clips), "-o", str(tmp_path / "r4"), "--init", str(tmp_path / "none.safetensors")], "--init"),
        (["train", str(pan_clips), "-o", str(tmp_path / "r5"), "--val", str(tmp_path / "noval")], "--val"),
    ]
    for args, message in cases:
        code, err = cli_in_process(capsys, *args)
        assert code == 2, (args, err)
        assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
        assert not Path(args[3]).exists(), f"{args[3]} left behind"


# ----------------------------------------------------------------------------- training


@pytest.mark.slow
def test_a_short_cpu_run_lowers_the_photometric_loss_clearly(tmp_path, pan_clips):
    cfg = TrainConfig(clips=str(pan_clips), out=str(tmp_path / "run"), steps=250, batch_size=8, work_size=WORK,
                      patch=PATCH, num_workers=0, threads=1, lr_milestones=(0.9,), seed=0).resolved()
    summary = train(cfg, show_progress=False)
    assert summary.weights.is_file() and summary.samples_per_s > 0

    # The same held-out windows before (the run's initial weights) and after training, no dropout.
    cached = build_frame_cache(discover_clips(pan_clips), tmp_path / "run" / "cache", WORK, 2, 8e9, workers=0,
                               show_progress=False)
    held_out = WindowDataset(cached, window=2, positions=1, patch=PATCH, seed=12345)
    batch = to_model_input(default_collate([held_out[i] for i in range(32)]), torch.device("cpu"))
    objective = Objective("base", patch=PATCH)
    torch.manual_seed(cfg.seed)
    before_net = HomographyNet(NetConfig(preset="compact", head="cnn", patch=PATCH)).eval()
    after_net, meta = load_weights(summary.weights)
    assert meta["variant"] == "base" and meta["extra"]["step"] == 250
    with torch.no_grad():
        before = objective(before_net, batch)["photometric"].item()
        after = objective(after_net, batch)["photometric"].item()
    assert after < 0.75 * before, (before, after)
    rows = read_log(tmp_path / "run")
    assert [int(r["step"]) for r in rows] == list(range(1, 251))
    assert {"lr", "photometric", "total", "samples_per_s"} <= set(rows[0])

    # The weights drive ``mosaic track`` and move it towards the true pan, (-2, -1) px a frame.
    from mosaic_cli.estimators import make_estimator
    from mosaic_cli.geometry import corner_error
    from mosaic_cli.track import track_video

    tracked = track_video(pan_clips / "pan.mp4", make_estimator("cnn", weights=str(summary.weights), device="cpu"),
                          show_progress=False)
    truth = np.array([[1, 0, -2.0], [0, 1, -1.0], [0, 0, 1]])
    assert tracked.pairwise.shape == (59, 3, 3)
    err = np.median(corner_error(tracked.pairwise, truth, WORK))
    print("track corner error", err, "identity", corner_error(np.eye(3), truth, WORK))
    assert err < 0.5 * corner_error(np.eye(3), truth, WORK)


@pytest.mark.slow
def test_resume_refuses_a_damaged_checkpoint_in_one_line(tmp_path, pan_clips, capsys):
    """A checkpoint cut short by a full disk, say (mosaic's own writes are atomic): --resume names
    the damaged file and says what to do, and writes nothing."""
    args = ["train", str(pan_clips), "--steps", "2", "--batch-size", "2", "--num-workers", "0", *SMALL, "-o", str(tmp_path / "run")]
    code, err = cli_in_process(capsys, *args)
    assert code == 0, err
    checkpoint = tmp_path / "run" / "checkpoint.safetensors"
    checkpoint.write_bytes(checkpoint.read_bytes()[:1000])
    before = sorted(p.name for p in (tmp_path / "run").iterdir())
    code, err = cli_in_process(capsys, *args[:-2], "--steps", "4", "-o", str(tmp_path / "run"), "--resume")
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert lines[0].startswith("mosaic: error: ") and "checkpoint.safetensors: damaged" in lines[0] and "--resume" in lines[0]
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == before


@pytest.mark.slow
def test_an_interrupted_run_resumes_at_its_step_and_matches_an_uninterrupted_one(tmp_path, pan_clips, capsys):
    args = ["train", str(pan_clips), "--steps", "40", "--batch-size", "8", "--num-workers", "1",
            "--checkpoint-every", "1000", *SMALL]
    code, err = cli_in_process(capsys, *args, "-o", str(tmp_path / "a"))
    assert code == 0, err

    run_b = tmp_path / "b"

    def press_ctrl_c_after_five_steps():
        deadline = time.time() + 120
        while time.time() < deadline:
            if (run_b / "log.csv").is_file() and len(read_log(run_b)) >= 5:
                os.kill(os.getpid(), signal.SIGINT)  # what Ctrl-C sends; handled in the main thread
                return
            time.sleep(0.005)

    presser = threading.Thread(target=press_ctrl_c_after_five_steps)
    presser.start()
    code, err = cli_in_process(capsys, *args, "-o", str(run_b))
    presser.join()
    assert code == 130, err
    assert "continue with --resume" in " ".join(err.split())
    assert err.strip().splitlines()[-1].startswith("mosaic: error: interrupted: checkpoint at step")
    stopped_at = json.loads((run_b / "state.json").read_text())["step"]
    assert 5 <= stopped_at < 40
    assert len(read_log(run_b)) == stopped_at
    assert not (run_b / "weights.safetensors").exists()

    code, err = cli_in_process(capsys, *args, "-o", str(run_b), "--resume")
    assert code == 0, err
    rows_a, rows_b = read_log(tmp_path / "a"), read_log(run_b)
    assert [int(r["step"]) for r in rows_b] == list(range(1, 41))  # the step count continued, no step twice
    for ra, rb in zip(rows_a, rows_b):
        assert float(rb["total"]) == pytest.approx(float(ra["total"]), rel=1e-5, abs=1e-6), ra["step"]
    final_a, final_b = tensors(tmp_path / "a" / "weights.safetensors"), tensors(run_b / "weights.safetensors")
    for name in final_a:
        torch.testing.assert_close(final_b[name], final_a[name], rtol=1e-5, atol=1e-6)

    # A resumed run keeps what defines it; a finished one needs a larger --steps.
    code, err = cli_in_process(capsys, *args, "-o", str(run_b), "--resume", "--batch-size", "4")
    assert code == 2 and "batch-size" in err
    code, err = cli_in_process(capsys, *args, "-o", str(run_b), "--resume")
    assert code == 2 and "already run 40 steps" in err
    code, err = cli_in_process(capsys, *args, "-o", str(run_b))
    assert code == 2 and "--resume" in err


@pytest.mark.slow
def test_a_two_process_cpu_ddp_run_completes(tmp_path, pan_clips):
    run = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "-m", "mosaic_cli",
           "train", str(pan_clips), "-o", str(run), "--variant", "reg-all", "--steps", "3", "--batch-size", "1",
           "--num-workers", "0", *SMALL]
    result = subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    state = json.loads((run / "state.json").read_text())
    assert state["world"] == 2 and state["step"] == 3
    rows = read_log(run)
    assert [int(r["step"]) for r in rows] == [1, 2, 3]
    assert all(np.isfinite(float(r[k])) for r in rows for k in ("photometric", "spatial", "scale", "temporal1", "temporal2"))
    net, meta = load_weights(run / "weights.safetensors")
    assert meta["variant"] == "reg-all"


def _ddp_half_batch(rank: int, world: int, port: int, batch: dict, out: str) -> None:
    import torch.distributed as dist

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=world)
    try:
        torch.manual_seed(5)
        net = HomographyNet(NetConfig(preset="compact", head="cnn", patch=PATCH)).eval()  # eval: no dropout
        ddp = torch.nn.parallel.DistributedDataParallel(net)
        half = {k: v[rank::world] for k, v in batch.items()}
        Objective("base", patch=PATCH)(ddp, half)["total"].backward()
        if rank == 0:
            torch.save({k: p.grad for k, p in net.named_parameters()}, out)
        dist.barrier()  # neither process leaves the group while the other still uses it (gloo aborts)
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
def test_two_process_ddp_gradients_equal_one_process_on_the_whole_batch(tmp_path):
    """Each of two gloo processes takes half of a batch; DistributedDataParallel averages their
    gradients, which must be the gradients of one process on the whole batch (the loss is a mean
    over the batch)."""
    import socket

    import torch.multiprocessing as mp

    frames = torch.from_numpy(pan_frames(8)).float() / 127.5 - 1.0
    batch = {"frames": torch.stack([frames[k:k + 2] for k in range(4)])[:, :, None],
             "positions": torch.tensor([[[4, 2]], [[10, 6]], [[20, 8]], [[30, 12]]])}
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    out = tmp_path / "grads.pt"
    mp.spawn(_ddp_half_batch, args=(2, port, batch, str(out)), nprocs=2, join=True)
    torch.manual_seed(5)
    net = HomographyNet(NetConfig(preset="compact", head="cnn", patch=PATCH)).eval()
    Objective("base", patch=PATCH)(net, batch)["total"].backward()
    averaged = torch.load(out)
    for name, p in net.named_parameters():
        torch.testing.assert_close(averaged[name], p.grad, rtol=1e-4, atol=1e-7)


@pytest.mark.slow
def test_lstm_fine_tuned_from_base_keeps_the_copied_backbone_frozen(tmp_path, pan_clips):
    def run(name: str, **options) -> dict[str, torch.Tensor]:
        cfg = TrainConfig(clips=str(pan_clips), out=str(tmp_path / name), steps=2, work_size=WORK, patch=PATCH,
                          num_workers=0, threads=1, **options).resolved()
        return tensors(train(cfg, show_progress=False).weights)

    base = run("base", batch_size=2)
    shared = [k for k in base if k.startswith(("backbone.", "embed."))]
    init = str(tmp_path / "base" / "weights.safetensors")
    frozen = run("lstm", variant="lstm", init=init, batch_size=1)
    assert shared and all(torch.equal(frozen[k], base[k]) for k in shared)
    torch.manual_seed(0)  # the run's seed: the LSTM and regressor weights it started from
    untrained = HomographyNet(NetConfig(preset="compact", head="lstm", patch=PATCH)).state_dict()
    assert any(not torch.equal(frozen[k], untrained[k]) for k in frozen if k.startswith(("lstm.", "regressor.")))
    everything = run("lstm_all", variant="lstm", init=init, batch_size=1, freeze=False)
    assert not all(torch.equal(everything[k], base[k]) for k in shared)
    model, meta = load_weights(tmp_path / "lstm" / "weights.safetensors")
    assert meta["variant"] == "lstm"
    if quantize.engine() is not None:  # the final weights carry int8 ranges that fit the net
        assert meta["int8"]["pairs"] == CALIBRATION_PAIRS
        assert quantize.quantized_features(model, meta["int8"]) is not None


def test_device_windows_cut_real_windows_and_draw_from_the_step_alone(tmp_path):
    """--data device: each window is consecutive frames of one clip (forward or reversed), the
    patches inside the frame, the same batch for the same (seed, step) and another for another
    step; in [-1, 1] as to_model_input gives them."""
    from mosaic_cli.train.data import DeviceWindows

    frames = pan_frames(30)
    clips = [write_png_folder(tmp_path / name, frames[k::2] if name == "b" else frames) for k, name in enumerate("ab")]
    cached = build_frame_cache(clips, tmp_path / "cache", WORK, window=4, budget_bytes=1e9, workers=0, show_progress=False)
    windows = DeviceWindows(cached, window=4, positions=2, patch=PATCH, seed=3, device=torch.device("cpu"), flip=False)
    stored = [np.load(c.file) for c in cached]
    batch = windows.batch(7, batch_size=16)
    assert batch["frames"].shape == (16, 4, 1, *WORK[::-1]) and batch["frames"].min() >= -1 and batch["frames"].max() <= 1
    reversed_seen = 0
    for window in ((batch["frames"][:, :, 0] + 1.0) * 127.5).round().to(torch.uint8).numpy():
        found = [(c, s, d) for c, clip in enumerate(stored) for d in (1, -1) for s in range(len(clip) - 3)
                 if np.array_equal(window, clip[s:s + 4][::d])]
        assert found, "every window is 4 consecutive frames of one clip"
        reversed_seen += found[0][2] == -1
    assert 0 < reversed_seen < 16
    pos = batch["positions"]
    assert pos.min() >= 0 and pos[..., 0].max() <= WORK[0] - PATCH and pos[..., 1].max() <= WORK[1] - PATCH
    again = windows.batch(7, batch_size=16)
    assert torch.equal(again["frames"], batch["frames"]) and torch.equal(again["positions"], batch["positions"])
    assert not torch.equal(windows.batch(8, batch_size=16)["positions"], batch["positions"])


# ----------------------------------------------------------------------------- bursts


def test_burst_windows_keep_the_clean_frames_and_spoil_only_what_the_network_reads(tmp_path):
    """--bursts: the same windows as a plain run (drawn last), the burst never on the first or last
    frame, about the asked share of windows; spoil() takes the detail out of exactly the coded
    frames and leaves the others as they were."""
    from mosaic_cli.train.bursts import BLUR, DARK, FLAT, GLARE, spoil

    clip = write_png_folder(tmp_path / "clip", pan_frames(40))
    cached = build_frame_cache([clip], tmp_path / "cache", WORK, window=8, budget_bytes=1e9, workers=0, show_progress=False)
    plain = WindowDataset(cached, window=8, positions=1, patch=PATCH, seed=3)
    bursty = WindowDataset(cached, window=8, positions=1, patch=PATCH, seed=3, bursts=0.5)
    hits = 0
    for index in range(200):
        a, b = plain[index], bursty[index]
        assert "burst" not in a
        torch.testing.assert_close(a["frames"], b["frames"])
        torch.testing.assert_close(a["positions"], b["positions"])
        code = b["burst"].numpy()
        hits += bool(code.any())
        assert code[0] == 0 and code[-1] == 0 and code.sum() == 0 or len(set(code[code > 0])) == 1
    assert 70 < hits < 130
    frames = torch.from_numpy(pan_frames(6)).float()[None, :, None] / 127.5 - 1.0  # (1, 6, 1, h, w)
    code = torch.tensor([[0, GLARE, BLUR, DARK, FLAT, 0]])
    level = torch.tensor([[0, 0.05, 60.0, 0.04, 0.04, 0]])
    angle = torch.tensor([[0, 0, 30.0, 0, 0, 0]])
    out = spoil(frames, code, level, angle)
    torch.testing.assert_close(out[:, [0, 5]], frames[:, [0, 5]])
    def detail(x):  # the ground's detail above the sensor noise spoil() adds: smoothed, then its spread
        smooth = torch.from_numpy(np.stack([cv2.GaussianBlur(f, (0, 0), 2.0) for f in x[0, :, 0].numpy()]))
        return smooth.flatten(1).std(dim=1)

    assert torch.all(detail(out)[[1, 3, 4]] < 0.2 * detail(frames)[[1, 3, 4]])  # glare, dark, flat
    assert not torch.allclose(out[0, 2], frames[0, 2], atol=0.05)  # the gust's blur
    assert out[0, 1].mean() > 0.8 and out[0, 3].mean() < -0.8  # white, black


def test_with_bursts_the_network_reads_spoilt_frames_and_the_loss_compares_clean_ones(tmp_path):
    """A zero-offset net gives the identity whatever it reads, so every loss term must be the same
    with and without the burst keys (the photometric terms compare the clean frames); the
    patches the network is given do change where the burst is."""
    from mosaic_cli.train.bursts import DARK

    net = HomographyNet(NetConfig(preset="compact", head="lstm", patch=PATCH))
    with torch.no_grad():
        net.regressor.weight.zero_()
        net.regressor.bias.zero_()
    seen = []
    net.features = (lambda f: (lambda x: (seen.append(x.detach().clone()), f(x))[1]))(net.features)
    frames = torch.from_numpy(pan_frames(16)).float()[None, :, None] / 127.5 - 1.0
    batch = {"frames": frames, "positions": torch.tensor([[[8, 4]]])}
    spoilt = {**batch, "burst": torch.zeros(1, 16, dtype=torch.long), "burst_level": torch.full((1, 16), 0.03),
              "burst_angle": torch.zeros(1, 16)}
    spoilt["burst"][0, 5:7] = DARK
    objective = Objective("lstm-reg-t", patch=PATCH)
    clean_terms, spoilt_terms = objective(net, batch), objective(net, spoilt)
    for name in clean_terms:
        torch.testing.assert_close(clean_terms[name], spoilt_terms[name])
    clean_in, spoilt_in = seen  # (T, 2, P, P): pair t reads frames t and t+1
    assert torch.equal(clean_in[:4], spoilt_in[:4]) and torch.equal(clean_in[7:], spoilt_in[7:])
    assert spoilt_in[5].abs().max() > 0 and spoilt_in[5].mean() < -0.9  # both frames of pair 5 dark


# ----------------------------------------------------------------------------- validation


@pytest.mark.slow
def test_validation_mace_of_a_zero_motion_net_is_the_identity_mace(tmp_path, pan_clips):
    from mosaic_cli.evaluate import landmarks_from_ground_truth, mace
    from mosaic_cli.simulate import SimulateOptions, simulate_flight
    from mosaic_cli.train.validate import find_flights, validation_mace

    gt = simulate_flight(tmp_path / "f.mp4", options=SimulateOptions(frames=40, size=(128, 96), preset="ultrafast"), show_progress=False)
    flights = find_flights(tmp_path)
    net = HomographyNet(NetConfig(preset="compact", head="lstm", patch=PATCH))
    with torch.no_grad():
        net.regressor.weight.zero_()
        net.regressor.bias.zero_()  # offsets 0: the identity for every pair
    got = validation_mace(net, flights, torch.device("cpu"), (128, 96))
    identity = mace(np.tile(np.eye(3), (gt.frames - 1, 1, 1)), landmarks_from_ground_truth(gt), gt.size)
    assert got == pytest.approx(identity, rel=1e-9)
    assert identity > 1.0  # the flight moves: a non-trivial number

    # During training: every --val-every steps and at the end, in val.csv.
    cfg = TrainConfig(clips=str(pan_clips), out=str(tmp_path / "run"), steps=3, batch_size=2, work_size=(128, 96),
                      patch=PATCH, num_workers=0, threads=1, val=str(tmp_path), val_every=2).resolved()
    summary = train(cfg, show_progress=False)
    rows = list(csv.DictReader(open(tmp_path / "run" / "val.csv")))
    assert [int(r["step"]) for r in rows] == [2, 3]
    assert float(rows[-1]["mace"]) == pytest.approx(summary.val_mace, rel=1e-6) and np.isfinite(summary.val_mace)


@pytest.mark.slow
def test_validation_scores_the_network_alone_never_the_classical_fallback(tmp_path):
    """A zero-motion net on a fast flight: the identity does not correlate with the moved ground,
    so an estimator with ORB as its fallback would replace most pairs by ORB's (far better)
    estimates; validation must score what the network said (val.csv would flatter it otherwise)."""
    from mosaic_cli.evaluate import landmarks_from_ground_truth, mace
    from mosaic_cli.simulate import SimulateOptions, simulate_flight
    from mosaic_cli.train.validate import find_flights, validation_mace

    gt = simulate_flight(tmp_path / "f.mp4", options=SimulateOptions(profile="fast", frames=40, size=(256, 144), preset="ultrafast"),
                         show_progress=False)
    flights = find_flights(tmp_path)
    net = HomographyNet(NetConfig(preset="compact", head="cnn", patch=PATCH))
    with torch.no_grad():
        net.regressor.weight.zero_()
        net.regressor.bias.zero_()
    got = validation_mace(net, flights, torch.device("cpu"), (256, 144))
    identity = mace(np.tile(np.eye(3), (gt.frames - 1, 1, 1)), landmarks_from_ground_truth(gt), gt.size)
    assert identity > 20.0  # the flight moves far: ORB in its place would score a few px
    assert got == pytest.approx(identity, rel=1e-9)


# ----------------------------------------------------------------------------- real imagery


@pytest.mark.slow
def test_trains_on_a_flight_rendered_from_real_aerial_imagery(tmp_path, shared_data):
    from mosaic_cli.simulate import SimulateOptions, simulate_flight

    still = shared_data / "aerial_stills" / "opencv_aero" / "aero1.jpg"
    if not still.is_file():
        pytest.skip(f"{still} is not present")
    clips = tmp_path / "clips"
    clips.mkdir()
    simulate_flight(clips / "aero.mp4", still, SimulateOptions(frames=24, size=(128, 72), preset="ultrafast"), show_progress=False)
    cfg = TrainConfig(clips=str(clips), out=str(tmp_path / "run"), steps=3, batch_size=2, work_size=(64, 36),
                      patch=PATCH, num_workers=1, threads=1).resolved()
    summary = train(cfg, show_progress=False)
    rows = read_log(tmp_path / "run")
    assert [int(r["step"]) for r in rows] == [1, 2, 3] and all(np.isfinite(float(r["total"])) for r in rows)
    assert load_weights(summary.weights)[1]["work_size"] == (64, 36)
