"""The learned estimator's pool of threads (``--threads``): each pair's own work (the polish and its
wide retry, the correlation check, the fallback's registration) runs on the pool, what follows
from the pairs before (the carried motion, the prior, the counts) after it, in order;
the estimates with 2 and 4 threads are those of one thread to the bit, on flights where every
path runs, and ``mosaic track --threads N`` sizes the pool."""

from __future__ import annotations

import json
import threading
import time

import cv2
import numpy as np
import pytest
import torch
from test_learned import FULL, WORK, PhaseNet, short_sighted

from conftest import textured_image, write_clip
from mosaic_cli import device
from mosaic_cli.cli import main
from mosaic_cli.estimators import estimate_stream, make_estimator
from mosaic_cli.estimators.learned import LearnedConfig, LearnedEstimator, default_weights
from mosaic_cli.estimators.orb import OrbEstimator
from mosaic_cli.model.checkpoint import load_weights

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(autouse=True)
def threads_as_they_were():
    """``--threads`` is process state (the commands set it): each test leaves it as it found it."""
    asked, torch_threads = device._cpu_threads["asked"], torch.get_num_threads()
    yield
    device._cpu_threads["asked"] = asked
    torch.set_num_threads(torch_threads)


def pan(texture: np.ndarray, n: int, step: tuple[int, int], x0: int, y0: int) -> list[np.ndarray]:
    """``n`` FULL-size frames of ``texture``, the content moving by ``step`` px a frame."""
    w, h = FULL
    return [texture[y0 - step[1] * t : y0 - step[1] * t + h, x0 - step[0] * t : x0 - step[0] * t + w] for t in range(n)]


def mixed_flight() -> list[np.ndarray]:
    """A fast pan (18 working px a frame: the fallback's until the motion prior knows it), four
    black frames (carried, then failed past the carry limit), the pan again, a cut to other
    ground moving another way, and there two blurred frames and a glare (spoilt frames, carried
    or not)."""
    a = pan(textured_image(1400, 700, seed=5), 14, (36, -8), 20 + 13 * 36, 150)
    b = pan(textured_image(1400, 700, seed=8), 12, (12, 4), 400, 100)
    b[3], b[4] = (cv2.GaussianBlur(f, (0, 0), 8) for f in b[3:5])
    b[8] = np.clip(b[8].astype(int) * 4 + 120, 0, 255).astype(np.uint8)
    return a[:6] + [np.zeros_like(a[0])] * 4 + a[6:] + b


class Watched:
    """Counts, from any thread, what an estimator did: wide polishes, fallback registrations,
    pairs decided that touch a spoilt frame."""

    def __init__(self, est: LearnedEstimator):
        self.wide, self.fallback, self.decided_spoilt = 0, 0, 0
        self._lock = threading.Lock()
        polish_once, decide = est._polish_once, est._decide

        def polish_counted(prev, cur, H, config):
            if config is est.config.polish_wide:
                self._count("wide")
            return polish_once(prev, cur, H, config)

        def decided_counted(prev, cur, *args):
            if prev.spoilt or cur.spoilt:
                self._count("decided_spoilt")
            return decide(prev, cur, *args)

        est._polish_once, est._decide = polish_counted, decided_counted  # type: ignore[method-assign]
        if est._fallback is not None:
            register = est._fallback.register

            def register_counted(*args):
                self._count("fallback")
                return register(*args)

            est._fallback.register = register_counted  # type: ignore[method-assign]

    def _count(self, what: str) -> None:
        with self._lock:
            setattr(self, what, getattr(self, what) + 1)


def estimates(est: LearnedEstimator, frames, size=FULL) -> dict:
    out = list(estimate_stream(est, frames, size))
    return {"H": np.array([e.H for e in out]), "confidence": np.array([e.confidence for e in out]),
            "paths": [e.path for e in out], "path_counts": dict(est.path_counts)}


