"""A live command's network loaded beside the opening of its stream: the socket listens at once
(a sender that connects within a second is not refused), and the frames that come meanwhile
queue.  ``python -m benchmarks live listen`` times it."""

from __future__ import annotations

import concurrent.futures
import contextlib
import gc
import json
import sys
import threading
from collections.abc import Callable, Iterator
from typing import TypeVar

T = TypeVar("T")

# The interpreter's switch interval while the network loads (seconds; Python's default 0.005):
# torch's import runs Python code for seconds and holds the interpreter lock up to this long each
# time a live thread (the reader, ORB, the solver, the warps) asks for it.
LOADING_SWITCH_INTERVAL = 0.0005


def built_beside(build: Callable[[], T], after_start: bool = False, in_this_process: bool = True) -> concurrent.futures.Future:
    """``build()`` on a thread of its own: its result (or its error) when the future is asked.

    ``after_start``: the build waits for :func:`begin` (which :func:`waited_for` also calls on
    its way out, so that nothing waits for a build that never began).  A live command begins it
    once its decoder has started: on a cold machine, torch's import reads a gigabyte of
    libraries, and beside it the decoder took seconds to listen (``python -m benchmarks live listen --cold``).

    The cyclic garbage collector waits meanwhile, and what the build made is then frozen out of
    its later passes: torch's import makes hundreds of thousands of objects, and collecting
    while it ran stopped every thread of a live run for up to 0.1 s, a few hundred times, as
    the first frames came in (``python -m benchmarks live stabilize``, cold runs).  Meanwhile the interpreter
    hands its lock on every :data:`LOADING_SWITCH_INTERVAL`: at Python's 5 ms, 3 of 4 cold runs
    left 5-11 of their first frames at their deadline, at 0.5 ms none of 8.  None of this where
    ``in_this_process`` is False: the build only waits for another process to load (:mod:`.network_process`)."""
    future: concurrent.futures.Future = concurrent.futures.Future()
    go = threading.Event()
    future.begin = go.set  # type: ignore[attr-defined]
    if not after_start:
        go.set()

    def run() -> None:
        go.wait()
        collecting = gc.isenabled() and in_this_process
        if collecting:
            gc.disable()
        interval = sys.getswitchinterval()
        if in_this_process:
            sys.setswitchinterval(min(interval, LOADING_SWITCH_INTERVAL))
        result: T | None = None
        error: BaseException | None = None
        try:
            result = build()
        except BaseException as exc:  # noqa: BLE001 - raised to whoever asks for the result
            error = exc
        finally:  # (before the result is told: whoever waits for it finds things as they were)
            sys.setswitchinterval(interval)
            if collecting:
                gc.freeze()
                gc.enable()
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(result)

    threading.Thread(target=run, name="mosaic-build", daemon=True).start()
    return future


@contextlib.contextmanager
def waited_for(future: concurrent.futures.Future | None) -> Iterator[None]:
    """On the way out, wait for ``future``'s work to end, however the block ends: a network's
    loading in this process is never left half done (torch's import) as mosaic exits."""
    try:
        yield
    finally:
        if future is not None:
            begin(future)
            concurrent.futures.wait([future])


def begin(future: concurrent.futures.Future | None) -> None:
    """Let a build made with ``after_start`` begin (nothing for one that began or for None)."""
    if future is not None and hasattr(future, "begin"):
        future.begin()


def trained_width(name: str | None, weights: str | None) -> int | None:
    """The width a learned estimator (``-e name``, ``--weights``) works at, read from its
    weights' header alone (no torch); None where that cannot be read here (a bad file: the
    loading reports it, in its own words)."""
    from safetensors import safe_open

    from mosaic_cli.estimators import DEFAULT_ESTIMATOR, parse_spec
    from mosaic_cli.estimators.weights import default_weights

    base, spec = parse_spec(name if name is not None else ("" if weights else DEFAULT_ESTIMATOR))
    try:
        path = spec.get("weights") or weights or default_weights(base)
        with safe_open(str(path), framework="numpy") as fh:
            return int(json.loads((fh.metadata() or {}).get("work_size", "[320, 180]"))[0])
    except Exception:  # noqa: BLE001 - see above
        return None


__all__ = ["begin", "built_beside", "trained_width", "waited_for"]
