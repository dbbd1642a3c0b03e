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


def test_the_lock_pins_every_dependency_within_its_declared_range():
    """constraints.txt (what the README's commands and CI install) pins one exact version of
    every package pyproject.toml asks for, its extras included, and each pin is inside the range
    pyproject.toml declares; every range has an upper bound (no untested major release)."""
    import tomllib

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    root = Path(__file__).resolve().parents[1]
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    pins = {}
    for line in (root / "constraints.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: {line!r} is not an exact pin"
            pins[canonicalize_name(name)] = version
    wanted = [Requirement(r) for r in project["dependencies"]]
    wanted += [Requirement(r) for extra in project["optional-dependencies"].values() for r in extra]
    for req in wanted:
        name = canonicalize_name(req.name)
        if name == "mosaic-cli":
            continue
        assert name in pins, f"{req.name} is not pinned in constraints.txt"
        assert req.specifier.contains(pins[name], prereleases=True), f"{req.name}=={pins[name]} is outside {req.specifier}"
        assert any(spec.operator in ("<", "==", "<=", "~=") for spec in req.specifier), f"{req} has no upper bound"
