"""Scheduling the learned estimator's frame pairs: chunks, the pool of threads, the look-ahead.

A chunk's frames are described and its pairs checked on a pool of ``--threads`` threads (OpenCV
lets go of the GIL) while the network runs; the pairs are then decided in order, so that the
estimates are the same, to the bit, on any number of threads.  With ``lookahead`` (a video file's
pass) a chunk's checks run while the next chunk's network does, its estimates told a chunk late.
On a GPU (or ``polish-with=torch``) the chunk's checks are first batched on the device; only the
pairs they do not settle go to the pool.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from mosaic_cli.device import pair_threads
from mosaic_cli.estimators.base import PairEstimate
from mosaic_cli.estimators.learned_batch_checks import BatchedPairChecks
from mosaic_cli.estimators.learned_checks import WorkFrame
from mosaic_cli.estimators.learned_network import NetworkRun


class PairSchedule(NetworkRun, BatchedPairChecks):
    """The scheduling of :class:`~mosaic_cli.estimators.learned.LearnedEstimator`: each chunk's
    network (:class:`.NetworkRun`), its pairs' checks on the pool and their decisions in order
    (:class:`.BatchedPairChecks`)."""

    # Set by LearnedEstimator (__init__, reset).
    threads: int | None
    _workers: int  # the pool's threads for this video
    _pool: ThreadPoolExecutor | None
    _pool_size: int
    _pending: list[WorkFrame]  # the frames of the chunk being filled
    _ahead: tuple | None  # the chunk checked on the pool while the next one's network runs (lookahead)
    _batched: bool  # the chunk's LK polish and check batched on the device (polish-with)

    def _run_chunk(self) -> list[PairEstimate]:
        frames = self._pending
        self._pending = [frames[-1]]  # the last frame starts the next chunk's first pair
        pool = self._pair_pool()
        if pool is not None and self._looks_ahead(pool):
            return self._run_ahead(frames, pool)
        assert self._ahead is None, "a chunk looked ahead and the next did not"  # (the settings are a video's)
        described = self._read_frames(frames, pool)  # on the pool: while the network runs
        pairs = list(zip(frames[:-1], frames[1:]))
        if self.config.polish_start == "velocity":  # each pair starts from the one before: no batch, in turn
            described()
            return [self._finish_pair(prev, cur, self._motion, True, 1.0) for prev, cur in pairs]
        seeds, offsets_ok, agreement = self._seeds(frames)
        described()
        if self._batched:
            return self._finish_batched(pairs, seeds, offsets_ok, agreement, pool)
        if pool is None:  # one thread: each pair finished in turn
            return [self._finish_pair(prev, cur, seeds[k], offsets_ok[k], agreement[k]) for k, (prev, cur) in enumerate(pairs)]
        self._valid_pixels()  # made once, before the threads read it
        checks = pool.map(lambda k: self._check(pairs[k][0], pairs[k][1], seeds[k], bool(offsets_ok[k])), range(len(pairs)))
        # map yields in the pairs' order: each decided once those before it are
        return self._decide_all(pairs, seeds, offsets_ok, agreement, checks)

    def frames_held(self, lookahead: bool = False) -> int:
        """A chunk less one (its pairs are told once the chunk is full), and with ``lookahead``
        and a pool a chunk more (told when the next one is full: :meth:`_run_ahead`)."""
        workers = self.threads if self.threads is not None else pair_threads()
        ahead = lookahead and workers > 1 and self._can_look_ahead()
        return self.config.chunk - 1 + (self.config.chunk if ahead else 0)

    def _can_look_ahead(self) -> bool:
        """Whether a chunk's network reads nothing the decisions of the chunk before leave (no
        motion prior, no velocity seed), and its checks run on the pool (the batched polish waits
        on the device's one copy back anyway)."""
        return self.config.polish_start == "network" and not self._prior_warp and not self._batched

    def _looks_ahead(self, pool: ThreadPoolExecutor | None) -> bool:
        """Whether this chunk's network runs while the chunk before is checked (``lookahead``)."""
        return self.lookahead and pool is not None and self._can_look_ahead()

    def _run_ahead(self, frames: list[WorkFrame], pool: ThreadPoolExecutor) -> list[PairEstimate]:
        """:meth:`_run_chunk` a chunk late: this chunk's network runs on this thread while the
        pool checks the chunk before, whose pairs are then decided and returned; this chunk's
        checks start on the pool (decided at the next chunk, or at :meth:`finish`).  The same
        estimates, in the same order, as without the lookahead."""
        described = self._read_frames(frames, pool)
        pairs = list(zip(frames[:-1], frames[1:]))
        seeds, offsets_ok, agreement = self._seeds(frames)
        described()
        out = self._decide_ahead()
        self._valid_pixels()  # made once, before the threads read it
        futures = [pool.submit(self._check, prev, cur, seeds[k], bool(offsets_ok[k])) for k, (prev, cur) in enumerate(pairs)]
        self._ahead = (pairs, seeds, offsets_ok, agreement, futures)
        return out

    def _decide_ahead(self) -> list[PairEstimate]:
        """The pairs of the chunk whose checks run ahead, decided in order (none: [])."""
        if self._ahead is None:
            return []
        pairs, seeds, offsets_ok, agreement, futures = self._ahead
        self._ahead = None
        return self._decide_all(pairs, seeds, offsets_ok, agreement, (f.result() for f in futures))

    def _decide_all(self, pairs: list[tuple[WorkFrame, WorkFrame]], seeds: np.ndarray, offsets_ok: np.ndarray,
                    agreement: np.ndarray, checks) -> list[PairEstimate]:
        """The chunk's pairs decided in order from their checks (an iterable in the pairs' order)."""
        return [self._decide(prev, cur, seeds[k], agreement[k], check) for k, ((prev, cur), check) in enumerate(zip(pairs, checks))]

    def _finish_batched(self, pairs: list[tuple[WorkFrame, WorkFrame]], seeds: np.ndarray, offsets_ok: np.ndarray,
                        agreement: np.ndarray, pool: ThreadPoolExecutor | None) -> list[PairEstimate]:
        """The chunk's pairs with the polish and check batched on the device (:meth:`_batch_checks`);
        the pairs it does not settle are checked by :meth:`_check` as without it, on the pool."""
        settled = self._batch_checks(pairs, seeds, offsets_ok)
        todo = [k for k, check in enumerate(settled) if check is None]
        if pool is None:
            checked = {k: self._check(pairs[k][0], pairs[k][1], seeds[k], bool(offsets_ok[k])) for k in todo}
        else:
            self._valid_pixels()  # made once, before the threads read it
            checked = dict(zip(todo, pool.map(lambda k: self._check(pairs[k][0], pairs[k][1], seeds[k], bool(offsets_ok[k])), todo)))
        checks = [check if check is not None else checked[k] for k, check in enumerate(settled)]
        return self._decide_all(pairs, seeds, offsets_ok, agreement, checks)

    def _finish_pair(self, prev: WorkFrame, cur: WorkFrame, seed: np.ndarray, offsets_ok: bool, agreement: float) -> PairEstimate:
        """Polish the seed, confirm it by the correlation of the registered detail, and where the
        learned path cannot confirm the pair, let the classical fallback try it."""
        return self._decide(prev, cur, seed, agreement, self._check(prev, cur, seed, offsets_ok))

    def close(self) -> None:
        """Stop the pool's threads: idle workers would otherwise outlive the run (a live run's
        estimator, built beside the stream with the garbage collector frozen, is never collected)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool, self._pool_size = None, 0

    def _pair_pool(self) -> ThreadPoolExecutor | None:
        """The pool of this video's threads; None for one thread."""
        if self._workers <= 1:
            return None
        if self._pool is None or self._pool_size != self._workers:
            if self._pool is not None:
                self._pool.shutdown(wait=False)
            self._pool = ThreadPoolExecutor(self._workers, thread_name_prefix="mosaic-pairs")
            self._pool_size = self._workers
        return self._pool

    def _read_frames(self, frames: list[WorkFrame], pool: ThreadPoolExecutor | None) -> Callable[[], None]:
        """Read the frames not yet read (:meth:`_read_frame`): now, in turn, without a pool;
        with one, their own part on the pool (:meth:`_texture`), and the call returned waits for it
        and tells the spoilt frames in the flight's order (:meth:`_judge_spoilt`)."""
        todo = [f for f in frames if f.textured is None]
        if pool is None:
            for f in todo:
                self._read_frame(f)
            return lambda: None
        futures: list[Future] = [pool.submit(self._texture, f) for f in todo]

        def described() -> None:
            for f, future in zip(todo, futures):
                future.result()
                self._judge_spoilt(f)

        return described
