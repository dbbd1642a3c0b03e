"""Where the shipped weights of the learned estimators are found: the package data of an
installed mosaic, or the repository's models/ in a checkout."""

from __future__ import annotations

import importlib.resources
from pathlib import Path

from mosaic_cli.errors import BadInput

REPO_MODELS = Path(__file__).resolve().parents[2] / "models"


def default_weights(kind: str) -> Path:
    """The shipped weights for ``kind`` ("lstm" or "cnn"): ``<kind>.safetensors`` in the
    ``mosaic_cli.models`` package data, ``mosaic_cli/weights/``, or the repository's ``models/``."""
    name = f"{kind}.safetensors"
    candidates: list[Path] = []
    for package in ("mosaic_cli.models", "mosaic_cli.weights"):
        try:
            candidates.append(Path(str(importlib.resources.files(package) / name)))
        except (ModuleNotFoundError, TypeError):
            pass
    candidates += [Path(__file__).resolve().parents[1] / "weights" / name, REPO_MODELS / name]
    for path in candidates:
        if path.is_file():
            return path
    raise BadInput(f"no shipped weights for {kind!r} yet: pass --weights FILE (train one with mosaic train)")
