"""What the suites share: the repository's paths, the data beside it, a suite's sub-commands, the
CPU seconds of this process and its children, a command's stage times, and the scores of a
panorama against exact truth (the stitch tests use them too)."""

from __future__ import annotations

import argparse
import inspect
import os
import re
import resource
import shlex
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]  # the repository
SHARED_DATA = ROOT.parent / "shared" / "data"  # the images and clips beside it, where present
STILLS = SHARED_DATA / "aerial_stills"
# The NEON orthophoto most flights fly over (a procedural map where it is absent).
ORTHOPHOTO = STILLS / "deepforest_neon_orthophoto" / "2019_YELL_2_528000_4978000_image_crop2.png"

Command = Callable[[list[str]], "int | None"]  # a command: its arguments -> its exit status (None: 0)


def prog(suite: str, command: str | None = None) -> str:
    """How a suite's command is called, for its parser's usage line."""
    return " ".join(["python -m benchmarks", suite, *([command] if command else [])])


def make_parser(suite: str, command: str | None, doc: str | None) -> argparse.ArgumentParser:
    """The parser of a suite's command, its docstring as the description, as written."""
    return argparse.ArgumentParser(prog=prog(suite, command), description=inspect.cleandoc(doc or ""),
                                   formatter_class=argparse.RawDescriptionHelpFormatter)


def run_commands(suite: str, doc: str | None, commands: Mapping[str, Command], argv: Sequence[str], default: Command | None = None) -> int:
    """Run the command of ``commands`` that the first word of ``argv`` names, with the rest of
    ``argv``; or, where it names none, ``default`` with all of ``argv``.  ``--help`` lists the
    commands, then shows the default's own arguments."""
    argv = list(argv)
    if argv and argv[0] in commands:
        return commands[argv[0]](argv[1:]) or 0
    if default is not None and argv[:1] not in (["-h"], ["--help"]):
        return default(argv) or 0
    if argv and argv[0] not in ("-h", "--help"):
        print(f"{prog(suite)}: no command {argv[0]!r} (of {', '.join(commands)})", file=sys.stderr)
        return 2
    print(inspect.cleandoc(doc or ""), "\ncommands:", sep="\n")
    if default is not None:
        print(f"  {'(none)':<18} {summary(default)} (its arguments below)")
    for name, fn in commands.items():
        print(f"  {name:<18} {summary(fn)}")
    print(f"\n{prog(suite, 'COMMAND')} --help: a command's own arguments")
    if default is not None:
        print()
        return default(["--help"]) or 0
    return 0


def summary(fn: Command, width: int = 110) -> str:
    """The first sentence of a command's docstring, cut at ``width`` characters."""
    paragraph = " ".join(inspect.cleandoc(fn.__doc__ or "").split("\n\n")[0].split())
    sentence = re.split(r"(?<=[^.][.?])\s", paragraph)[0].rstrip(".")
    return sentence if len(sentence) <= width else sentence[: width - 3] + "..."


def command_line() -> str:
    """The command this process runs, to print beside its figures."""
    if sys.argv[0].endswith(("benchmarks/__main__.py", "-m")):
        return shlex.join(["python", "-m", "benchmarks", *sys.argv[1:]])
    return shlex.join([sys.executable, *sys.argv])


def print_start() -> None:
    """The command and the machine's load, printed before a benchmark's figures."""
    print("command:", command_line())
    print(f"cpus: {os.cpu_count()}, load average at start: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


def cpu_seconds() -> float:
    """User and system CPU seconds of this process (every thread) and of its children waited for
    (ffmpeg): the cost, which a loaded machine does not change much."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


# A mosaic command's final line names its stages' seconds: "... (overlays 1.2 s, track 3.4 s)".
STAGE = re.compile(r"(overlays|track|path|render|scan|register|compose|write) ([0-9.]+) s")


def stage_seconds(stderr: str) -> dict[str, float]:
    """The stage seconds of a mosaic command's final line that names any (empty where none does)."""
    lines = [line for line in stderr.strip().splitlines() if STAGE.search(line)]
    return {name: float(value) for name, value in STAGE.findall(lines[-1])} if lines else {}


def decoded_count(path: Path | str) -> int:
    """Frames OpenCV's own FFmpeg build decodes from ``path`` (each coded frame once; no container
    figures); a folder: its PNG images."""
    if Path(path).is_dir():
        return len(list(Path(path).glob("*.png")))
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    count = 0
    while capture.grab():
        count += 1
    capture.release()
    return count


def placement_errors(indices: Sequence[int], frame_to_pano: Sequence[np.ndarray], map_to_frame: Sequence[np.ndarray] | np.ndarray,
                     size: tuple[int, int], gap: int) -> np.ndarray:
    """Corner error of used frame i placed relative to used frame j (i -> j through the panorama),
    for every pair of used frames at least ``gap`` frames apart, against the exact homography."""
    from mosaic_cli.geometry import corner_error

    errors = []
    for a, i in enumerate(indices):
        for b, j in enumerate(indices):
            if j - i >= gap:
                estimate = np.linalg.inv(frame_to_pano[b]) @ frame_to_pano[a]
                truth = map_to_frame[j] @ np.linalg.inv(map_to_frame[i])
                errors.append(float(corner_error(estimate, truth, size)))
    return np.array(errors)


def plain_chain(video: Path, indices: list[int], features: int = 4000, patch: int = 31, ransac_px: float = 3.0) -> list[np.ndarray]:
    """The baseline drift control is measured against: full-resolution ORB (``features``, its
    ``patch`` size) + RANSAC between consecutive used frames, chained (frame -> first used frame),
    no joint refinement."""
    from mosaic_cli.geometry import normalize
    from mosaic_cli.video import open_video

    wanted, gray = set(indices), {}
    with open_video(video, gray=True) as stream:
        for k, frame in enumerate(stream):
            if k in wanted:
                gray[k] = frame
            if k >= indices[-1]:
                break
    orb = cv2.ORB_create(features, fastThreshold=10, edgeThreshold=patch, patchSize=patch)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    placements = [np.eye(3)]
    for a, b in zip(indices[:-1], indices[1:]):
        ka, da = orb.detectAndCompute(gray[a], None)
        kb, db = orb.detectAndCompute(gray[b], None)
        good = [m[0] for m in matcher.knnMatch(da, db, k=2) if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
        src = np.array([ka[m.queryIdx].pt for m in good], np.float32)
        dst = np.array([kb[m.trainIdx].pt for m in good], np.float32)
        H_ab, _ = cv2.findHomography(src, dst, cv2.RANSAC, ransac_px)
        placements.append(normalize(placements[-1] @ np.linalg.inv(H_ab)))
    return placements
