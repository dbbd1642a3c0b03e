"""A live run's network in a process of its own (:mod:`mosaic_cli.live.network_process`): the
same estimates as the network run in the live process, its errors in one line, and no child
left behind."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from mosaic_cli.errors import BadInput, ProcessingError
from mosaic_cli.estimators import make_estimator
from mosaic_cli.live.network_process import NetworkProcess
from tests.conftest import textured_image

pytestmark = pytest.mark.alone  # wall-clock bounds: run with no other test beside it (conftest.py)

FULL = (640, 360)
BUILD = {"name": "lstm", "work_width": None, "weights": None, "device": "cpu", "default_width": 320, "chunk": 4}


def panned_grays(count: int, step: float) -> tuple[list[np.ndarray], np.ndarray]:
    """Gray frames at the network's 320x180, each ``step`` px (full resolution) right of the last, and that shift's homography."""
    ground = cv2.cvtColor(textured_image(FULL[0] + 200, FULL[1], seed=5), cv2.COLOR_RGB2GRAY)
    grays = [cv2.resize(ground[:, int(round(k * step)):int(round(k * step)) + FULL[0]], (320, 180), interpolation=cv2.INTER_AREA)
             for k in range(count)]
    truth = np.array([[1.0, 0.0, -step], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # frame t -> t+1 (the ground moves left)
    return grays, truth


def run(estimator, grays: list[np.ndarray]) -> list:
    estimator.set_mask(None)
    estimator.reset(FULL)
    estimates = []
    for gray in grays:
        estimates += estimator.feed(gray)
    return estimates + estimator.finish()


@pytest.mark.slow
def test_the_network_in_its_own_process_gives_the_estimates_it_gives_in_this_one():
    grays, truth = panned_grays(10, 8.0)
    child = NetworkProcess(BUILD)
    try:
        assert child.name == "lstm-reg-t" and child.input_width == 320 and child.config.chunk == 4
        remote = run(child, grays)
    finally:
        child.close()
    with make_estimator(**BUILD) as here:
        local = run(here, grays)
    assert len(remote) == len(local) == len(grays) - 1
    for a, b in zip(remote, local):
        assert np.allclose(a.H, b.H, atol=1e-9) and a.confidence == pytest.approx(b.confidence) and a.path == b.path
    corners = np.array([[0, 0, 1], [FULL[0], 0, 1], [0, FULL[1], 1], [FULL[0], FULL[1], 1]], float).T
    for estimate in remote:  # and right: each pair within a pixel of the pan
        moved, true = estimate.H @ corners, truth @ corners
        assert np.abs(moved[:2] / moved[2] - true[:2]).max() < 1.0


@pytest.mark.slow
def test_a_network_that_cannot_load_says_why_in_one_line(tmp_path):
    bad = tmp_path / "weights.safetensors"
    bad.write_bytes(b"not weights")
    started = time.monotonic()
    with pytest.raises((BadInput, ProcessingError)) as caught:
        NetworkProcess({**BUILD, "weights": str(bad)})
    assert "\n" not in str(caught.value) and str(caught.value)
    assert time.monotonic() - started < 30


@pytest.mark.slow
def test_a_child_that_dies_is_an_error_not_a_hang_and_close_leaves_none():
    grays, _ = panned_grays(3, 4.0)
    child = NetworkProcess(BUILD)
    child.reset(FULL)
    child.feed(grays[0])
    child._child.kill()
    with pytest.raises(ProcessingError, match="network's process ended"):
        child.feed(grays[1])
    assert child._child.poll() is not None
    healthy = NetworkProcess(BUILD)
    healthy.close()
    assert healthy._child.returncode == 0
