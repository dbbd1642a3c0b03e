"""Benchmark estimators: latency per stage, throughput and accuracy on one clip.

Stages are timed separately, per frame:

* decode: pulling the frame out of the encoded video (``open_video``, gray, at the
  estimator's input width; every estimator with the same input width gets the very same
  decoded frames, decoded once and kept in memory);
* preprocess: ``estimator.prepare(frame)``;
* estimate: ``estimator.feed`` on the prepared frame (a batching estimator's time is spread
  over the frames of the batch it returns).

With no video, a short flight is simulated first, so accuracy (MACE, corner error, failure
rate, see :mod:`mosaic_cli.evaluate`) comes with the timings.  A video with a ``.gt.json``
beside it (a simulated flight) is scored too; any other video gives latency only.

:func:`run_flights` scores a folder of flights (every video ``X.mp4`` with its ``X.gt.json``): each
flight is decoded once and every estimator runs on the same frames; MACE pools the landmark
pairs of all flights (the paper's protocol), corner errors and failures pool the frame pairs,
and a breakdown per flight profile (paper / fast / hard ...) comes with the totals.

Estimators are named as on the command line, options included (``cnn:refine=none``); their
name is their label in the report, so one estimator can be run with several settings.

One concept a module: what is asked (:mod:`.options`), timing an estimator (:mod:`.timing`),
scoring flights (:mod:`.scoring`), running the benchmark (:mod:`.run`) and its tables (:mod:`.render`).
"""

from mosaic_cli.bench.options import DEFAULT_ESTIMATORS, BenchOptions, check_request, simulated_flight
from mosaic_cli.bench.render import render_flights_table, render_table
from mosaic_cli.bench.run import bench, build_estimators, run_bench, run_flights
from mosaic_cli.bench.scoring import Flight, FlightScore, find_flights, pool, score_flight
from mosaic_cli.bench.timing import StageTimes, decode_frames, gpu_batch, time_estimator, warm_up

__all__ = [
    "DEFAULT_ESTIMATORS",
    "BenchOptions",
    "Flight",
    "FlightScore",
    "StageTimes",
    "bench",
    "build_estimators",
    "check_request",
    "decode_frames",
    "find_flights",
    "gpu_batch",
    "pool",
    "render_flights_table",
    "render_table",
    "run_bench",
    "run_flights",
    "score_flight",
    "simulated_flight",
    "time_estimator",
    "warm_up",
]
