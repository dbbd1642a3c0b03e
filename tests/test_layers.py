"""The layers of docs/architecture.md.  The command line's rule: ``cli.py`` registers the commands; a
command imports neither ``mosaic_cli.cli`` nor another command, only the flags they share
(``commands/options.py``) and the library.  Checked on the source with ``ast``, so that an
import inside a function counts as much as one at the top.  The library's layers, top to bottom:
import-linter's contract in pyproject.toml (``lint-imports``), run here too."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import mosaic_cli.commands
from mosaic_cli.cli import COMMANDS, app

COMMANDS_DIR = Path(mosaic_cli.commands.__file__).parent
PACKAGE = "mosaic_cli.commands"
SHARED = {f"{PACKAGE}.options"}  # what every command may import from its own package


def imported_modules(source: str, module: str) -> set[str]:
    """Every module ``source`` (the text of ``module``) imports, with ``from PACKAGE import name``
    counted as the module ``PACKAGE.name`` (a command is imported that way too)."""
    package = module.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package up (level - 1) packages
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            found.add(base)
            found |= {f"{base}.{alias.name}" for alias in node.names}
    return found


def forbidden(source: str, module: str) -> set[str]:
    """The imports of ``module`` that break the rule."""
    names = imported_modules(source, module)
    cli = {n for n in names if n == "mosaic_cli.cli" or n.startswith("mosaic_cli.cli.")}
    commands = {n for n in names if n.startswith(f"{PACKAGE}.") and n not in SHARED and n != module
                and n.count(".") == PACKAGE.count(".") + 1}
    return cli | commands


def test_the_rule_catches_each_kind_of_forbidden_import():
    module = f"{PACKAGE}.stitch"
    assert forbidden("from mosaic_cli.cli import app", module) == {"mosaic_cli.cli", "mosaic_cli.cli.app"}
    assert forbidden("import mosaic_cli.cli", module) == {"mosaic_cli.cli"}
    assert forbidden("def f():\n    from mosaic_cli.commands.track import _median", module) == {f"{PACKAGE}.track"}
    assert forbidden("from mosaic_cli.commands import track", module) == {f"{PACKAGE}.track"}
    assert forbidden("from . import track", module) == {f"{PACKAGE}.track"}
    assert forbidden("from .track import track", module) == {f"{PACKAGE}.track"}
    allowed = "from mosaic_cli.commands.options import Device\nfrom .options import Mask\nfrom mosaic_cli.stitch import stitch"
    assert forbidden(allowed, module) == set()


@pytest.mark.parametrize("path", sorted(COMMANDS_DIR.glob("*.py")), ids=lambda p: p.name)
def test_a_command_imports_neither_the_cli_nor_another_command(path):
    module = f"{PACKAGE}.{path.stem}" if path.stem != "__init__" else PACKAGE
    assert forbidden(path.read_text(), module) == set()


def test_every_command_module_is_registered_once_under_its_name():
    """cli.py's table names one function of each command module, and typer lists those."""
    modules = {p.stem for p in COMMANDS_DIR.glob("*.py")} - {"__init__", "options"}
    registered = {function.__module__.rpartition(".")[2] for function in COMMANDS.values()}
    assert registered == modules
    assert [c.name for c in app.registered_commands] == list(COMMANDS)
    assert [c.callback for c in app.registered_commands] == list(COMMANDS.values())


# -- the library's layers (pyproject.toml's [tool.importlinter], checked by import-linter) --------

ROOT = Path(__file__).resolve().parents[1]


def importlinter_layers() -> list[str]:
    import tomllib

    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    (contract,) = [c for c in config["contracts"] if c["type"] == "layers"]
    return [name.strip() for layer in contract["layers"] for name in layer.replace(":", "|").split("|")]


def test_every_module_of_the_package_sits_in_a_layer():
    """A module the layers contract does not name would go unchecked: each top-level module and
    subpackage of mosaic_cli is in one layer (``__main__``, ``python -m mosaic_cli``, only calls
    the CLI)."""
    package = ROOT / "mosaic_cli"
    found = {f"mosaic_cli.{p.stem}" for p in package.glob("*.py")} | {f"mosaic_cli.{p.parent.name}" for p in package.glob("*/__init__.py")}
    layers = importlinter_layers()
    assert len(layers) == len(set(layers))
    assert found - {"mosaic_cli.__init__", "mosaic_cli.__main__"} == set(layers)


def test_the_layers_hold():
    """import-linter's contracts (every import, in a function or not, ``TYPE_CHECKING`` imports
    included), as ``.ci/run`` runs them with ``lint-imports``."""
    pytest.importorskip("importlinter")
    import os
    import subprocess
    import sys

    code = ("import sys; from importlinter.cli import lint_imports; "
            "sys.exit(lint_imports(config_filename='pyproject.toml', no_cache=True, no_logo=True))")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr


