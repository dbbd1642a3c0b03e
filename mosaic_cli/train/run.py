"""The run directory: everything a training run writes, and how it is read back to resume.

    RUN_DIR/checkpoint.safetensors  model weights at the last checkpoint (model.checkpoint format)
    RUN_DIR/optimizer.safetensors   the optimizer's tensors (Adam moments and step counts)
    RUN_DIR/state.json              step, config, schedule, RNG scheme, optimizer scalars; written
                                    last, so it names the step the two files above belong to
    RUN_DIR/log.csv                 one row per step: learning rate, every loss term, samples/s
    RUN_DIR/val.csv                 with --val: step, MACE (1280x720-equivalent px)
    RUN_DIR/weights.safetensors     the final weights (what ``mosaic track --weights`` takes)
    RUN_DIR/cache/                  decoded frames (see mosaic_cli.train.data)

Every file is written atomically (temporary file, then rename).  The step is also stored in
the metadata of both safetensors files, so a set torn by a crash between two renames is
detected on resume instead of silently mixing two steps.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from mosaic_cli.atomic import atomic_path, write_json
from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.model.checkpoint import load_weights, save_weights

STATE_FORMAT = 1


@dataclass(frozen=True)
class RunDir:
    root: Path

    @property
    def checkpoint(self) -> Path:
        return self.root / "checkpoint.safetensors"

    @property
    def optimizer(self) -> Path:
        return self.root / "optimizer.safetensors"

    @property
    def state(self) -> Path:
        return self.root / "state.json"

    @property
    def log(self) -> Path:
        return self.root / "log.csv"

    @property
    def val_log(self) -> Path:
        return self.root / "val.csv"

    @property
    def weights(self) -> Path:
        return self.root / "weights.safetensors"

    @property
    def cache(self) -> Path:
        return self.root / "cache"

    def has_run(self) -> bool:
        return self.state.is_file()

    def read_state(self) -> dict:
        try:
            state = json.loads(self.state.read_text())
        except FileNotFoundError:
            raise BadInput(f"{self.root}: no run to resume (no state.json)") from None
        except (OSError, ValueError) as exc:
            raise BadInput(f"{self.state}: unreadable ({exc.__class__.__name__})") from None
        if state.get("format") != STATE_FORMAT:
            raise BadInput(f"{self.state}: unknown state format {state.get('format')!r}")
        return state


# ----------------------------------------------------------------------------- checkpoints


def save_checkpoint(run: RunDir, step: int, net, optimizer: torch.optim.Optimizer, state: dict, variant: str,
                    work_size: tuple[int, int]) -> None:
    """Weights, then optimizer, then state.json (which makes the new set current)."""
    save_weights(run.checkpoint, net, net.config, variant, extra={"step": step}, work_size=work_size)
    tensors, scalars = _flatten_optimizer(optimizer)
    with atomic_path(run.optimizer) as tmp:
        save_file(tensors, str(tmp), metadata={"step": str(step)})
    write_json(run.state, {**state, "format": STATE_FORMAT, "step": step, "optimizer": scalars})


def load_checkpoint(run: RunDir, state: dict, device: torch.device):
    """(net, optimizer tensors) of the checkpoint that ``state`` names, after checking that
    the three files belong to the same step."""
    step = int(state["step"])
    for path in (run.checkpoint, run.optimizer):
        if not path.is_file():
            raise BadInput(f"{run.root}: {path.name} is missing; cannot resume")
        found = _metadata_step(path)
        if found is None:
            raise BadInput(f"{path}: damaged (not a readable mosaic checkpoint); cannot resume "
                           "(start again without --resume, or --init from a weights file)")
        if found != step:
            raise ProcessingError(
                f"{run.root}: {path.name} is from step {found} but state.json from step {step} "
                "(a checkpoint write was cut short); cannot resume exactly"
            )
    net, _ = load_weights(run.checkpoint, device="cpu")
    with safe_open(str(run.optimizer), framework="pt", device="cpu") as fh:
        tensors = {k: fh.get_tensor(k) for k in fh.keys()}
    return net.to(device), tensors


def restore_optimizer(optimizer: torch.optim.Optimizer, tensors: dict, scalars: dict) -> None:
    per_param: dict[int, dict] = {}
    for key, value in tensors.items():
        _, index, name = key.split(".", 2)
        per_param.setdefault(int(index), {})[name] = value
    for index, values in scalars.get("state", {}).items():
        per_param.setdefault(int(index), {}).update(values)
    optimizer.load_state_dict({"state": per_param, "param_groups": scalars["param_groups"]})


def _flatten_optimizer(optimizer: torch.optim.Optimizer) -> tuple[dict, dict]:
    """Tensors as ``state.<param index>.<name>`` for safetensors; everything else for JSON."""
    sd = optimizer.state_dict()
    tensors, other = {}, {}
    for index, values in sd["state"].items():
        for name, value in values.items():
            if torch.is_tensor(value):
                tensors[f"state.{index}.{name}"] = value.detach().to("cpu").contiguous()
            else:
                other.setdefault(str(index), {})[name] = value
    return tensors, {"param_groups": sd["param_groups"], "state": other}


def _metadata_step(path: Path) -> int | None:
    try:
        with safe_open(str(path), framework="pt", device="cpu") as fh:
            meta = fh.metadata() or {}
    except Exception:  # noqa: BLE001 - any unreadable file is simply "not from this step"
        return None
    for key in ("step", "extra"):
        value = meta.get(key)
        if value is None:
            continue
        try:
            parsed = json.loads(value)
        except ValueError:
            continue
        if isinstance(parsed, dict) and "step" in parsed:
            return int(parsed["step"])
        if isinstance(parsed, int):
            return parsed
    return None


# ----------------------------------------------------------------------------- CSV log


class CsvLog:
    """``log.csv``: one row per step.  On resume the rows after the checkpoint are dropped (those
    steps run again), so the log never holds a step twice."""

    def __init__(self, path: Path | None, keep_until: int | None):
        """``path`` None: a log that writes nothing (processes other than rank 0)."""
        self.path = path
        self.columns: list[str] | None = None
        self._fh = None
        if path is None or keep_until is None or not path.is_file():
            return
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
        kept = [r for r in rows if r.get("step") and int(r["step"]) <= keep_until]
        if rows:
            self.columns = list(rows[0].keys())
            with atomic_path(path) as tmp, open(tmp, "w", newline="") as out:
                writer = csv.DictWriter(out, self.columns)
                writer.writeheader()
                writer.writerows(kept)

    def write(self, row: dict) -> None:
        if self.path is None:
            return
        if self._fh is None:
            fresh = self.columns is None
            if fresh:
                self.columns = list(row.keys())
            self._fh = open(self.path, "w" if fresh else "a", newline="")
            self._writer = csv.DictWriter(self._fh, self.columns, extrasaction="ignore")
            if fresh:
                self._writer.writeheader()
        self._writer.writerow({k: _fmt(v) for k, v in row.items()})
        self._fh.flush()

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def _fmt(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.7g}"
    return str(value)


def save_final_weights(run: RunDir, net, variant: str, step: int, work_size: tuple[int, int],
                       int8: dict | None = None) -> None:
    save_weights(run.weights, net, net.config, variant, extra={"step": step}, work_size=work_size, int8=int8)
