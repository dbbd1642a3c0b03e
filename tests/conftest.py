"""Shared fixtures and helpers: procedural textures, virtual camera flights with exact
homographies, tiny generated clips, running the CLI in this process and checking its one-line
errors, and one torch thread for small-tensor tests.  Everything here is made on the fly, so
tests need no data files."""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from benchmarks.common import decoded_count as opencv_count  # noqa: F401  (the tests' name for it)
from mosaic_cli.cli import main

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

try:
    import imageio_ffmpeg

    FFMPEG = imageio_ffmpeg.get_ffmpeg_exe()
except ImportError:  # the lent GPU machine has no video tools; the tests it runs (-m cuda) need none
    FFMPEG = "ffmpeg"


# -- tests that time themselves run alone ------------------------------------------------------
# The suite runs on every core (pytest-xdist, ``-n auto``).  A test marked ``alone`` asserts
# wall-clock bounds (a live stream's latency, an exit within 2 s, a worker's retry) that hold on
# an idle machine, not beside another test: it waits for the other workers' tests to end, and
# none starts until it has.  A readers-writer lock on a file the run's workers share (in a folder
# the controlling process makes and removes): every other test holds it shared; the turnstile
# keeps a waiting ``alone`` test from starving.
LOCKS = "MOSAIC_TEST_LOCKS"
_locks_made = pytest.StashKey[str]()


def pytest_configure(config):
    if not hasattr(config, "workerinput") and config.getoption("numprocesses", None):  # xdist's controller
        import tempfile

        config.stash[_locks_made] = os.environ[LOCKS] = tempfile.mkdtemp(prefix="mosaic-test-locks-")  # the workers inherit it


