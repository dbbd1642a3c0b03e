"""Small command-line behaviours: -q/--quiet is a flag everywhere (help shows no value for it),
--weights never silently replaces a named classical estimator, simulate makes its output
folder, and progress written to a file or pipe is one plain line per stage."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from mosaic_cli import progress
from mosaic_cli.cli import main

COMMANDS = ["track", "stitch", "stabilize", "simulate", "eval", "bench", "train"]


def run_cli(capsys, *args):
    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in args])
    code = exit_info.value.code
    captured = capsys.readouterr()
    return (0 if code is None else code), captured.out, captured.err


@pytest.mark.slow
@pytest.mark.parametrize("command", COMMANDS)
def test_quiet_is_a_flag_in_every_command(capsys, command):
    code, out, _ = run_cli(capsys, command, "--help")
    assert code == 0
    quiet = [line for line in out.splitlines() if "--quiet" in line]
    assert quiet and "-q" in quiet[0]
    assert "<bool>" not in out  # no flag reads as if it took a value (-q true)
    code, _, err = run_cli(capsys, command, "-q", "true")
    assert code == 2 and err.startswith("mosaic: error: ")


@pytest.mark.parametrize("command", COMMANDS)
def test_each_commands_description_reads_as_its_docstring_says_it(command):
    """On a terminal wide enough (4000 columns), each paragraph of a command's docstring is one line of its
    ``--help``, words and brackets kept (``pairwise[t]``): not the docstring's own line ends
    (which broke its lines mid-sentence at 80 columns) nor rich's markup eating ``[t]``."""
    import inspect

    from mosaic_cli.cli import COMMANDS as FUNCTIONS

    run = subprocess.run([sys.executable, "-m", "mosaic_cli", command, "--help"], capture_output=True, text=True,
                         env={"COLUMNS": "4000", "PATH": "/usr/bin:/bin", "PYTHONPATH": ":".join(sys.path), "TERM": "dumb"})
    assert run.returncode == 0, run.stderr
    shown = [line.strip() for line in run.stdout.splitlines()]
    for paragraph in inspect.cleandoc(FUNCTIONS[command].__doc__).split("\n\n"):
        assert " ".join(paragraph.split()) in shown, paragraph


@pytest.mark.parametrize("name", ["orb", "orb-ransac", "orb-paper", "identity"])
def test_weights_with_a_classical_estimator_is_one_line_error(tmp_path, capsys, tiny_clip, name):
    weights = tmp_path / "w.safetensors"
    weights.write_bytes(b"not read: the combination is refused first")
    out = tmp_path / "t.json"
    code, _, err = run_cli(capsys, "track", tiny_clip, "-o", out, "-e", name, "--weights", weights, "-q")
    assert code == 2 and err.count("\n") == 1, err
    assert f"-e {name} takes no weights" in err and not out.exists()


@pytest.mark.slow
def test_simulate_makes_the_output_folder(tmp_path, capsys):
    out = tmp_path / "flights" / "day 1" / "f.mp4"
    code, _, err = run_cli(capsys, "simulate", "-o", out, "-n", "3", "--size", "64x48", "--preset", "ultrafast", "-q")
    assert code == 0, err
    assert out.exists() and (out.parent / "f.gt.json").exists()
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, _, err = run_cli(capsys, "simulate", "-o", blocker / "f.mp4", "-n", "3", "--size", "64x48", "-q")
    assert code == 2 and err.count("\n") == 1 and "is a file" in err


