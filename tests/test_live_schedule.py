"""The live stabiliser's schedule (mosaic_cli/live/schedule.py): deadlines, late solves and the
adaptive lookahead, driven step by step with a test clock (no threads, nothing timed)."""

from __future__ import annotations

import numpy as np

from mosaic_cli.live.schedule import ENCODE_RESERVE, LiveSchedule
from mosaic_cli.stabilize.crop import output_warps
from mosaic_cli.stabilize.online import MIN_LOOKAHEAD, Horizon, OnlineL1Path
from mosaic_cli.stabilize.path import motion_model

SIZE = (320, 180)
FPS = 30.0


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def shaky_pan(n: int, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pairwise = np.tile(np.eye(3), (n - 1, 1, 1))
    pairwise[:, 0, 2] = 2.0 + rng.normal(0, 1.5, n - 1)
    pairwise[:, 1, 2] = rng.normal(0, 1.5, n - 1)
    return pairwise


def schedule(clock: Clock, realtime: bool = True, horizon: Horizon = Horizon(step=4, lookahead=10)) -> LiveSchedule:
    path = OnlineL1Path(motion_model("similarity"), SIZE, None, horizon)
    return LiveSchedule(path, SIZE, FPS, latency=1.0, realtime=realtime, capacity=10_000, clock=clock)


def arrive(s: LiveSchedule, clock: Clock, pairwise: np.ndarray, frames: range) -> None:
    """Frames arrive at FPS and their motion is known at once."""
    for k in frames:
        clock.now = k / FPS
        s.add_frame(np.full((SIZE[1] * 3 // 2, SIZE[0]), k % 256, np.uint8), clock.now)
        s.add_motion(None if k == 0 else pairwise[k - 1])


def solve(s: LiveSchedule, job) -> np.ndarray:
    window, final = job
    params = s.path.solve(window)
    s.solved(window, params, final, 0.01)
    return params


def take_ready(s: LiveSchedule) -> list:
    """The frames the renderer may take now (settled, or due by the clock), without waiting."""
    taken = []
    while s._frames and (s._frames[0].warp is not None or (s.realtime and s.clock() >= s.deadline(s._frames[0]))):
        taken.append(s.next_frame())
    return taken


def test_a_late_solve_leaves_frames_on_the_last_plan_and_drops_none():
    n, clock = 90, Clock()
    pairwise = shaky_pan(n)
    s = schedule(clock)
    out = []
    arrive(s, clock, pairwise, range(30))
    first = s.next_window()
    plan = solve(s, first)  # the normal path: frames with the lookahead in view are settled
    settled_normally = s.path.settled
    assert settled_normally == 30 - 10 and s.late == 0
    out += take_ready(s)
    assert len(out) == settled_normally

    arrive(s, clock, pairwise, range(30, 40))
    late_job = s.next_window()  # posed now, and its solve comes back too late:
    clock.now = s.deadline(s._frames[0])  # the next frame's deadline has come
    forced = take_ready(s)
    assert s.late >= 1 and len(forced) == s.late
    # Those frames left with the views of the last plan, its predicted frames included.
    window, _ = first
    expected = output_warps(s.path.model.matrices(plan[settled_normally - window.first:][:len(forced)]), SIZE)
    np.testing.assert_allclose([f.warp for f in forced], expected, atol=1e-12)
    out += forced
    late_plan = solve(s, late_job)
    # Its start no longer matches what was settled: it is joined to the last settled frame,
    # the offset fading out, and it plans what follows.
    assert s.stale == 0 and s.path.rejoined == 1
    last = s.path.settled - 1
    window, _ = late_job
    np.testing.assert_allclose(s.path._plan[last - window.first], s.path._tail[-1], atol=1e-12)
    far = last + s.path.rejoin
    np.testing.assert_allclose(s.path._plan[far - window.first:], late_plan[far - window.first:], atol=1e-12)

    # The rest of the stream, then its end: every frame out once, in order.
    arrive(s, clock, pairwise, range(40, n))
    s.end_motion()
    while (job := s.next_window()) is not None:
        solve(s, job)
        out += take_ready(s)
    assert s.next_frame() is None
    assert len(out) == n == len(s.warps)
    assert [int(f.pixels[0, 0]) for f in out] == [k % 256 for k in range(n)]
    assert s.path.settled == n


def test_frames_before_any_plan_leave_at_their_deadline_unwarped():
    clock = Clock()
    s = schedule(clock)
    arrive(s, clock, shaky_pan(40), range(20))
    clock.now = 5.0  # the solver stalled: every frame is past its deadline, and nothing was planned
    out = take_ready(s)
    assert len(out) == 20 and s.late == 20 and s.path.held == 20
    np.testing.assert_allclose([f.warp for f in out], np.tile(np.eye(3), (20, 1, 1)), atol=1e-12)


def test_a_file_has_no_deadlines_and_waits_for_its_lookahead():
    clock = Clock()
    s = schedule(clock, realtime=False)
    arrive(s, clock, shaky_pan(30), range(30))
    clock.now = 100.0
    assert take_ready(s) == []
    assert s.late == 0 and s.lookahead() == 10
    solve(s, s.next_window())
    assert s.path.settled == 30 - 10 and s.late == 0


def test_the_lookahead_shrinks_while_tracking_is_slow_and_comes_back():
    clock = Clock()
    s = schedule(clock, horizon=Horizon(step=5, lookahead=17))
    assert s.lookahead() == 17  # nothing measured yet: the horizon's
    for lag in (0.1, 0.3, 0.6, 0.9):
        for _ in range(60):
            s.track_lag.add(lag)
        shorter = s.lookahead()
        assert MIN_LOOKAHEAD <= shorter <= 17
        # A frame settles (lookahead + step - 1) frames after it arrived, plus the lag: in time.
        if shorter > MIN_LOOKAHEAD:
            assert (shorter + 4) / FPS + lag + s.reserve() <= 1.0
    assert shorter == MIN_LOOKAHEAD
    for _ in range(60):
        s.track_lag.add(0.05)
    assert s.lookahead() == 17
    assert s.reserve() == ENCODE_RESERVE  # nothing rendered yet


def test_a_frame_settled_past_the_plans_known_motion_keeps_the_planned_path():
    """The plan predicted frames N.. with the recent mean motion; they really shook.  Settled
    from that plan, their views must put the output where the plan's path is (camera @
    transform), not where its transforms would with the predicted camera."""
    from mosaic_cli.stabilize.path import fit_model, to_normalized

    n, model = 30, motion_model("similarity")
    pairwise = shaky_pan(n + 8, seed=5)
    path = OnlineL1Path(model, SIZE, None, Horizon(step=4, lookahead=10), recover=0.0)
    for t in range(n):
        path.push(None if t == 0 else pairwise[t - 1])
    window = path.pose()
    plan = path.solve(window)
    assert path.adopt(window, plan)
    for t in range(n, n + 6):  # their motion arrives, different from the prediction
        path.push(pairwise[t - 1])
    views = path.commit(n + 6)  # frames 0 .. n + 5 (no --crop: the views are the transforms)
    first = window.first
    real = np.eye(3)
    predicted = np.eye(3)
    for t in range(n, n + 6):
        real = real @ fit_model(np.linalg.inv(to_normalized(pairwise[t - 1], SIZE)), model)
        predicted = predicted @ window.motion[t - 1 - first]
        np.testing.assert_allclose(real @ views[t], predicted @ model.matrices(plan[t - first]), atol=1e-9)
    assert path.held == 0


def test_a_frame_settled_past_the_plans_known_motion_returns_to_the_last_planned_transform():
    """``recover`` pulls such a frame's transform towards the plan's last known frame's: with
    1, the transform is that one (the output moves with the camera from there)."""
    n, model = 30, motion_model("similarity")
    pairwise = shaky_pan(n + 8, seed=5)
    path = OnlineL1Path(model, SIZE, None, Horizon(step=4, lookahead=10), recover=1.0)
    for t in range(n + 6):
        path.push(None if t == 0 else pairwise[t - 1])
        if t == n - 1:
            window = path.pose()
            plan = path.solve(window)
            assert path.adopt(window, plan)
    views = path.commit(n + 6)
    np.testing.assert_allclose(views[n:], np.repeat(model.matrices(plan[n - 1 - window.first])[None], 6, axis=0), atol=1e-9)
