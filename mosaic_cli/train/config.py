"""Everything that defines a training run, with the paper's values as defaults.

A run's config is saved in ``RUN_DIR/state.json``; ``--resume`` reads it back, so the options
that shape the run (variant, preset, batch size, learning rate, seed, sizes) cannot change
half way.  Options left as ``None`` take the paper's value for the chosen variant.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace

from mosaic_cli.device import check_device
from mosaic_cli.errors import BadInput
from mosaic_cli.inputs import check_threads
from mosaic_cli.model.network import PRESETS as NET_PRESETS
from mosaic_cli.model.network import VARIANTS
from mosaic_cli.train.losses import PHOTOMETRIC_SPACES

PRESETS = tuple(NET_PRESETS)
DATA = ("stream", "device")  # windows built per sample by loader processes, or cut from the cache held on the device
LSTM_STARTS = ("random", "cnn")

# The paper trains BASE for 300k iterations at batch 64 and fine-tunes the REG-* variants
# (batch 32) and the LSTM variants (batch 8) from it for 90k iterations.
PAPER_STEPS = {"base": 300_000}
PAPER_FINETUNE_STEPS = 90_000
PAPER_BATCH = {"base": 64, "lstm": 8, "lstm-reg-t": 8, "lstm-reg-all": 8}
PAPER_REG_BATCH = 32

# Options that define what a run learns: a resumed run must keep them.
RUN_DEFINING = ("variant", "preset", "init", "freeze", "batch_size", "lr", "lr_decay", "lr_milestones", "seed",
                "work_size", "patch", "flip", "photometric", "lstm_start", "bursts", "data")


def paper_steps(variant: str) -> int:
    return PAPER_STEPS.get(variant, PAPER_FINETUNE_STEPS)


def paper_batch_size(variant: str) -> int:
    return PAPER_BATCH.get(variant, PAPER_REG_BATCH)


@dataclass
class TrainConfig:
    clips: str
    out: str
    variant: str = "base"
    preset: str = "compact"
    init: str | None = None  # a checkpoint to fine-tune from (the paper fine-tunes REG-* and LSTM from BASE)
    freeze: bool = True  # LSTM from a CNN checkpoint: keep the copied backbone + first Linear fixed
    steps: int | None = None  # None: the paper's count for the variant
    batch_size: int | None = None  # windows per step per process; None: the paper's for the variant
    lr: float = 1e-3
    lr_decay: float = 0.1
    lr_milestones: tuple[float, ...] = (1 / 3, 2 / 3)  # fractions of ``steps`` where lr *= lr_decay
    device: str = "auto"
    amp: bool = True  # mixed precision on CUDA (never on CPU)
    seed: int = 0
    val: str | None = None
    val_every: int = 1000
    checkpoint_every: int = 500
    checkpoint_minutes: float = 15.0  # also checkpoint when this long has passed (slow CPU runs)
    work_size: tuple[int, int] = (320, 180)
    patch: int = 128
    lstm_start: str = "random"  # an LSTM from a CNN --init: "random" head (the paper) or "cnn" (starts as the CNN's head)
    photometric: str = "gray"  # what the photometric terms compare: "gray" (the paper) or "band" (band-passed)
    flip: bool = False  # mirror windows left-right and/or upside down (off: runs saved before it resume unchanged)
    bursts: float = 0.0  # share of the windows with a burst of spoilt frames the network reads (train.bursts)
    data: str = "stream"  # "device": the frame cache held on the training device, batches cut there (train.data.DeviceWindows)
    num_workers: int = 1
    max_minutes: float | None = None  # stop (checkpoint and final weights) after this long, whatever --steps says
    threads: int | None = None  # torch CPU threads per process; None: torch's default (all cores)
    cache_gb: float = 8.0  # disk budget of the decoded-frame cache in RUN_DIR/cache
    extra: dict = field(default_factory=dict)  # free-form notes kept with the run

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Every value, by the flag that sets it (``steps`` and ``batch_size`` may still be None:
        the paper's, filled in by :meth:`resolved`)."""
        if self.variant not in VARIANTS:
            raise BadInput(f"unknown --variant {self.variant!r}: choose one of {', '.join(VARIANTS)}")
        if self.preset not in PRESETS:
            raise BadInput(f"unknown --preset {self.preset!r}: choose one of {', '.join(PRESETS)}")
        if self.lstm_start not in LSTM_STARTS:
            raise BadInput(f"unknown --lstm-start {self.lstm_start!r}: choose one of {', '.join(LSTM_STARTS)}")
        if self.photometric not in PHOTOMETRIC_SPACES:
            raise BadInput(f"unknown --photometric {self.photometric!r}: choose one of {', '.join(PHOTOMETRIC_SPACES)}")
        if self.data not in DATA:
            raise BadInput(f"unknown --data {self.data!r}: choose one of {', '.join(DATA)}")
        check_device(self.device)
        checks = [
            (self.steps is None or self.steps >= 1, f"--steps must be at least 1, got {self.steps}"),
            (self.batch_size is None or self.batch_size >= 1, f"--batch-size must be at least 1, got {self.batch_size}"),
            (self.lr > 0, f"--lr must be positive, got {self.lr}"),
            (0 < self.lr_decay <= 1, f"the learning-rate decay must be in (0, 1], got {self.lr_decay}"),
            (all(0 < m < 1 for m in self.lr_milestones), "learning-rate milestones must be fractions in (0, 1)"),
            (self.seed >= 0, f"--seed must be 0 or more, got {self.seed}"),
            (self.patch >= 16, f"--patch must be at least 16, got {self.patch}"),
            (min(self.work_size) >= self.patch,
             f"--work-size {self.work_size[0]}x{self.work_size[1]} is smaller than a {self.patch}px patch"),
            (self.num_workers >= 0, f"--num-workers must be 0 or more, got {self.num_workers}"),
            (self.checkpoint_every >= 1, f"--checkpoint-every must be at least 1, got {self.checkpoint_every}"),
            (self.val_every >= 1, f"--val-every must be at least 1, got {self.val_every}"),
            (self.checkpoint_minutes > 0, f"--checkpoint-minutes must be positive, got {self.checkpoint_minutes}"),
            (self.cache_gb > 0, f"--cache-gb must be positive, got {self.cache_gb}"),
            (self.max_minutes is None or self.max_minutes > 0, f"--max-minutes must be positive, got {self.max_minutes}"),
            (0 <= self.bursts <= 1, f"--bursts must be a share of the windows in [0, 1], got {self.bursts}"),
        ]
        for ok, message in checks:
            if not ok:
                raise BadInput(message)
        check_threads(self.threads)

    def resolved(self) -> TrainConfig:
        """A copy with the paper's defaults filled in for the variant."""
        return replace(
            self,
            steps=paper_steps(self.variant) if self.steps is None else int(self.steps),
            batch_size=paper_batch_size(self.variant) if self.batch_size is None else int(self.batch_size),
            work_size=tuple(int(v) for v in self.work_size),
            lr_milestones=tuple(float(m) for m in self.lr_milestones),
        )

    def to_dict(self) -> dict:
        data = asdict(self)
        data["work_size"] = list(self.work_size)
        data["lr_milestones"] = list(self.lr_milestones)
        return data

    @classmethod
    def from_dict(cls, data: dict) -> TrainConfig:
        known = {f.name for f in fields(cls)}
        values = {k: v for k, v in data.items() if k in known}
        if "work_size" in values:
            values["work_size"] = tuple(values["work_size"])
        if "lr_milestones" in values:
            values["lr_milestones"] = tuple(values["lr_milestones"])
        return cls(**values)
