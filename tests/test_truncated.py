"""A truncated video: the run goes on with one warning line that says how many frames were
decoded of how many the container announced, every output records it, and ``--strict`` makes
it an error (exit 2, no output).  Known counts: clips of a known number of frames written here,
cut to a share of their bytes, decoded back with OpenCV."""

from __future__ import annotations

import json

import pytest

from conftest import ffmpeg, opencv_count
from mosaic_cli.cli import main

FRAMES = 90


def run_cli(capsys, *args):
    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in args])
    code = exit_info.value.code
    return (0 if code is None else code), capsys.readouterr().err


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    """(whole mp4, the first 40 % of its bytes, the same cut of an mkv copy, a clip cut
    without re-encoding whose edit list leaves frames out: not truncated)."""
    folder = tmp_path_factory.mktemp("cut")
    whole = folder / "whole.mp4"
    ffmpeg("-f", "lavfi", "-i", "testsrc2=size=320x180:rate=30", "-frames:v", str(FRAMES), "-c:v", "libx264",
           "-preset", "ultrafast", "-pix_fmt", "yuv420p", "-movflags", "+faststart", str(whole))
    data = whole.read_bytes()
    cut = folder / "cut.mp4"
    cut.write_bytes(data[: len(data) * 4 // 10])
    mkv = folder / "whole.mkv"
    ffmpeg("-i", str(whole), "-c", "copy", str(mkv))
    cut_mkv = folder / "cut.mkv"
    cut_mkv.write_bytes(mkv.read_bytes()[: mkv.stat().st_size * 4 // 10])
    trimmed = folder / "trimmed.mp4"
    ffmpeg("-ss", "1.05", "-i", str(whole), "-c", "copy", str(trimmed))
    return whole, cut, cut_mkv, trimmed


@pytest.mark.slow
def test_truncated_track_warns_once_and_records_it(tmp_path, capsys, clips):
    _, cut, cut_mkv, _ = clips
    for video in (cut, cut_mkv):
        decoded = opencv_count(video)
        assert 0 < decoded < FRAMES * 0.8
        out = tmp_path / f"{video.stem}.json"
        code, err = run_cli(capsys, "track", video, "-o", out, "-e", "orb", "-q")
        assert code == 0, err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("mosaic: warning: "), err
        assert f"decoded {decoded} of the {FRAMES} frames" in lines[0] and video.name in lines[0]
        data = json.loads(out.read_text())
        assert data["frames"] == decoded
        assert data["meta"]["input"]["frames_decoded"] == decoded
        assert data["meta"]["input"]["frames_announced"] == FRAMES and data["meta"]["input"]["truncated"] is True


def test_strict_refuses_a_truncated_video_in_every_command(tmp_path, capsys, clips):
    _, cut, _, _ = clips
    out = tmp_path / "out"
    out.mkdir()
    for args in (["track", cut, "-o", out / "t.json"], ["stitch", cut, "-o", out / "p.png", "--transforms", out / "t.json"],
                 ["stabilize", cut, out / "s.mp4", "--warps", out / "w.json"]):
        code, err = run_cli(capsys, *args, "-e", "orb", "-q", "--strict")
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and lines[0].startswith("mosaic: error: "), (args, err)
        # (refused before any work where ffmpeg already complains of the end, else after decoding)
        assert "truncated or damaged" in lines[0] and f" {FRAMES} frames" in lines[0] and "--strict" in lines[0]
        assert list(out.iterdir()) == [], args


@pytest.mark.slow
def test_stabilize_and_stitch_record_the_shortfall(tmp_path, capsys, clips):
    _, cut, _, _ = clips
    decoded = opencv_count(cut)
    code, err = run_cli(capsys, "stabilize", cut, tmp_path / "s.mp4", "--warps", tmp_path / "w.json", "-e", "orb", "-q")
    assert code == 0 and err.count("mosaic: warning: ") == 1, err
    warps = json.loads((tmp_path / "w.json").read_text())
    assert warps["frames"] == decoded == opencv_count(tmp_path / "s.mp4")
    assert warps["input"]["frames_decoded"] == decoded and warps["input"]["frames_announced"] == FRAMES
    # testsrc2 is no flight: overlay detection would mask its static pattern and leave the
    # moving box to stitch, in pieces; the shortfall is what is checked here.
    code, err = run_cli(capsys, "stitch", cut, "-o", tmp_path / "p.png", "--transforms", tmp_path / "t.json", "-e", "orb", "-q",
                        "--no-overlay-detect")
    assert code == 0 and err.count("mosaic: warning: ") == 1, err
    assert json.loads((tmp_path / "t.json").read_text())["input"]["frames_decoded"] == decoded


@pytest.mark.slow
def test_whole_and_edit_list_clips_are_not_called_truncated(tmp_path, capsys, clips):
    whole, _, _, trimmed = clips
    assert opencv_count(trimmed) < FRAMES  # the container still lists the frames the edit list leaves out
    for video in (whole, trimmed):
        out = tmp_path / f"{video.stem}.json"
        code, err = run_cli(capsys, "track", video, "-o", out, "-e", "orb", "-q", "--strict")
        assert code == 0 and err == "", err
        data = json.loads(out.read_text())
        assert data["frames"] == opencv_count(video) and "input" not in data["meta"]
    # frames skipped by --start count as decoded
    code, err = run_cli(capsys, "stitch", whole, "--start", "30", "-o", tmp_path / "p.png", "-e", "orb", "-q", "--strict")
    assert code == 0 and err == "", err
