"""Tracking that starts before the overlays are known, and starts again if one is found.

Overlay detection reads frames spread over the whole clip (a few seconds on a 4K one), and the
mask it makes changes every estimate.  Rather than wait for it, a tracking pass (an *attempt*)
starts with the mask known so far (:attr:`~.merge.PendingMask.known`: the ``--mask`` file's, or
none) while the detection goes on.  What the attempt tells anyone else (the pairs to stabilize's
path planner, its progress) is held back by its :class:`Gate` until the mask has settled:

- settled as the attempt started (no overlay found, the usual case): what was held is let
  through in order, and the attempt goes on; its results are those of a pass started with the
  final mask, bit for bit (the same frames, the same mask, the same estimator state);
- settled otherwise (an overlay found): :class:`MaskChanged` ends the attempt wherever it is,
  what it held is dropped, and :func:`speculate` runs a new attempt from the first frame with the
  final mask (a fresh decoder, the estimator reset): the results are those the sequential
  order gave.

The gate looks at the detection between frames (:meth:`Gate.frames`) and waits for it at the
attempt's end (:meth:`Gate.wait`).  An attempt that holds more than the gate can see (stitch's
scanner: keyframes, their spilled pixels) drops it when :class:`MaskChanged` passes through it.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from mosaic_cli.overlay.merge import FrameMask, PendingMask

R = TypeVar("R")
F = TypeVar("F")


class MaskChanged(Exception):
    """The mask settled unlike the one the attempt started with: what it did is void."""

    def __init__(self, mask: FrameMask):
        super().__init__("the overlay mask changed: tracking starts again")
        self.mask = mask


def same_mask(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    """Whether two use masks ((h, w) uint8, or None: everything used) keep the same pixels out."""
    if a is None or b is None:
        return a is b
    return a.shape == b.shape and bool(np.array_equal(a, b))


@dataclass(eq=False)
class Gate:
    """One attempt's view of the pending mask.  ``use``: the mask it runs with; ``pending``: the
    detection, while it may still change the mask (None once settled, or from the start);
    ``restarted``: this attempt replaces one whose mask was wrong (its side state, such as a
    rolling-shutter probe it fed, starts over).  Used from the attempt's thread only."""

    pending: PendingMask | None = None
    use: np.ndarray | None = None
    restarted: bool = False
    waited: float = 0.0  # seconds :meth:`wait` waited for the detection at the attempt's end
    _held: list[Callable[[], Any]] = field(default_factory=list, init=False, repr=False)

    @property
    def settled(self) -> bool:
        return self.pending is None

    def emit(self, effect: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """``effect(*args, **kwargs)`` now once the mask is settled, else when it settles as
        this attempt's (in order), or never (it settled otherwise)."""
        if self.pending is None:
            effect(*args, **kwargs)
        else:
            self._held.append(functools.partial(effect, *args, **kwargs))

    def frames(self, frames: Iterable[F]) -> Iterator[F]:
        """``frames``, the detection looked at before each (:meth:`poll`)."""
        for frame in frames:
            self.poll()
            yield frame

    def poll(self) -> None:
        """If the detection has ended: settle (the held effects run, or :class:`MaskChanged`)."""
        if self.pending is not None and self.pending.done():
            self._settle(self.pending.result())

    def wait(self) -> None:
        """At the attempt's end: wait for the detection, then settle as :meth:`poll`."""
        if self.pending is not None:
            clock = time.perf_counter()
            mask = self.pending.result()
            self.waited += time.perf_counter() - clock
            self._settle(mask)

    def _settle(self, mask: FrameMask) -> None:
        self.pending = None
        held, self._held = self._held, []
        if not same_mask(mask.use, self.use):
            raise MaskChanged(mask)
        for effect in held:
            effect()


@dataclass
class Speculation:
    """What the pending mask cost a tracking pass: ``restarted``, an overlay was found after the
    pass had started without it (its first attempt discarded, ``lost_seconds`` of it); and
    ``waited_seconds``, the pass's end waiting for the detection."""

    restarted: bool = False
    lost_seconds: float = 0.0
    waited_seconds: float = 0.0

    @property
    def seconds(self) -> float:
        """The pass's wall time that went to the overlays rather than to its kept estimates."""
        return self.lost_seconds + self.waited_seconds

    def to_meta(self) -> dict:
        """The track file's ``meta`` keys (docs/guide/track.md)."""
        return {"overlay_restart": self.restarted, "overlay_wait_seconds": self.waited_seconds,
                "overlay_lost_seconds": self.lost_seconds}


def speculate(pending: PendingMask, attempt: Callable[[np.ndarray | None, Gate], R]) -> tuple[R, Speculation]:
    """``attempt(use, gate)`` with the mask known so far (or the final one, when the detection
    has already ended), then, if the mask settles otherwise, once more from the start with the
    final one (see the module docstring).  ``attempt`` sets ``use`` on its estimator (and
    anything else that reads the mask), feeds its frames through ``gate.frames``, sends what
    others see through ``gate.emit``, and ends with ``gate.wait()`` when it has more to drop
    than its return value.

    Errors: the detection's is raised where the attempt sees it, ending the attempt.  An error
    of the attempt while the detection still runs waits for the detection, whose error (the
    one the sequential order raised, the detection running first) is raised in its place; else
    the attempt's own.  Ctrl-C (any BaseException not an Exception) is raised at once: the
    caller's ``with pending:`` stops the detection."""
    outcome = Speculation()
    if pending.done():
        gate = Gate(None, pending.result().use)
    else:
        gate = Gate(pending, pending.known)
    clock = time.perf_counter()
    try:
        result = attempt(gate.use, gate)
        gate.wait()
    except MaskChanged as changed:
        outcome.restarted, outcome.lost_seconds = True, time.perf_counter() - clock
        gate = Gate(None, changed.mask.use, restarted=True)
        result = attempt(gate.use, gate)
    except Exception:
        if gate.pending is not None:
            gate.pending.result()  # raises the detection's error, if it failed
        raise
    outcome.waited_seconds = gate.waited
    return result, outcome


__all__ = ["Gate", "MaskChanged", "Speculation", "same_mask", "speculate"]
