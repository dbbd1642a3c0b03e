"""Checkpoints: the network's weights in a safetensors file (no pickle), with JSON metadata that
says what net it is, so that ``--weights FILE`` alone rebuilds the right estimator.

Metadata keys (all strings, as safetensors wants):

    format     "mosaic-homography"         version   "1"
    config     NetConfig as JSON (preset, head, patch, dropout, backbone, embed, hidden)
    variant    one of network.VARIANTS
    work_size  "[320, 180]": the working frame the net was trained at
    direction  "t_to_t+1": offsets move patch corners from frame t to frame t+1
    extra      JSON of whatever the trainer adds (step, data, losses, ...)
    int8       optional: JSON of the activation ranges for int8 CPU inference (see quantize.py)
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from mosaic_cli.atomic import atomic_path
from mosaic_cli.errors import BadInput
from mosaic_cli.inputs import check_weights_file
from mosaic_cli.model.network import VARIANTS, HomographyNet, NetConfig

FORMAT = "mosaic-homography"
FORMAT_VERSION = 1
DEFAULT_WORK_SIZE = (320, 180)


def save_weights(
    path: str | Path,
    model: HomographyNet,
    config: NetConfig | None = None,
    variant: str = "base",
    extra: dict | None = None,
    work_size: tuple[int, int] = DEFAULT_WORK_SIZE,
    int8: dict | None = None,
) -> None:
    """Write ``model``'s weights (fp32, CPU) and metadata to ``path`` atomically; ``int8``: the
    calibrated activation ranges of :func:`mosaic_cli.model.quantize.calibrate`, if any."""
    config = config or model.config
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}")
    model = getattr(model, "module", model)  # unwrap DistributedDataParallel
    tensors = {k: v.detach().to("cpu", torch.float32).contiguous() for k, v in model.state_dict().items()}
    metadata = _metadata(config, variant, extra, work_size, int8)
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata=metadata)


def _tensors(path: str | Path) -> dict[str, torch.Tensor]:
    with safe_open(str(path), framework="pt") as fh:
        return {k: fh.get_tensor(k) for k in fh.keys()}


def _metadata(config: NetConfig, variant: str, extra: dict | None, work_size: tuple[int, int], int8: dict | None) -> dict:
    metadata = {
        "format": FORMAT,
        "version": str(FORMAT_VERSION),
        "config": config.to_json(),
        "variant": variant,
        "preset": config.preset,
        "head": config.head,
        "patch": str(config.patch),
        "work_size": json.dumps(list(work_size)),
        "direction": "t_to_t+1",
        "extra": json.dumps(extra or {}),
    }
    if int8 is not None:
        metadata["int8"] = json.dumps(int8)
    return metadata


def read_metadata(path: str | Path) -> dict:
    """The decoded metadata of a mosaic checkpoint; BadInput if it is not one."""
    p = check_weights_file(path)
    try:
        with safe_open(str(p), framework="pt") as fh:
            raw = fh.metadata() or {}
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise BadInput(f"{p}: not a safetensors checkpoint ({exc.__class__.__name__})") from None
    if raw.get("format") != FORMAT:
        raise BadInput(f"{p}: a safetensors file, but not a mosaic checkpoint (train one with mosaic train)")
    try:
        meta = {
            "version": int(raw["version"]),
            "config": json.loads(raw["config"]),
            "variant": raw["variant"],
            "work_size": tuple(json.loads(raw.get("work_size", "[320, 180]"))),
            "direction": raw.get("direction", "t_to_t+1"),
            "extra": json.loads(raw.get("extra", "{}")),
            "int8": json.loads(raw["int8"]) if "int8" in raw else None,
        }
    except (KeyError, ValueError, TypeError) as exc:
        raise BadInput(f"{p}: damaged mosaic checkpoint metadata ({exc})") from None
    if meta["version"] > FORMAT_VERSION:
        raise BadInput(f"{p}: checkpoint format {meta['version']} is newer than this mosaic understands")
    return meta


def load_weights(path: str | Path, device: str | torch.device = "cpu") -> tuple[HomographyNet, dict]:
    """Rebuild the saved net (eval mode, on ``device``) -> (model, meta); ``meta["config"]`` is the
    NetConfig.  BadInput for anything that is not a complete mosaic checkpoint."""
    meta = read_metadata(path)
    try:
        config = NetConfig.from_dict(meta["config"])
    except (ValueError, TypeError) as exc:
        raise BadInput(f"{path}: unusable network config in checkpoint ({exc})") from None
    model = HomographyNet(config)
    try:
        model.load_state_dict(_tensors(path), strict=True)
    except (SafetensorError, RuntimeError, OSError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else exc.__class__.__name__
        raise BadInput(f"{path}: weights do not match their config ({first})") from None
    meta["config"] = config
    return model.to(device).eval(), meta


__all__ = ["FORMAT", "FORMAT_VERSION", "DEFAULT_WORK_SIZE", "save_weights", "read_metadata", "load_weights"]