@pytest.mark.slow
def test_progress_to_a_pipe_is_one_line_per_stage(tmp_path, tiny_clip):
    """A child whose stderr is a pipe: no bars, no wrapped lines, one line a stage."""
    out = tmp_path / "t.json"
    run = subprocess.run([sys.executable, "-m", "mosaic_cli", "track", str(tiny_clip), "-o", str(out), "-e", "orb"],
                         capture_output=True, text=True, env={"COLUMNS": "40", "PATH": "/usr/bin:/bin",
                                                              "PYTHONPATH": ":".join(sys.path)})
    assert run.returncode == 0, run.stderr
    lines = run.stderr.strip().splitlines()
    frames = json.loads(out.read_text())["frames"]
    assert lines[0].startswith("overlays: ") and lines[0].endswith("% masked")  # the detection stage
    assert lines[1].startswith(f"track (orb): {frames}/{frames} in ") and lines[1].endswith("fr/s)")
    assert len(lines) == 3 and lines[2].startswith(f"{frames} frames, ")  # the stages, then the summary, each whole
    assert not any(mark in run.stderr for mark in "━╸\r")


@pytest.mark.slow
def test_stitch_progress_counts_the_summarys_keyframes_and_shows_no_empty_stage(tmp_path, tiny_clip):
    """The scan's count includes the last keyframe (added as the scan ends), and a loop search
    with no pair to try writes no line."""
    run = subprocess.run([sys.executable, "-m", "mosaic_cli", "stitch", str(tiny_clip), "-o", str(tmp_path / "p.png"), "-e", "orb"],
                         capture_output=True, text=True, env={"PATH": "/usr/bin:/bin", "PYTHONPATH": ":".join(sys.path)})
    assert run.returncode == 0, run.stderr
    lines = run.stderr.strip().splitlines()
    keyframes = int(next(line for line in lines if " frames -> " in line).split(" -> ")[1].split()[0])
    assert keyframes >= 2  # the last one is added after the last frame is scanned
    assert next(line for line in lines if line.startswith("scan (orb): ")).endswith(f"; {keyframes} keyframes"), lines
    assert not any(": 0/0 in " in line for line in lines), lines


def test_line_progress_writes_at_the_end_and_every_interval(monkeypatch):
    written = []
    monkeypatch.setattr(progress.LineProgress, "_write", lambda self, text: (written.append(text),
                                                                               setattr(self, "last_line", self.clock())))
    now = [0.0]
    lines = progress.LineProgress("render", 300, "fr/s", every=60.0, clock=lambda: now[0])
    for _ in range(100):
        now[0] += 0.5
        lines.advance(1)  # 50 s: no line yet
    assert written == []
    for _ in range(100):
        now[0] += 0.5
        lines.advance(1, status="ok")
    assert written == ["render: 120/300 in 0:01:00 (2.0 fr/s), ETA 0:01:30; ok"]
    assert lines.line(final=True) == "render: 200/300 in 0:01:40 (2.0 fr/s); ok"


def test_version_prints_the_package_version(capsys):
    from importlib import metadata

    code, out, err = run_cli(capsys, "--version")
    assert code == 0 and not err
    assert out == f"mosaic {metadata.version('mosaic-cli')}\n"


def test_version_of_an_uninstalled_checkout_is_pyprojects(capsys, monkeypatch):
    """Run from a checkout that was never installed: the version pyproject.toml declares."""
    import tomllib
    from importlib import metadata
    from pathlib import Path

    def not_installed(name):
        raise metadata.PackageNotFoundError(name)

    monkeypatch.setattr(metadata, "version", not_installed)
    declared = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]["version"]
    code, out, _ = run_cli(capsys, "--version")
    assert code == 0 and out == f"mosaic {declared}\n"


# -- --work-width: no silent option ---------------------------------------------------------


@pytest.mark.parametrize("name", ["lstm", "cnn"])
def test_work_width_other_than_the_networks_is_refused_before_any_work(tmp_path, capsys, tiny_clip, name):
    """A learned estimator works at its weights' width: another --work-width would be ignored."""
    out = tmp_path / "t.json"
    code, _, err = run_cli(capsys, "track", tiny_clip, "-o", out, "-e", name, "--work-width", 640, "-q")
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"mosaic: error: --work-width 640: the {name} network works at 320 px, the width its weights were trained at")
    assert not out.exists()
    code, _, err = run_cli(capsys, "stitch", tiny_clip, "-o", tmp_path / "p.png", "--work-width", 512, "-q")  # the default, lstm
    assert code == 2 and "--work-width 512: the lstm network works at 320 px" in err