def assert_identical(got: dict, want: dict) -> None:
    assert got["paths"] == want["paths"]
    assert got["path_counts"] == want["path_counts"]
    assert np.array_equal(got["H"], want["H"])  # to the bit
    assert np.array_equal(got["confidence"], want["confidence"])


def phase_estimator(threads: int, **config) -> LearnedEstimator:
    """A short-sighted phase-correlation "net" (3 working px of reach) with the motion prior, the
    polish and the fallback, carrying at most two pairs in a row."""
    cfg = {"refine": "lk", "fallback": "orb", "prior": "velocity", "chunk": 4, "carry_limit": 2, **config}
    return LearnedEstimator(PhaseNet(short_sighted), {"variant": "phase", "work_size": WORK}, "cpu", LearnedConfig(**cfg), threads=threads)


@pytest.fixture(scope="module")
def mixed():
    return mixed_flight()


@pytest.fixture(scope="module")
def one_thread(mixed):
    est = phase_estimator(1)
    watched = Watched(est)
    return estimates(est, mixed), watched


@pytest.fixture(scope="module")
def reference(mixed, one_thread):
    """The one-thread estimates of the mixed flight for a config, each made once for the tests below."""
    made = {(): one_thread[0]}

    def of(config: dict) -> dict:
        key = tuple(sorted(config.items()))
        if key not in made:
            made[key] = estimates(phase_estimator(1, **config), mixed)
        return made[key]

    return of


def test_the_mixed_flight_runs_every_path(one_thread):
    """The reference run itself: each path made pairs, the wide polish and the fallback ran, pairs
    touching spoilt frames were decided, and the carry limit stopped a run of carried pairs (so
    the counts depend on the order the pairs are decided in)."""
    ref, watched = one_thread
    counts = ref["path_counts"]
    assert all(counts[p] > 0 for p in ("learned", "fallback", "carried", "failed")), counts
    assert watched.wide > 0 and watched.fallback > counts["fallback"] and watched.decided_spoilt > 0
    paths = "".join(p[0] for p in ref["paths"])
    assert "ccf" in paths, paths  # two carried, then the limit: failed


@pytest.mark.parametrize("config, threads", [({}, 2), ({}, 4), ({"chunk": 16}, 4), ({"chunk": 1}, 4), ({"polish_start": "velocity"}, 4),
                                             ({"refine": "ecc"}, 4), ({"carry": "network"}, 4)],
                         ids=["default-2", "default-4", "chunk16-4", "chunk1-4", "velocity-seed-4", "ecc-4", "carry-network-4"])
@pytest.mark.slow
def test_threads_give_the_one_thread_estimates_to_the_bit(mixed, reference, threads, config):
    """2 and 4 threads on the default config; each other config on 4 (the more threads, the more
    orders the pairs' checks can end in; the lookahead test below runs them on 2)."""
    ref = reference(config)
    est = phase_estimator(threads, **config)
    got = estimates(est, mixed)
    assert est._pool is not None and est._pool_size == threads
    assert_identical(got, ref)
    assert_identical(estimates(est, mixed), ref)  # a second video on the same pool: the same


@pytest.mark.parametrize("config", [{"prior": "none"}, {"prior": "none", "chunk": 1}, {"prior": "none", "carry": "network"}, {}],
                         ids=["no-prior", "chunk1", "carry-network", "velocity-prior"])
