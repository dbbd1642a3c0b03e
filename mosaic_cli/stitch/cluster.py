"""The stitch's work on a Dask cluster (``dask.distributed``, the ``cluster`` extra).

``--workers N`` starts N local worker processes; ``--scheduler tcp://HOST:PORT`` uses a running
cluster.  Two stages are spread over its workers: the scans (stitch/flights.py: one task a
flight, and a video at least two segments long cut into segments, one task a segment; the
register stage joins the segments as it joins the parts of a flight after a cut) and the compose
stage's tiles (one task a tile; each worker keeps the keyframes it read for the next tiles).
Seams and exposure are still decided once, here, on small copies; each tile is blended by the
same code as in one process (compose.compose_tile), so the composed panorama is the same to the
bit for the same placements.  Tasks lost with a worker are run again by Dask on another.  The
workers read the inputs and the keyframe pixels from the disk the stitch works on: a cluster on
other machines needs that folder shared (checked before any work).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mosaic_cli.errors import BadInput, ProcessingError, install_hint
from mosaic_cli.stitch.compose import ComposePlan, HeldKeyframes, TileSink, compose_tile

CONNECT_SECONDS = 5  # a scheduler that does not answer within this is one line, not a hang
IN_FLIGHT = 2  # tiles queued per worker: enough to keep each busy, few enough to bound the results held


@dataclass(frozen=True)
class ClusterOptions:
    workers: int | None = None  # local worker processes; None: no cluster of our own
    scheduler: str | None = None  # tcp://HOST:PORT of a running cluster
    # A video is cut into segments scanned at once, one a worker, each at least this many frames
    # (stitch/workers.py, segment_ranges): 40 s at 30 fps, so that a worker's own estimator and
    # overlay search (a few seconds) stay a small share of its segment's scan.
    segment_frames: int = 1200

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if self.segment_frames < 1:
            raise ValueError(f"segment_frames must be 1 or more, got {self.segment_frames}")
        if self.workers is not None and self.workers < 1:
            raise BadInput(f"--workers must be 1 or more, got {self.workers}")
        if self.workers is not None and self.scheduler is not None:
            raise BadInput("--workers starts a cluster here, --scheduler uses a running one: give one of them")
        if self.scheduler is not None and "://" not in self.scheduler:
            raise BadInput(f"--scheduler must be an address such as tcp://HOST:PORT, got {self.scheduler!r}")

    @property
    def wanted(self) -> bool:
        return self.workers is not None or self.scheduler is not None


@contextlib.contextmanager
def connect(options: ClusterOptions, workdir: str | Path) -> Iterator[Any]:
    """A ``distributed.Client`` for ``options`` (None when no cluster is asked), its workers
    checked to see ``workdir``; a local cluster is closed on leaving."""
    if not options.wanted:
        yield None
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise BadInput(f"--workers and --scheduler need the cluster extra: {install_hint('cluster')}") from None
    import dask

    with contextlib.ExitStack() as stack:
        with dask.config.set({"distributed.comm.timeouts.connect": f"{CONNECT_SECONDS}s", "logging.distributed": "error"}):
            if options.workers is not None:
                cluster = stack.enter_context(LocalCluster(n_workers=options.workers, threads_per_worker=1, processes=True,
                                                           host="127.0.0.1", dashboard_address=None, silence_logs=40))
                client = stack.enter_context(Client(cluster, timeout=f"{CONNECT_SECONDS}s"))
            else:
                try:
                    client = stack.enter_context(Client(options.scheduler, timeout=f"{CONNECT_SECONDS}s"))
                except (OSError, TimeoutError) as exc:
                    raise BadInput(f"--scheduler {options.scheduler}: no Dask scheduler answered within {CONNECT_SECONDS} s "
                                   f"({type(exc).__name__})") from None
        _check_shared(client, Path(workdir))
        yield client


def _check_shared(client, workdir: Path) -> None:
    """Every worker must read what the stitch writes to ``workdir`` (the keyframe pixels)."""
    handle, name = tempfile.mkstemp(prefix=".mosaic-probe-", dir=workdir)
    os.close(handle)
    try:
        seen = client.run(os.path.exists, name)
    finally:
        os.unlink(name)
    if not seen:
        raise BadInput("the Dask cluster has no worker")
    blind = [address for address, ok in seen.items() if not ok]
    if blind:
        raise BadInput(f"{len(blind)} of the cluster's workers cannot see {workdir} (the folder the stitch works in): "
                       f"mosaic's workers need a disk shared with this machine")


def tile_runner(client) -> Callable[[ComposePlan, TileSink, Callable[..., None]], None]:
    """compose's ``runner``: the plan's tiles blended on the cluster's workers, a few queued per
    worker in canvas order, each written to the sink here as it comes back."""

    def run(plan: ComposePlan, sink: TileSink, advance: Callable[..., None]) -> None:
        from distributed import as_completed

        shared = client.scatter(plan, broadcast=True)
        queue = list(plan.tiles)
        limit = IN_FLIGHT * max(1, len(client.scheduler_info()["workers"]))
        running = as_completed()
        for _ in range(min(limit, len(queue))):
            running.add(client.submit(blend_tile, shared, *queue.pop(0), pure=False))
        for future in running:
            try:
                x0, y0, rgba = future.result()
            except Exception as exc:  # a task that failed on every worker it was given to
                raise ProcessingError(f"compose on the cluster failed: {type(exc).__name__}: {exc}") from None
            if rgba is not None:
                sink.write(x0, y0, rgba)
            advance(1)
            if queue:
                running.add(client.submit(blend_tile, shared, *queue.pop(0), pure=False))

    return run


_WORKER_HELD: dict[str, HeldKeyframes] = {}  # (on a worker) the keyframes it read, kept from one tile to the next of a plan


def blend_tile(plan: ComposePlan, x0: int, y0: int) -> tuple[int, int, np.ndarray | None]:
    """(Run on a worker.)  The tile at canvas pixel (x0, y0), as compose blends it in one
    process.  OpenCV runs on one thread here: the cluster's workers are the parallelism."""
    import cv2

    cv2.setNumThreads(1)
    key = plan.token
    if key not in _WORKER_HELD:
        _WORKER_HELD.clear()  # another plan's keyframes
        _WORKER_HELD[key] = HeldKeyframes(plan.cache_megabytes)
    return x0, y0, compose_tile(plan, x0, y0, _WORKER_HELD[key])