def test_work_width_wider_than_the_video_is_clamped_with_a_warning(tmp_path, capsys, tiny_clip):
    """orb never upscales: a 96 px wide video with --work-width 4096 is worked at 96 px, and said so."""
    out = tmp_path / "t.json"
    code, _, err = run_cli(capsys, "track", tiny_clip, "-o", out, "-e", "orb", "--work-width", 4096, "-q")
    assert code == 0, err
    assert err == "mosaic: warning: --work-width 4096 is wider than the video (96 px): working at 96 px (upscaling adds no detail, only time)\n"
    assert json.loads(out.read_text())["meta"]["work_width"] == 96
    # The default (320) is not the user's choice: clamped without a word.
    code, _, err = run_cli(capsys, "track", tiny_clip, "-o", out, "-e", "orb", "-q")
    assert code == 0 and err == ""
    assert json.loads(out.read_text())["meta"]["work_width"] == 96


def test_one_estimator_instance_keeps_the_requested_width_across_videos():
    """bench resets one estimator for flights of several sizes: a narrow one clamps only itself."""
    from mosaic_cli.estimators import make_estimator

    orb = make_estimator("orb", work_width=640)
    orb.reset((320, 180))
    assert orb.work_size == (320, 180)
    orb.reset((1280, 720))
    assert orb.work_size == (640, 360)
    assert make_estimator("orb", default_width=640).work_width == 640  # stabilize's default


def help_panels(capsys, command: str) -> dict[str, list[str]]:
    """The boxes of ``mosaic COMMAND --help``: panel title -> the long flags listed in it."""
    code, out, _ = run_cli(capsys, command, "--help")
    assert code == 0
    panels: dict[str, list[str]] = {}
    title = None
    for line in out.splitlines():
        if line.startswith("╭─ "):
            title = line[3:].split(" ─")[0].strip()
            panels[title] = []
        elif title is not None and line.startswith("│ "):
            panels[title] += [word for word in line[2:].split() if word.startswith("--")][:1]
    return panels


@pytest.mark.parametrize("command", COMMANDS)
def test_every_option_of_every_command_is_in_a_named_help_panel(capsys, monkeypatch, command):
    """--help reads as groups: the plain Options box holds --help alone, and each option of the
    command is listed under one panel."""
    import typer

    from mosaic_cli.cli import app

    monkeypatch.setenv("COLUMNS", "200")  # one row per option: no flag wrapped away
    panels = help_panels(capsys, command)
    assert panels["Options"] == ["--help"]
    click_command = typer.main.get_command(app).commands[command]
    flags = [next(o for o in p.opts if o.startswith("--")) for p in click_command.params
             if p.param_type_name == "option" and not p.hidden]  # (hidden: an old spelling, refused with the new one)
    listed = [flag for title, shown in panels.items() if title not in ("Options", "Arguments") for flag in shown]
    assert sorted(listed) == sorted(flags)


def test_stitch_help_groups_its_options(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    panels = help_panels(capsys, "stitch")
    assert list(panels) == ["Arguments", "Options", "Input and output", "Estimator", "Drift control", "Output quality",
                            "Overlays and mask", "Telemetry and maps", "Live input", "Progress and run", "Machine"]
    assert panels["Machine"] == ["--workers", "--scheduler"]
    assert panels["Drift control"] == ["--drift-control", "--max-loop-pairs", "--overlap"]
    assert panels["Live input"] == ["--live", "--preview", "--every", "--timeout"]
    assert "--telemetry" in panels["Telemetry and maps"] and "--work-width" in panels["Estimator"]
