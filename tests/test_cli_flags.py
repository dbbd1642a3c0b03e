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