@pytest.mark.slow
def test_a_files_lookahead_gives_the_same_estimates_a_chunk_late(mixed, reference, config):
    """``lookahead`` (a file's pass, estimate_stream's): the next chunk's network runs while the
    pool checks the chunk before, whose pairs come back a chunk late: the same estimates, to the
    bit, as one thread.  With the motion prior the network reads the decisions: no lookahead."""
    ref = reference(config)
    est = phase_estimator(2, **config)
    got = list(estimate_stream(est, mixed, FULL, lookahead=True))
    assert_identical({"H": np.array([e.H for e in got]), "confidence": np.array([e.confidence for e in got]),
                      "paths": [e.path for e in got], "path_counts": dict(est.path_counts)}, ref)
    assert est.lookahead is False and est._ahead is None  # as it was, nothing left behind
    chunk = est.config.chunk
    est.reset(FULL)
    est.lookahead = True
    told = [len(est.feed(f)) for f in mixed[: 2 * chunk + 1]]
    ahead = config.get("prior") == "none"
    assert told[chunk] == (0 if ahead else chunk)  # the first chunk: told at the second, when ahead
    assert told[2 * chunk] == chunk


def test_pairs_checked_out_of_order_are_decided_in_order(mixed, one_thread):
    """The first pair of every chunk is checked last (its thread is held back): the decisions,
    which carry the motion, the carried run and the counts from pair to pair, still come in the
    flight's order, and the estimates are the same."""
    est = phase_estimator(4)
    check = est._check

    def late_first(prev, cur, seed, offsets_ok):
        if any(prev is pending for pending in starts):
            time.sleep(0.05)
        return check(prev, cur, seed, offsets_ok)

    starts: list = []
    run_chunk = est._run_chunk

    def chunk():
        starts[:] = [est._pending[0]]
        return run_chunk()

    est._check, est._run_chunk = late_first, chunk  # type: ignore[method-assign]
    assert_identical(estimates(est, mixed), one_thread[0])


def test_one_thread_has_no_pool(mixed):
    est = phase_estimator(1)
    estimates(est, mixed[:8])
    assert est._pool is None


def test_the_pool_defaults_to_the_cores_and_follows_threads(monkeypatch):
    monkeypatch.setattr(device.os, "cpu_count", lambda: 6)
    device.ask_cpu_threads(None)
    assert device.pair_threads() == 6 and torch.get_num_threads() == device.DEFAULT_CPU_THREADS  # the network: one
    est = phase_estimator(1)
    est.threads = None
    est.reset(FULL)
    assert est._workers == 6
    device.ask_cpu_threads(3)
    est.reset(FULL)
    assert est._workers == 3 and device.pair_threads() == 3
    monkeypatch.setattr(device.os, "cpu_count", lambda: None)
    device.ask_cpu_threads(None)
    assert device.pair_threads() == 1


def test_the_fallback_registers_alike_from_many_threads():
    """One OrbEstimator asked from several threads at once (each has its own detector and
    matcher): the same registrations as one after the other."""
    frames = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in pan(textured_image(1000, 600, seed=3), 9, (9, 5), 200, 100)]
    frames = [cv2.resize(f, WORK, interpolation=cv2.INTER_AREA) for f in frames]
    orb = OrbEstimator(WORK[0])
    orb.reset(WORK)
    pairs = list(zip(frames[:-1], frames[1:])) * 4

    def register(pair):
        H, confidence = orb.register(*pair)
        return H.tobytes(), confidence

    want = [register(p) for p in pairs]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(4) as pool:
        assert list(pool.map(register, pairs)) == want


