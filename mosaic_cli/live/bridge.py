"""A live run's tracker while its network loads (``stabilize --latency``): ORB on the frames that
come meanwhile, then the network from the last frame ORB saw (:class:`Bridged`)."""

from __future__ import annotations

import concurrent.futures

import numpy as np

from mosaic_cli.estimators import Estimator


class Bridged:
    """The network once it has loaded (``loading``), and ORB until then, on the same gray images
    (``width`` wide): a live stream's first frames, which come while the network loads, are
    tracked as they come instead of waiting for it.  The network starts from the last frame
    ORB saw, so that no pair is lost or estimated twice."""

    def __init__(self, loading: concurrent.futures.Future, width: int, use: np.ndarray | None, size: tuple[int, int]):
        from mosaic_cli.estimators import OrbEstimator

        self.loading, self.use, self.size = loading, use, size
        self.orb = OrbEstimator(width)
        self.orb.set_mask(use)
        self.orb.reset(size)
        self.current: Estimator = self.orb
        self.bridged = 0  # frames ORB took
        self.name = "network"  # the network's name, once it has loaded
        self._last: np.ndarray | None = None

    def feed(self, gray: np.ndarray) -> list:
        handed = []
        if self.current is self.orb and self.loading.done():
            network = self.loading.result()  # (its error, if loading failed: the track stage's)
            network.set_mask(self.use)
            network.reset(self.size)
            self.name = network.name
            handed = self.orb.finish()
            if self._last is not None:
                handed += network.feed(self._last)  # its first frame: no pair yet
            self.current = network
        if self.current is self.orb:
            self.bridged += 1
        self._last = gray
        return handed + self.current.feed(gray)

    def finish(self) -> list:
        return self.current.finish()

    @property
    def loaded(self) -> bool:
        """Whether the network has taken over from ORB."""
        return self.current is not self.orb

    @property
    def orb_pairs(self) -> int:
        """The pairs ORB estimated: those between the frames it took (it holds none back; the
        pair from its last frame to the network's first is the network's)."""
        return max(0, self.bridged - 1)
