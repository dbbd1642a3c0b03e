"""The wheel: the shipped weights and their model card are package data (read from models/, no
symlink), beside every package of mosaic_cli."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_wheel_holds_the_weights_the_model_card_and_every_package(tmp_path):
    pytest.importorskip("setuptools")
    # Built from a copy: setuptools leaves build/ beside the sources, whose stale files would
    # reach the next wheel built there.
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    shutil.copytree(ROOT / "mosaic_cli", source / "mosaic_cli", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(ROOT / "models", source / "models")
    out = tmp_path / "wheel"
    run = subprocess.run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation", "-q", "-w", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    (wheel,) = out.glob("mosaic_cli-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        for kind in ("cnn", "lstm"):
            assert z.read(f"mosaic_cli/weights/{kind}.safetensors") == (ROOT / "models" / f"{kind}.safetensors").read_bytes()
        assert z.read("mosaic_cli/weights/README.md") == (ROOT / "models" / "README.md").read_bytes()
    packages = {p.parent.relative_to(ROOT).as_posix() for p in (ROOT / "mosaic_cli").rglob("__init__.py")}
    modules = {p.relative_to(ROOT).as_posix() for p in (ROOT / "mosaic_cli").rglob("*.py") if "__pycache__" not in p.parts}
    assert {f"{p}/__init__.py" for p in packages} <= names
    assert modules <= names, sorted(modules - names)  # a new subpackage must join pyproject.toml's list
