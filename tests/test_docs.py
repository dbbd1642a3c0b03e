"""The README is a front door (issue 26): short, the two set-up commands first, and no link in
README.md, docs/ or models/README.md leads nowhere (files and, for Markdown files, anchors)."""

from __future__ import annotations

import functools
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
MAX_README_LINES = 200

FENCE = re.compile(r"^(```|~~~)")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")


def _prose_lines(text: str) -> list[str]:
    """The lines outside fenced code blocks, with inline code spans blanked."""
    lines, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line.lstrip()):
            fenced = not fenced
            continue
        if not fenced:
            lines.append(re.sub(r"`[^`]*`", "``", line))
    return lines


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link in a heading: its text
    text = text.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    anchors = set()
    fenced = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if FENCE.match(line.lstrip()):
            fenced = not fenced
            continue
        match = None if fenced else HEADING.match(line)
        if match:
            slug = _slug(match.group(2))
            count = seen.get(slug, 0)
            anchors.add(slug if count == 0 else f"{slug}-{count}")
            seen[slug] = count + 1
    return anchors


def _documents() -> list[Path]:
    return [README, ROOT / "models" / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _relative_links(path: Path) -> list[str]:
    links = []
    for line in _prose_lines(path.read_text(encoding="utf-8")):
        for target in LINK.findall(line):
            if not re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:
                links.append(target)
    return links


def test_readme_is_short():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines; at most {MAX_README_LINES}"


def test_readme_starts_with_exactly_two_setup_commands():
    text = README.read_text(encoding="utf-8")
    sections = re.split(r"^## ", text, flags=re.M)
    assert len(sections) > 1, "README.md has no ## section"
    setup = sections[1]
    assert setup.lower().startswith("set-up"), f"the first section of README.md is not the set-up: {setup.splitlines()[0]!r}"
    blocks = re.findall(r"^```[a-z]*\n(.*?)^```", setup, flags=re.M | re.S)
    assert len(blocks) == 2, f"the set-up section holds {len(blocks)} fenced blocks, not 2"
    commands = [block.strip() for block in blocks]
    for command in commands:
        assert "\n" not in command, f"a set-up block is not one command: {command!r}"
        assert command.startswith("python3 -m venv .venv && "), command
    assert "pip install -e . " in commands[0] and "mosaic stitch" in commands[0]
    # the main job makes a panorama worth looking at: a survey flight (several keyframes), as in
    # the README's picture and the maps guide, stitched from the video just simulated
    (simulate,) = [step for step in commands[0].split(" && ") if step.startswith("mosaic simulate ")]
    assert re.search(r"\s(-p|--profile)[ =]survey\b", simulate), simulate
    flight = re.search(r"\s(-o|--out)[ =](\S+)", simulate)
    assert flight and f"mosaic stitch {flight.group(2)} -o " in commands[0], commands[0]
    assert "pip install -e '.[test]'" in commands[1] and commands[1].endswith("python -m pytest -q -n auto")
    # No other fenced block comes before the set-up section.
    assert "```" not in sections[0]
    # CI runs that same test command (after lint and types).
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").replace(" --quiet", "")
    for step in commands[1].split(" && "):
        assert step in ci, f".ci/run does not run {step!r}"


@pytest.mark.parametrize("path", _documents(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path: Path):
    broken = []
    for target in _relative_links(path):
        file_part, _, anchor = target.partition("#")
        resolved = (path.parent / file_part).resolve() if file_part else path
        if not resolved.exists():
            broken.append(f"{target} (no such file)")
            continue
        if anchor and resolved.suffix == ".md" and anchor not in _anchors(resolved):
            broken.append(f"{target} (no heading #{anchor})")
    assert not broken, f"{path.relative_to(ROOT)}: broken links: {broken}"


# -- one install hint for each extra (issue 40) -------------------------------------------------

EXTRA_INSTALL = re.compile(r"pip install [^`\n]*?\[(\w+)\]'?")  # a pip install that names an extra


def _install_hints() -> dict[str, set[str]]:
    """Every ``pip install ... [extra]`` written in the package's messages and help, README.md and
    docs/, by extra; the set-up commands (README's, .ci/run's: installing the checkout itself with
    its tests) left out."""
    found: dict[str, set[str]] = {}
    texts = [p.read_text(encoding="utf-8") for p in (ROOT / "mosaic_cli").rglob("*.py")]
    texts += [p.read_text(encoding="utf-8") for p in [README, *sorted((ROOT / "docs").rglob("*.md"))]]
    for text in texts:
        for match in EXTRA_INSTALL.finditer(text):
            if match.group(1) != "test":
                found.setdefault(match.group(1), set()).add(match.group(0))
    return found


def test_every_extra_has_one_install_hint_everywhere():
    """The ``--plot`` error, the maps' error, the commands' help, the README and the guides name
    the same command for an extra: the one the messages print (``errors.install_hint``)."""
    from mosaic_cli.errors import GEO_EXTRA, install_hint
    from mosaic_cli.plots import INSTALL

    assert GEO_EXTRA.endswith(install_hint("geo")) and INSTALL == install_hint("plot")
    hints = _install_hints()
    assert hints.get("plot") == {install_hint("plot")} and hints.get("geo") == {install_hint("geo")}, hints
    readme = README.read_text(encoding="utf-8")
    assert install_hint("plot") in readme and install_hint("geo") in readme
    # the --plot help of track and stabilize, as typer shows it
    import typer.main

    from mosaic_cli.cli import app

    group = typer.main.get_command(app)
    for name in ("track", "stabilize"):
        (plot,) = [p for p in group.commands[name].params if p.name == "plot"]
        assert install_hint("plot") in rendered_help(name)
    # the finder sees another form, should one come back
    assert EXTRA_INSTALL.search("needs `pip install -e '.[plot]'` (matplotlib)").group(0) == "pip install -e '.[plot]'"


HELPED = ("track", "stitch", "stabilize", "simulate", "train", "bench", "eval")
HELP_MARK = "\n=== mosaic --help of: "


@functools.cache
def _helps() -> dict[str, str]:
    """``mosaic COMMAND --help`` of each command, written to a pipe as a user's terminal would
    show it (wide enough not to wrap), by one interpreter (one start-up for them all)."""
    code = ("import sys\nfrom mosaic_cli.cli import main\n"
            "for command in sys.argv[1:]:\n"
            f"    print({HELP_MARK!r} + command, flush=True)\n"
            "    try:\n        main([command, '--help'])\n    except SystemExit as exit_:\n"
            "        assert exit_.code in (0, None), (command, exit_.code)\n"
            "    sys.stdout.flush()\n")
    proc = subprocess.run([sys.executable, "-c", code, *HELPED], capture_output=True, text=True,
                          env={**os.environ, "COLUMNS": "1000", "NO_COLOR": "1"}, timeout=120)
    assert proc.returncode == 0, proc.stderr
    parts = [part.split("\n", 1) for part in proc.stdout.split(HELP_MARK)[1:]]
    assert [name for name, _ in parts] == list(HELPED)
    return dict(parts)


def rendered_help(command: str) -> str:
    """``mosaic COMMAND --help`` as a user's terminal shows it, one space for every run of spaces
    and box borders."""
    return re.sub(r"[\s│╭╮╰╯─]+", " ", _helps()[command])


@pytest.mark.parametrize("command", HELPED)
def test_the_help_shows_every_bracket_its_source_wrote(command):
    """typer renders help as rich markup, where ``[plot]`` is a style tag and vanishes: every
    word of an option's help that holds a bracket is shown with it."""
    import typer.main

    from mosaic_cli.cli import app

    shown = rendered_help(command)
    for param in typer.main.get_command(app).commands[command].params:
        text = (param.help or "").replace("\\[", "[")  # escaped with rich.markup.escape: shown as written
        for bracket in re.findall(r"\[[^\]]*\]", text):
            assert " ".join(bracket.split()) in shown, f"mosaic {command} {param.opts[0]}: {bracket!r} is not in the rendered help"
