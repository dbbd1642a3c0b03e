"""``mosaic train``: unsupervised training of the homography network on raw clips.

Read ``train`` top to bottom; it is the whole procedure:

    1. plan the run          fresh, or resumed from RUN_DIR/state.json (see mosaic_cli.train.run)
    2. decode the clips      once, into a memory-mapped frame cache (mosaic_cli.train.data)
    3. build the network     from scratch, from --init (fine-tune), or from the checkpoint
    4. the optimiser         Adam with the paper's step schedule (mosaic_cli.train.schedule)
    5. step                  windows -> objective -> backward -> Adam, logging every term
    6. checkpoint            every N steps, every few minutes, on Ctrl-C / SIGTERM, at the end
                             (the final weights also carry int8 activation ranges, model.quantize)
    7. validate              MACE on --val flights every N steps (mosaic_cli.train.validate)

Exact resume: sample ``i`` depends only on ``(seed, i)`` and step ``s`` uses samples
``s * batch * world ...``; dropout is re-seeded from ``(seed, step, rank)`` at every step;
the learning rate is a function of the step; Adam's moments and step counts are saved.  So a
run interrupted at step s and resumed computes the same steps s+1.. as one that never stopped.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import signal
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import nn

from mosaic_cli.atomic import check_writable
from mosaic_cli.errors import BadInput, Interrupted, MosaicError, ProcessingError
from mosaic_cli.model import quantize
from mosaic_cli.model.checkpoint import load_weights
from mosaic_cli.model.network import HomographyNet, NetConfig
from mosaic_cli.progress import console, progress_task
from mosaic_cli.train.config import RUN_DEFINING, TrainConfig
from mosaic_cli.train.data import (
    DeviceWindows,
    StepBatches,
    WindowDataset,
    build_frame_cache,
    discover_clips,
    make_loader,
    sample_pairs,
    to_model_input,
)
from mosaic_cli.train.distributed import Distributed
from mosaic_cli.train.objective import Objective
from mosaic_cli.train.run import (
    CsvLog,
    RunDir,
    load_checkpoint,
    restore_optimizer,
    save_checkpoint,
    save_final_weights,
)
from mosaic_cli.train.schedule import StepSchedule

CALIBRATION_PAIRS = 512  # training patch pairs that set the int8 activation ranges of the final weights
# --lstm-start cnn: the LSTM's input scale, as a multiple of the largest feature seen.  Larger
# keeps the cell nearer tanh's linear range (the start nearer the CNN), but the regressor must
# then amplify a smaller hidden state as much, and the optimiser's first steps on the LSTM's
# weights move it that much more: 2x starts within about a working px of the CNN.
LSTM_START_MARGIN = 2.0
MAX_SKIPPED_STEPS = 50  # consecutive non-finite losses before the run is declared diverged


@dataclass
class TrainSummary:
    run_dir: Path
    start_step: int
    steps: int
    samples_per_s: float  # over this session's steps, all processes together, first step excluded
    last_terms: dict
    val_mace: float | None
    weights: Path | None


# ----------------------------------------------------------------------------- 1. plan


def plan_run(clips: str, out: str, options: dict, resume: bool) -> TrainConfig:
    """The config of a fresh run (``options`` over the defaults) or of the run in ``out``
    (its saved config; ``options`` may only change what does not alter what is learnt)."""
    options = {k: v for k, v in options.items() if v is not None}
    if not resume:
        if RunDir(Path(out)).has_run():
            raise BadInput(f"{out} already holds a training run: pass --resume to continue it, or choose another --out")
        return TrainConfig(clips=str(clips), out=str(out), **options).resolved()
    saved = TrainConfig.from_dict(RunDir(Path(out)).read_state()["config"])
    for key in RUN_DEFINING:
        if key in options and _comparable(options[key]) != _comparable(getattr(saved, key)):
            raise BadInput(
                f"{out} was trained with {key.replace('_', '-')}={getattr(saved, key)!r}; a resumed run keeps it "
                f"(drop the option, or start a new run with another --out)"
            )
    changeable = {k: v for k, v in options.items() if k not in RUN_DEFINING}
    return replace(saved, clips=str(clips), out=str(out), **changeable).resolved()


def _comparable(value):
    return list(value) if isinstance(value, (tuple, list)) else value


# ----------------------------------------------------------------------------- the procedure


def train(cfg: TrainConfig, resume: bool = False, show_progress: bool = True) -> TrainSummary:
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    dist = Distributed.start(cfg.device)
    try:
        return _train(cfg, resume, dist, show_progress and dist.is_main)
    finally:
        dist.close()


def _train(cfg: TrainConfig, resume: bool, dist: Distributed, show_progress: bool) -> TrainSummary:
    # 1. plan: every input is checked before anything is written or decoded
    run = RunDir(Path(cfg.out))
    state = run.read_state() if resume else {"step": 0}
    start = int(state["step"])
    if start >= cfg.steps:
        raise BadInput(f"{run.root} has already run {start} steps; pass a larger --steps to continue it")
    clips = discover_clips(cfg.clips)
    objective = Objective(cfg.variant, patch=cfg.patch, photometric_space=cfg.photometric)
    flights = find_val_flights(cfg.val) if cfg.val else []
    init_net = load_init(cfg) if (cfg.init and not resume) else None
    prepare_run_dir(run)

    # 2. decode the clips (rank 0; the others then find every clip in the cache)
    failure, cached = None, []
    if dist.is_main:
        try:
            cached = decode_clips(clips, run, cfg, objective.window, fresh=not resume, show_progress=show_progress)
        except MosaicError as exc:
            failure = exc
    if dist.any_flag(failure is not None)[0]:
        raise failure or ProcessingError("rank 0 could not prepare the clips")
    if not dist.is_main:
        cached = decode_clips(clips, run, cfg, objective.window, fresh=False, show_progress=False)

    # 3. the network and 4. the optimiser
    dataset = WindowDataset(cached, objective.window, objective.positions, cfg.patch, cfg.seed, flip=cfg.flip, bursts=cfg.bursts)
    torch.manual_seed(cfg.seed)  # the same initial weights on every rank (DDP also broadcasts them)
    if resume:
        net, optimizer_tensors = load_checkpoint(run, state, dist.device)
    else:
        net = HomographyNet(NetConfig(preset=cfg.preset, head=objective.head, patch=cfg.patch)).to(dist.device)
        if init_net is not None:
            initialise_from(net, init_net, dataset if cfg.lstm_start == "cnn" else None, cfg.seed)
    trainable = set_trainable(net, cfg)
    # The parameters this run adds (a new head) get the run's learning rate; the frozen ones none.
    optimizer = torch.optim.Adam([{"params": trainable, "name": "trained"}], lr=cfg.lr)
    if resume:
        restore_optimizer(optimizer, optimizer_tensors, state["optimizer"])
    schedule = StepSchedule(cfg.lr, cfg.steps, cfg.lr_milestones, cfg.lr_decay)
    model, precision = wrap_for_device(net, dist, cfg.amp)
    scaler = torch.amp.GradScaler("cuda", enabled=precision == torch.float16)

    batches = step_batches(cfg, dataset, cached, objective, dist, start)
    log = CsvLog(run.log if dist.is_main else None, keep_until=start if resume else None)
    val_log = CsvLog(run.val_log if dist.is_main and flights else None, keep_until=start if resume else None)
    if show_progress:
        describe_run(cfg, dist, net, trainable, cached, schedule, start, precision)

    # 5. step, 6. checkpoint, 7. validate
    samples_per_step = cfg.batch_size * dist.world
    run_state = {"config": cfg.to_dict(), "schedule": schedule.describe(), "world": dist.world,
                 "samples_per_step": samples_per_step,
                 "rng": {"seed": cfg.seed, "scheme": "torch.manual_seed(seed * 1000003 + step * world + rank) each step"}}
    rate = RateMeter()
    terms: dict = {}
    val_mace = None
    step = start
    last_checkpoint = time.monotonic()
    skipped = 0
    started = time.monotonic()
    with contextlib.closing(log), contextlib.closing(val_log), StopRequests() as stop, progress_task(
        f"train {cfg.variant}", cfg.steps - start, unit="step/s", disable=not show_progress
    ) as advance:
        for step, batch in zip(range(start, cfg.steps), batches):
            lr = schedule.lr_at(step)
            for group in optimizer.param_groups:
                group["lr"] = lr
            torch.manual_seed(cfg.seed * 1000003 + step * dist.world + dist.rank)
            losses = compute_gradients(model, objective, optimizer, scaler, batch)
            # One wait for the device per step: every term and whether the total is finite, together.
            names = list(losses)
            values = torch.stack([losses[k].detach().float() for k in names]).tolist()
            # One collective per step: whether any process saw a non-finite loss, was asked to
            # stop, or is due a time-based checkpoint, so that all act on it together.
            now = time.monotonic()
            time_due = now - last_checkpoint > 60 * cfg.checkpoint_minutes
            out_of_time = cfg.max_minutes is not None and now - started > 60 * cfg.max_minutes
            diverged, stop_now, time_due, out_of_time = dist.any_flag(
                not math.isfinite(values[names.index("total")]), stop.requested, time_due, out_of_time
            )
            skipped = skipped + 1 if diverged else 0
            if skipped > MAX_SKIPPED_STEPS:
                raise ProcessingError(f"training diverged: {skipped} steps in a row gave a non-finite loss")
            if not diverged:  # else skip this update everywhere rather than poison the weights
                scaler.step(optimizer)
                scaler.update()

            done = step + 1
            terms = dict(zip(names, dist.mean(values)))
            samples_per_s = rate.tick(samples_per_step)
            log.write({"step": done, "lr": lr, **terms, "samples_per_s": samples_per_s, "skipped": int(diverged)})
            advance(1, status=status_line(terms, samples_per_s, done, cfg.steps))

            if out_of_time:  # --max-minutes: this is the last step; the final weights follow
                cfg = replace(cfg, steps=done)
            if stop_now or time_due or done % cfg.checkpoint_every == 0 or done == cfg.steps:
                if dist.is_main:
                    save_checkpoint(run, done, net, optimizer, run_state, cfg.variant, cfg.work_size)
                last_checkpoint = time.monotonic()
            if flights and (done % cfg.val_every == 0 or done == cfg.steps):
                if dist.is_main:
                    val_mace = validate_now(net, flights, dist.device, cfg)
                    val_log.write({"step": done, "mace": val_mace})
                    console.print(f"step {done}: validation MACE {val_mace:.2f} px (1280x720-equivalent)")
                dist.barrier()
            if stop_now:
                raise Interrupted(f"interrupted: checkpoint at step {done} in {run.root}; continue with --resume")
            if out_of_time:
                break

    if dist.is_main:
        save_final_weights(run, net, cfg.variant, cfg.steps, cfg.work_size, int8=calibrate_int8(net, dataset, cfg.seed))
    dist.barrier()
    return TrainSummary(run.root, start, cfg.steps, rate.mean(), terms, val_mace,
                        run.weights if dist.is_main else None)


# ----------------------------------------------------------------------------- stages


def step_batches(cfg: TrainConfig, dataset: WindowDataset, cached, objective: Objective, dist: Distributed, start: int):
    """The batches of steps ``start``.., on the training device: from loader processes building
    each window (``--data stream``), or cut from the frame cache held on the device
    (``--data device``, :class:`DeviceWindows`), whose patch positions need no check."""
    if cfg.data == "device":
        windows = DeviceWindows(cached, objective.window, objective.positions, cfg.patch, cfg.seed, dist.device,
                                flip=cfg.flip, bursts=cfg.bursts)
        objective.check_positions = False
        return (windows.batch(step, cfg.batch_size, dist.rank, dist.world) for step in range(start, cfg.steps))
    loader = make_loader(dataset, StepBatches(start, cfg.steps, cfg.batch_size, dist.rank, dist.world),
                         cfg.num_workers, pin_memory=dist.device.type == "cuda")
    return (to_model_input(batch, dist.device) for batch in loader)


def calibrate_int8(net: HomographyNet, dataset: WindowDataset, seed: int) -> dict | None:
    """Activation ranges for int8 CPU inference, measured on training patch pairs and shipped in
    the final weights (None where this PyTorch has no int8 engine)."""
    if quantize.engine() is None:
        return None
    return quantize.calibrate(net, sample_pairs(dataset, CALIBRATION_PAIRS, seed=seed))


def compute_gradients(model: nn.Module, objective: Objective, optimizer: torch.optim.Optimizer,
                      scaler: torch.amp.GradScaler, batch: dict) -> dict:
    """Every loss term of one batch, with the gradient of the total in the parameters (averaged
    over the processes by DDP during backward)."""
    model.train()
    optimizer.zero_grad(set_to_none=True)
    losses = objective(model, batch)
    scaler.scale(losses["total"]).backward()
    return losses


def prepare_run_dir(run: RunDir) -> None:
    if run.root.exists() and not run.root.is_dir():
        raise BadInput(f"--out {run.root} exists and is not a folder")
    try:
        run.root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BadInput(f"cannot create --out {run.root}: {exc.strerror}") from None
    check_writable(run.state)


def decode_clips(clips, run: RunDir, cfg: TrainConfig, window: int, fresh: bool, show_progress: bool):
    """The frame cache of every usable clip.  A fresh run that finds no usable clip leaves no
    run folder behind."""
    try:
        return build_frame_cache(clips, run.cache, cfg.work_size, window, cfg.cache_gb * 1e9,
                                 workers=cfg.num_workers, show_progress=show_progress)
    except MosaicError:
        if fresh:
            shutil.rmtree(run.cache, ignore_errors=True)
            with contextlib.suppress(OSError):
                run.root.rmdir()  # only if empty: never remove anything the user put there
        raise


def load_init(cfg: TrainConfig) -> HomographyNet:
    """The --init checkpoint, checked against the run before any long work."""
    path = Path(cfg.init)
    if not path.is_file():
        raise BadInput(f"--init {path}: no such file")
    try:
        net, _ = load_weights(path, device="cpu")
    except BadInput:
        raise
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's input
        raise BadInput(f"--init {path}: not a mosaic checkpoint ({exc.__class__.__name__})") from None
    if net.config.preset != cfg.preset or net.config.patch != cfg.patch:
        raise BadInput(
            f"--init {path} is a {net.config.preset} net on {net.config.patch}px patches; "
            f"this run is {cfg.preset} on {cfg.patch}px (pass --preset {net.config.preset})"
        )
    return net


def initialise_from(net: HomographyNet, source: HomographyNet, start_as_cnn: WindowDataset | None = None,
                    seed: int = 0) -> None:
    """Fine-tuning: everything from a net with the same head; backbone + first Linear otherwise
    (the paper's BASE -> LSTM).  With ``start_as_cnn`` (``--lstm-start cnn``), an LSTM from a CNN
    also starts as the CNN's head (:meth:`HomographyNet.start_as`), its features' scale taken as
    LSTM_START_MARGIN times the largest feature over pairs of that dataset."""
    if source.head == net.head:
        net.load_state_dict(source.state_dict())
    elif start_as_cnn is not None and net.head == "lstm":
        with torch.no_grad():
            largest = float(source.eval().features(sample_pairs(start_as_cnn, CALIBRATION_PAIRS, seed=seed)).max())
        net.start_as(source, LSTM_START_MARGIN * max(largest, 1e-3))
    else:
        net.load_features_from(source)


def set_trainable(net: HomographyNet, cfg: TrainConfig) -> list[nn.Parameter]:
    """The paper trains the LSTM variants with the backbone and first Linear of a trained
    BASE held fixed; ``--no-freeze`` (or no --init) trains everything."""
    frozen = set()
    if cfg.init and cfg.freeze and net.head == "lstm":
        frozen = {id(p) for p in net.feature_parameters()}
    for p in net.parameters():
        p.requires_grad_(id(p) not in frozen)
    return [p for p in net.parameters() if p.requires_grad]


class AutocastNet(nn.Module):
    """Runs only the network in reduced precision: the DLT solve and warps of the objective stay
    in float32, where the 8x8 solve is well conditioned."""

    def __init__(self, net: nn.Module, dtype: torch.dtype):
        super().__init__()
        self.net = net
        self.dtype = dtype

    def forward(self, patches, state=None):
        with torch.autocast("cuda", dtype=self.dtype):
            offsets, state = self.net(patches, state)
        if state is not None:
            state = tuple(s.float() for s in state)
        return offsets.float(), state


def wrap_for_device(net: HomographyNet, dist: Distributed, amp: bool) -> tuple[nn.Module, torch.dtype]:
    """DistributedDataParallel across processes; mixed precision (bf16 where the GPU has it,
    else fp16 with loss scaling) on CUDA."""
    model: nn.Module = net
    if dist.active:
        ids = [dist.device.index] if dist.device.type == "cuda" else None
        model = nn.parallel.DistributedDataParallel(net, device_ids=ids)
    precision = torch.float32
    if amp and dist.device.type == "cuda":
        precision = torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
        model = AutocastNet(model, precision)
    return model, precision


def find_val_flights(folder: str):
    from mosaic_cli.train.validate import find_flights

    return find_flights(folder)


def validate_now(net: HomographyNet, flights, device: torch.device, cfg: TrainConfig) -> float:
    from mosaic_cli.train.validate import validation_mace

    was_training = net.training
    try:
        return validation_mace(net, flights, device, cfg.work_size, cfg.variant)
    finally:
        net.train(was_training)


def describe_run(cfg, dist, net, trainable, cached, schedule, start, precision) -> None:
    n_all = sum(p.numel() for p in net.parameters())
    n_train = sum(p.numel() for p in trainable)
    frames = sum(c.frames for c in cached)
    where = f"{dist.world} processes on {dist.device.type}" if dist.active else str(dist.device)
    console.print(
        f"{cfg.variant} ({cfg.preset}): {n_train / 1e6:.2f}M of {n_all / 1e6:.2f}M parameters trained; "
        f"{len(cached)} clips, {frames} frames cached; batch {cfg.batch_size} x {dist.world}; "
        f"{schedule.describe()}; {where}, {str(precision).replace('torch.', '')}"
        + (f"; resuming at step {start}" if start else "")
    )


# The paper's names for the terms, to keep the progress line short.
SHORT_NAMES = {"photometric": "L", "spatial": "Rp", "scale": "Rs", "temporal1": "Rt1", "temporal2": "Rt2"}


def status_line(terms: dict, samples_per_s: float, done: int, steps: int) -> str:
    parts = [f"{SHORT_NAMES.get(k, k)} {v:.4g}" for k, v in terms.items() if k != "total"]
    if len(parts) > 1:
        parts.append(f"total {terms['total']:.4g}")
    return f"{' '.join(parts)} | {samples_per_s:.1f} samples/s"


class RateMeter:
    """Samples per second: recent (for the progress line) and over the session (for the summary,
    leaving out the first step, which pays for start-up)."""

    def __init__(self, window: int = 20):
        self.window = window
        self.times: list[float] = [time.perf_counter()]
        self.counts: list[int] = [0]

    def tick(self, samples: int) -> float:
        self.times.append(time.perf_counter())
        self.counts.append(self.counts[-1] + samples)
        if len(self.times) > 2 * self.window + 2:  # keep the first two stamps for mean()
            del self.times[2:3], self.counts[2:3]
        k = min(self.window, len(self.times) - 1)
        dt = self.times[-1] - self.times[-1 - k]
        return (self.counts[-1] - self.counts[-1 - k]) / dt if dt > 0 else 0.0

    def mean(self) -> float:
        if len(self.times) < 3:
            return 0.0
        return (self.counts[-1] - self.counts[1]) / (self.times[-1] - self.times[1])


class StopRequests:
    """Ctrl-C or SIGTERM asks the loop to stop at the end of the current step (after writing a
    checkpoint); a second Ctrl-C stops at once."""

    def __init__(self):
        self.requested = False
        self._previous = {}

    def _handle(self, signum, frame):
        if self.requested and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.requested = True
        console.print("[yellow]stopping after this step (Ctrl-C again to stop at once)[/]")

    def __enter__(self) -> StopRequests:
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._previous[sig] = signal.signal(sig, self._handle)
            except ValueError:  # not the main thread: leave signals alone
                pass
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