# --- the shipped network on simulated flights -----------------------------------------------------


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A 640x360 extreme flight (-p extreme: 25-60 px a frame, where the wide polish runs) cut
    to one with bursts of spoilt frames (-p bursts), decoded at the working width."""
    from mosaic_cli.simulate import SimulateOptions, simulate_flight
    from mosaic_cli.video import open_video

    folder = tmp_path_factory.mktemp("flights")
    frames = []
    for profile, seed, n in (("extreme", 0, 50), ("bursts", 1, 80)):
        path = folder / f"{profile}.mp4"
        simulate_flight(path, options=SimulateOptions(profile=profile, frames=n, size=(640, 360), seed=seed), show_progress=False)
        with open_video(path, width=WORK[0], gray=True) as stream:
            frames += list(stream)
    return frames


def shipped_lstm(threads: int) -> LearnedEstimator:
    model, meta = load_weights(default_weights("lstm"), device="cpu")
    return LearnedEstimator(model, meta, device="cpu", threads=threads)


@pytest.mark.slow
def test_the_shipped_lstm_on_simulated_flights_is_the_same_on_any_number_of_threads(simulated):
    est = shipped_lstm(1)
    watched = Watched(est)
    ref = estimates(est, simulated, (640, 360))
    counts = ref["path_counts"]
    assert counts["carried"] > 0 and counts["learned"] > 100, counts  # the bursts
    assert ref["paths"][49] == "failed"  # the cut
    assert watched.wide > 10 and watched.fallback > 0 and watched.decided_spoilt > 0
    for threads in (2, 4):
        assert_identical(estimates(shipped_lstm(threads), simulated, (640, 360)), ref)


# --- the command line ----------------------------------------------------------------------------


@pytest.mark.slow
def test_track_threads_sizes_the_pool(tmp_path, monkeypatch, flight):
    """``mosaic track --threads N``: a pool of N (none for 1), the network on N torch threads; by
    default one a core; the same track whatever N."""
    clip = write_clip(tmp_path / "flight.mp4", flight.frames)
    sizes: list[int] = []
    reset = LearnedEstimator.reset

    def recorded(self, full_size):
        reset(self, full_size)
        sizes.append(self._workers)

    monkeypatch.setattr(LearnedEstimator, "reset", recorded)
    monkeypatch.setattr(device.os, "cpu_count", lambda: 3)
    tracks = {}
    for threads in ("1", "2", None):
        out = tmp_path / f"track{threads}.json"
        args = ["track", str(clip), "-o", str(out), "-q", "--device", "cpu", *(["--threads", threads] if threads else [])]
        with pytest.raises(SystemExit) as exit_info:
            main(args)
        assert exit_info.value.code in (0, None)
        tracks[threads] = json.loads(out.read_text())
        assert sizes[-1] == (int(threads) if threads else 3)
        assert torch.get_num_threads() == (int(threads) if threads else 1)
    assert tracks["1"]["pairwise"] == tracks["2"]["pairwise"] == tracks[None]["pairwise"]
    for key in ("confidence", "path", "paths"):
        assert tracks["1"].get(key) == tracks["2"].get(key) == tracks[None].get(key), key


def test_make_estimator_takes_the_pool_size_from_threads(monkeypatch):
    monkeypatch.setattr(device.os, "cpu_count", lambda: 5)
    device.ask_cpu_threads(None)
    est = make_estimator("lstm", device="cpu")
    est.reset(FULL)
    assert isinstance(est, LearnedEstimator) and est._workers == 5


def test_the_builds_warm_up_changes_no_estimate_and_leaves_no_state(tmp_path):
    """make_learned_estimator runs the network once on blank pairs (CUDA's plans, the first int8
    calls) before any video: the estimates of a flight are those of an estimator never warmed up,
    to the bit, and the sequence head starts from no state."""
    from conftest import simulated
    from mosaic_cli.estimators import estimate_stream
    from mosaic_cli.estimators.learned import LearnedEstimator, default_weights
    from mosaic_cli.model import load_weights
    from mosaic_cli.video import open_video

    video = simulated(tmp_path / "flight.mp4", "-p", "fast", "-n", "40", "--size", "320x180", "--preset", "ultrafast", "--seed", "3")

    def track(warm: bool) -> np.ndarray:
        model, meta = load_weights(default_weights("lstm"), device="cpu")
        estimator = LearnedEstimator(model, meta, device="cpu", threads=1)
        if warm:
            estimator.warm_up()
            assert estimator._state is None and estimator._pairs_done == 0
        with open_video(video, width=estimator.input_width, gray=True) as stream:
            return np.array([e.H for e in estimate_stream(estimator, stream, (320, 180))])

    np.testing.assert_array_equal(track(True), track(False))
