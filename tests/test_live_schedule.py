"""The live stabiliser's schedule (mosaic_cli/live/schedule.py): deadlines, late solves and the
adaptive lookahead, driven step by step with a test clock (no threads, nothing timed)."""

from __future__ import annotations

import numpy as np

from mosaic_cli.live.schedule import BURST_PACE, ENCODE_RESERVE, LiveSchedule
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


def schedule(clock: Clock, realtime: bool = True, horizon: Horizon = Horizon(step=4, lookahead=10),
             render_guess: float = 0.0) -> LiveSchedule:
    path = OnlineL1Path(motion_model("similarity"), SIZE, None, horizon)
    return LiveSchedule(path, SIZE, FPS, latency=1.0, realtime=realtime, capacity=10_000, clock=clock,
                        render_guess=render_guess)


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
    while s._frames and (s._frames[0].warp is not None or (s.realtime and s.clock() >= min(s._start_by()))):
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


def test_a_burst_of_frames_is_begun_early_enough_for_its_last_frame():
    """20 frames arrive at once (what a decoder held while it probed the stream) and none can be
    planned (the solver is still busy).  The renderer takes a frame at a time: it must begin
    early enough that the last of them is handed over within its budget, not only the first."""
    clock, render = Clock(), 0.03
    s = schedule(clock, render_guess=render)
    for k in range(20):
        s.add_frame(np.zeros((SIZE[1] * 3 // 2, SIZE[0]), np.uint8), 0.0)
        s.add_motion(None if k == 0 else np.eye(3))
    budget_ends = [f.start + s.latency - ENCODE_RESERVE for f in s._frames]
    handed = []
    while len(handed) < 20:  # the renderer on the test clock: 1 ms ticks, `render` a frame
        for _ in take_ready(s):
            clock.now += render
            handed.append(clock.now)
        clock.now += 0.001
    tick = 0.001  # (the renderer is woken at the first tick at or after a frame is due)
    assert all(h <= end + tick for h, end in zip(handed, budget_ends))
    # Not begun needlessly early: the last frame leaves within a tick of its budget's end.
    assert abs(budget_ends[-1] - handed[-1]) <= tick
    # (Begun at the first frame's own deadline, the last would have left too late.)
    assert budget_ends[0] - render + 20 * render > budget_ends[-1]


def test_a_frames_budget_counts_from_its_arrival_up_to_twice_the_frame_rate():
    clock = Clock()
    s = schedule(clock)
    frame = np.zeros((SIZE[1] * 3 // 2, SIZE[0]), np.uint8)
    # Real time: each from its arrival, however late mosaic takes it.
    starts = []
    for k in range(5):
        clock.now = k / FPS + 0.2  # taken 0.2 s after it arrived
        starts.append(s.add_frame(frame, k / FPS))
    np.testing.assert_allclose(starts, np.arange(5) / FPS)
    # Faster than twice the rate (a file piped in, all there at once): at that pace.
    piped = schedule(Clock())
    starts = [piped.add_frame(frame, 0.0) for _ in range(5)]
    np.testing.assert_allclose(starts, np.arange(5) / (BURST_PACE * FPS))
    # A file read in one pass: when taken.
    file = schedule(clock, realtime=False)
    clock.now = 3.0
    assert file.add_frame(frame, 1.0) == 3.0


def test_a_due_frame_is_never_held_back_by_a_tracker_that_fell_behind():
    """The decode stage waits for the tracker's queue only with frames whose budget has not
    started (a file piped in): a live frame that is due goes on to the renderer's deadlines."""
    import queue
    import threading

    from mosaic_cli.live.stabilize import TRACK_QUEUE, _put

    clock = Clock()
    s = schedule(clock)
    inbox: queue.Queue = queue.Queue()
    for _ in range(TRACK_QUEUE):
        inbox.put("behind")
    clock.now = 5.0
    _put(s, inbox, "due", start=4.0)
    assert inbox.qsize() == TRACK_QUEUE + 1

    inbox = queue.Queue()
    for _ in range(TRACK_QUEUE):
        inbox.put("behind")
    drained = threading.Event()

    def tracker() -> None:
        inbox.get()
        drained.set()

    threading.Timer(0.05, tracker).start()
    _put(s, inbox, "early", start=60.0)  # its budget starts in a minute: it waits for the tracker
    assert drained.is_set() and inbox.qsize() == TRACK_QUEUE

    # A tracker as many frames behind as may be in flight holds even a due frame (bounded memory).
    small = LiveSchedule(OnlineL1Path(motion_model("similarity"), SIZE, None, Horizon(step=4, lookahead=10)), SIZE, FPS,
                         latency=1.0, realtime=True, capacity=0, clock=clock)
    inbox = queue.Queue()
    for _ in range(small.capacity):
        inbox.put("behind")
    drained.clear()
    threading.Timer(0.05, tracker).start()
    _put(small, inbox, "due", start=4.0)
    assert drained.is_set() and inbox.qsize() == small.capacity