def cycle_in(edges: dict[str, set[str]]) -> list[str] | None:
    """One circle of ``edges`` (node -> the nodes it imports), as the list of nodes round it (the
    first repeated last); None if none."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        path.pop()
        state[node] = 2
        return None

    for node in sorted(edges):
        if node not in state and (found := visit(node)):
            return found
    return None


def top_level_cycle(graph) -> list[str] | None:
    """One circle of imports between mosaic_cli's top-level modules and subpackages (each import of
    a module inside one counted as the package's); None if none."""
    edges: dict[str, set[str]] = {}

    def top(module: str) -> str | None:
        parts = module.split(".")
        return ".".join(parts[:2]) if len(parts) > 1 else None

    for module in graph.modules:
        source = top(module)
        if source is None:
            continue
        for imported in graph.find_modules_directly_imported_by(module):
            target = top(imported)
            if target is not None and target != source:
                edges.setdefault(source, set()).add(target)
    return cycle_in(edges)


def module_cycle(graph) -> list[str] | None:
    """One circle of imports between any two modules (a package's ``__init__`` is one), inside a
    package too; None if none."""
    return cycle_in({m: set(graph.find_modules_directly_imported_by(m)) - {m} for m in graph.modules})


def test_the_cycle_finder_finds_a_circle():
    class Graph:
        modules = {"mosaic_cli", "mosaic_cli.inputs", "mosaic_cli.overlay.merge", "mosaic_cli.video.writer"}
        imports = {"mosaic_cli.inputs": {"mosaic_cli.overlay.merge"}, "mosaic_cli.overlay.merge": {"mosaic_cli.video.writer"},
                   "mosaic_cli.video.writer": {"mosaic_cli.inputs"}}

        def find_modules_directly_imported_by(self, module):
            return self.imports.get(module, set())

    found = top_level_cycle(Graph())
    assert found is not None and found[0] == found[-1]
    assert set(found) == {"mosaic_cli.inputs", "mosaic_cli.overlay", "mosaic_cli.video"}
    assert module_cycle(Graph()) == ["mosaic_cli.inputs", "mosaic_cli.overlay.merge", "mosaic_cli.video.writer", "mosaic_cli.inputs"]
    del Graph.imports["mosaic_cli.video.writer"]
    assert top_level_cycle(Graph()) is None and module_cycle(Graph()) is None


def test_the_module_cycle_finder_sees_a_circle_inside_one_package():
    """What top_level_cycle cannot see: two modules of one package that import each other (as
    stitch/pipeline.py and stitch/flights.py did, the first inside a function)."""

    class Graph:
        modules = {"mosaic_cli.stitch", "mosaic_cli.stitch.pipeline", "mosaic_cli.stitch.flights", "mosaic_cli.stitch.canvas"}
        imports = {"mosaic_cli.stitch.pipeline": {"mosaic_cli.stitch.flights", "mosaic_cli.stitch.canvas"},
                   "mosaic_cli.stitch.flights": {"mosaic_cli.stitch.pipeline"}}

        def find_modules_directly_imported_by(self, module):
            return self.imports.get(module, set())

    assert top_level_cycle(Graph()) is None
    assert module_cycle(Graph()) == ["mosaic_cli.stitch.flights", "mosaic_cli.stitch.pipeline", "mosaic_cli.stitch.flights"]
    Graph.imports["mosaic_cli.stitch.flights"] = {"mosaic_cli.stitch.canvas"}
    assert module_cycle(Graph()) is None


def test_no_import_circle_between_the_packages_type_checking_imports_included():
    """No circle of imports between mosaic_cli's modules and subpackages, not even through an import
    made only for the type checker (``inputs`` once imported ``overlay`` for a type, ``overlay``
    imports ``video``, and ``video.writer`` imported ``inputs.check_encoder``).  The layers contract
    counts ``TYPE_CHECKING`` imports too (``exclude_type_checking_imports = false``)."""
    grimp = pytest.importorskip("grimp")
    import tomllib

    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    assert config.get("exclude_type_checking_imports") is False
    graph = grimp.build_graph("mosaic_cli", exclude_type_checking_imports=False, cache_dir=None)
    assert top_level_cycle(graph) is None


def test_no_import_circle_between_any_two_modules():
    """No two modules import each other, directly or round a longer loop, inside one package too,
    an import in a function or for the type checker included: each module can be read knowing
    only those below it (stitch/pipeline.py and stitch/flights.py, telemetry/photos.py and
    telemetry/flight_log.py, estimators/__init__.py and estimators/learned.py once did)."""
    grimp = pytest.importorskip("grimp")
    graph = grimp.build_graph("mosaic_cli", exclude_type_checking_imports=False, cache_dir=None)
    assert module_cycle(graph) is None