def pytest_unconfigure(config):
    if _locks_made in config.stash:
        import shutil

        shutil.rmtree(config.stash[_locks_made], ignore_errors=True)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    folder = os.environ.get(LOCKS) if hasattr(item.config, "workerinput") else None
    if folder is None:  # one process: nothing runs beside it
        yield
        return
    import fcntl

    with open(Path(folder) / "turnstile", "a") as turnstile, open(Path(folder) / "lock", "a") as lock:
        fcntl.flock(turnstile, fcntl.LOCK_EX)
        fcntl.flock(lock, fcntl.LOCK_EX if item.get_closest_marker("alone") else fcntl.LOCK_SH)
        fcntl.flock(turnstile, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def textured_image(width: int, height: int, seed: int = 0) -> np.ndarray:
    """RGB uint8 texture with detail at every scale (multi-octave noise plus sharp-edged
    blobs), so that feature detectors find well-spread corners, as on aerial ground."""
    rng = np.random.default_rng(seed)
    img = np.zeros((height, width, 3), np.float32)
    for cell, weight in ((256, 0.9), (64, 0.7), (16, 0.5), (4, 0.35)):
        coarse = rng.random((max(2, height // cell + 2), max(2, width // cell + 2), 3), dtype=np.float32)
        img += weight * cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    img = (img - img.min()) / (img.max() - img.min()) * 200.0
    for _ in range(width * height // 4000):
        color = tuple(float(c) for c in rng.integers(0, 255, 3))
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        size = int(rng.integers(3, 25))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + size, y + int(rng.integers(3, 25))), color, -1)
        else:
            cv2.circle(img, (x, y), size // 2, color, -1)
    return np.clip(img, 0, 255).astype(np.uint8)


def camera_path(n_frames: int, frame_size: tuple[int, int], map_size: tuple[int, int], seed: int = 0,
                step: float = 6.0) -> np.ndarray:
    """(n, 3, 3) homographies frame pixel -> map pixel of a camera drifting over the map, with a
    slow rotation, zoom and a touch of perspective: every frame stays inside the map."""
    rng = np.random.default_rng(seed)
    fw, fh = frame_size
    mw, mh = map_size
    centre = np.array([fw / 2 - 0.5, fh / 2 - 0.5])
    heading = rng.uniform(0, 2 * np.pi)
    pos = np.array([mw / 2, mh / 2]) - step * (n_frames - 1) / 2 * np.array([np.cos(heading), np.sin(heading)])
    out = []
    for t in range(n_frames):
        angle = 0.01 * t + 0.2 * np.sin(seed + 1)
        scale = 1.0 + 0.05 * np.sin(0.1 * t + seed)
        tilt = 1.5e-5 * np.array([np.sin(0.07 * t), np.cos(0.05 * t)])
        to_centre = np.array([[1, 0, -centre[0]], [0, 1, -centre[1]], [0, 0, 1.0]])
        persp = np.array([[1, 0, 0], [0, 1, 0], [tilt[0], tilt[1], 1.0]])
        c, s = np.cos(angle) * scale, np.sin(angle) * scale
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        p = pos + step * t * np.array([np.cos(heading), np.sin(heading)])
        place = np.array([[1, 0, p[0]], [0, 1, p[1]], [0, 0, 1.0]])
        out.append(place @ rot @ persp @ to_centre)
    return np.array(out)


def render(map_img: np.ndarray, frame_to_map: np.ndarray, frame_size: tuple[int, int]) -> np.ndarray:
    """The camera frame whose pixel p shows map pixel frame_to_map @ p (pixel centres)."""
    return cv2.warpPerspective(map_img, frame_to_map, frame_size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REFLECT)


def true_pairwise(frame_to_map: np.ndarray) -> np.ndarray:
    """Exact frame t -> t+1 homographies of a camera path."""
    H = np.linalg.inv(frame_to_map[1:]) @ frame_to_map[:-1]
    return H / H[:, 2:3, 2:3]


def write_clip(path: Path, frames, fps: float = 30.0, codec: str = "libx264", pix_fmt: str = "yuv420p",
               extra: list[str] | None = None) -> Path:
    """Encode RGB frames with the bundled ffmpeg (any codec/container, for reader tests)."""
    frames = list(frames)
    h, w = frames[0].shape[:2]
    cmd = [FFMPEG, "-hide_banner", "-loglevel", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24",
           "-s", f"{w}x{h}", "-r", str(fps), "-i", "-", "-c:v", codec, "-pix_fmt", pix_fmt]
    if codec == "libx264":
        cmd += ["-crf", "12", "-preset", "ultrafast"]
    cmd += (extra or []) + [str(path)]
    subprocess.run(cmd, input=b"".join(np.ascontiguousarray(f).tobytes() for f in frames), check=True)
    return path


def ffmpeg(*args: str) -> None:
    subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", *args], check=True)


def cli_exit(args) -> int:
    """The exit status of ``mosaic ARGS`` run in this process (0: success)."""
    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in args])
    code = exit_info.value.code
    return 0 if code is None else int(code)


def run_cli(capsys, *args) -> tuple[int, str]:
    """(exit status, stderr) of ``mosaic ARGS`` run in this process."""
    code = cli_exit(args)
    return code, capsys.readouterr().err


def assert_one_line_error(code: int, err: str, *fragments: str, status: int = 2) -> None:
    """The CLI's contract for a failure: exit ``status`` and exactly one ``mosaic: error:`` line
    on stderr (no traceback) that contains every fragment (any case)."""
    assert code == status, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mosaic: error: "), err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment.lower() in lines[0].lower(), lines[0]


class Flight:
    """A rendered virtual-camera flight: frames and the exact pairwise homographies."""

    def __init__(self, n_frames=12, frame_size=(320, 180), map_size=(1200, 900), seed=0, step=6.0):
        self.frame_size = frame_size
        self.map = textured_image(*map_size, seed=seed)
        self.frame_to_map = camera_path(n_frames, frame_size, map_size, seed=seed, step=step * frame_size[0] / 320)
        self.frames = [render(self.map, M, frame_size) for M in self.frame_to_map]
        self.pairwise = true_pairwise(self.frame_to_map)


@pytest.fixture(scope="module")
def one_torch_thread():
    """For modules of small-tensor tests (``pytestmark = pytest.mark.usefixtures("one_torch_thread")``):
    one thread is faster, and on a busy machine OpenMP's spin-waiting threads make a 2-thread run
    up to 50x slower."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session", autouse=True)
def procedural_maps_made_once(tmp_path_factory):
    """The simulator's default map (4096x4096, about 4 s of CPU each) made once per seed for the
    whole session: ``load_map(None, seed)``, as every simulated flight in this process asks for
    it, reads the first one's bytes back from disk (a fresh array each time).  Only the name
    ``load_map`` looks up is replaced: the tests of the map itself (test_simulate) call the
    function as the package exports it."""
    from mosaic_cli.simulate import maps

    made = maps.procedural_map
    folder = tmp_path_factory.mktemp("procedural_maps")

    def once(size=(4096, 4096), seed=0):
        path = folder / f"{int(size[0])}x{int(size[1])}-{int(seed)}.npy"
        if not path.exists():
            np.save(path, made(size, seed))
        return np.load(path)

    maps.procedural_map = once
    yield
    maps.procedural_map = made


@pytest.fixture(scope="session", autouse=True)
def cli_built_once():
    """``mosaic`` run in this process (cli_exit, run_cli) builds its click command tree once, as
    a process does once: typer otherwise rebuilds it from the app on every call (30 ms, a few
    hundred calls).  Other typer apps are built as before."""
    import typer.main

    from mosaic_cli.cli import app

    build = typer.main.get_command
    built: dict = {}

    def once(typer_app):
        if typer_app is not app:
            return build(typer_app)
        if "app" not in built:
            built["app"] = build(app)
        return built["app"]

    typer.main.get_command = once
    yield
    typer.main.get_command = build


@pytest.fixture(scope="session")
def fresh_interpreter_build() -> dict:
    """What a fresh interpreter imports on the way to the shipped estimator, run once for the
    tests that ask (test_estimator_options, test_quantize): ``plan_estimator("lstm")`` then its
    build, then ``make_estimator(None)``; which of torch, torch._dynamo and torch._inductor were
    loaded after each step, the built estimators' types and the default one's precision."""
    import json
    import sys

    code = """if True:
        import json, sys
        seen = lambda: {name: name in sys.modules for name in ("torch", "torch._dynamo", "torch._inductor")}
        from mosaic_cli.estimators import make_estimator, plan_estimator
        build = plan_estimator("lstm")
        planned = seen()
        built = type(build()).__name__
        after_build = seen()
        default = make_estimator(None)
        print(json.dumps({"planned": planned, "built": built, "after_build": after_build,
                          "default": type(default).__name__, "precision": default.precision, "after_default": seen()}))
    """
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


@pytest.fixture(scope="session")
def texture() -> np.ndarray:
    """A 1600x1000 procedural RGB texture."""
    return textured_image(1600, 1000, seed=1)


@pytest.fixture(scope="session")
def flight() -> Flight:
    """12 frames at 320x180 over a procedural map, with exact ground truth."""
    return Flight()


@pytest.fixture(scope="session")
def flight_clip(tmp_path_factory, flight) -> Path:
    """The ``flight`` fixture encoded as a near-lossless H.264 mp4."""
    return write_clip(tmp_path_factory.mktemp("clips") / "flight.mp4", flight.frames)


@pytest.fixture(scope="session")
def tiny_clip(tmp_path_factory, texture) -> Path:
    """Eight 96x64 frames of a panning texture, H.264 mp4 at 10 fps."""
    frames = [texture[100:164, 100 + 3 * k:196 + 3 * k] for k in range(8)]
    return write_clip(tmp_path_factory.mktemp("clips") / "tiny.mp4", frames, fps=10)


def mosaic_run(*args, check: bool = True) -> SimpleNamespace:
    """``mosaic ARGS`` run in this process, its exit status, stdout and stderr as
    ``subprocess.run(..., text=True)`` gives them (for tests not about the process itself);
    ``check``: assert it succeeded."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli_exit(args)
    run = SimpleNamespace(returncode=code, stdout=out.getvalue(), stderr=err.getvalue())
    if check:
        assert run.returncode == 0, run.stderr
    return run


def simulated(path: Path, *args) -> Path:
    """``mosaic simulate -o PATH ARGS -q`` run in this process (the session's maps made once)."""
    assert cli_exit(["simulate", "-o", path, *args, "-q"]) == 0
    return path


@pytest.fixture(scope="session")
def survey_320x180(tmp_path_factory) -> Path:
    """A 120-frame survey flight at 320x180 (x264 veryfast), the one the live stitch tests stream."""
    return simulated(tmp_path_factory.mktemp("survey") / "survey.mp4", "-p", "survey", "-n", "120", "--size", "320x180",
                     "--preset", "veryfast")


@pytest.fixture(scope="session")
def plain_160x90(tmp_path_factory) -> Path:
    """A 20-frame paper flight at 160x90 without telemetry (test_maps, test_georef)."""
    return simulated(tmp_path_factory.mktemp("plain") / "plain.mp4", "-n", "20", "--size", "160x90", "--preset", "ultrafast")


@pytest.fixture
def shared_data() -> Path:
    """The real aerial imagery beside the repository; skips when it is absent (e.g. in a bare clone)."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not present")
    return SHARED_DATA


def overlay_flight_pair(folder: Path, frames: int, size: tuple[int, int], crf: int):
    """A fast simulated flight written twice into ``folder``: ``plain.mp4``, and ``burned.mp4``
    with a logo, a timestamp and letterbox bars burned in (the same frames otherwise).  Returns
    the two paths and the flight's plan."""
    from mosaic_cli.simulate import OverlaySpec, plan_flight, procedural_map, write_flight

    ground = procedural_map((1024, 1024), seed=3)
    plan = plan_flight((1024, 1024), "fast", frames=frames, size=size, seed=3)
    write_flight(folder / "plain.mp4", ground, plan, crf=crf, preset="veryfast", show_progress=False)
    write_flight(folder / "burned.mp4", ground, plan, crf=crf, preset="veryfast", show_progress=False,
                 overlays=OverlaySpec.parse("all"))
    return folder / "plain.mp4", folder / "burned.mp4", plan
