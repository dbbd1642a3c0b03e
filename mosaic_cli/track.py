"""Track: decode a video as a stream and estimate every pairwise homography (frame t -> t+1).

``mosaic track``'s pipeline, which picks between this pass, a live input's and JSON Lines
(``live/track.py``), is :func:`mosaic_cli.track_pipeline.track`."""

from __future__ import annotations

import contextlib
import itertools
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosaic_cli.atomic import atomic_path
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import Estimator, estimate_stream
from mosaic_cli.estimators.rolling import BandPlan, RollingProbe, parse_rolling_shutter, plan_bands
from mosaic_cli.geometry.rolling_shutter import CHANNELS, band_centres
from mosaic_cli.inputs import DEFAULT_TIMEOUT, check_max_frames, check_threads, check_timeout
from mosaic_cli.overlay import FrameMask, Gate, MaskOptions, PendingMask, speculate
from mosaic_cli.progress import progress_task
from mosaic_cli.video import VideoInfo, open_video
from mosaic_cli.video.lens_filter import ImageFilter
from mosaic_cli.video.policy import Shortfall
from mosaic_cli.video.stream import VideoStream

TRACK_FORMAT_VERSION = 1


@dataclass
class TrackOptions:
    """``mosaic track``'s options besides the estimator's (see :func:`mosaic_cli.estimators.make_estimator`)."""

    max_frames: int | None = None  # None: every frame
    threads: int | None = None  # a learned estimator's threads: its per-pair pool and torch's (None: one a core, and one)
    timeout: float = DEFAULT_TIMEOUT  # a live input ends when it sends nothing for this long
    mask: MaskOptions = field(default_factory=MaskOptions)  # --mask, burned-in overlays
    rolling_shutter: str | float = "off"  # auto, off or a readout: the row bands' motion in the track file

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        parse_rolling_shutter(self.rolling_shutter)
        check_max_frames(self.max_frames)
        check_threads(self.threads)
        check_timeout(self.timeout)


@dataclass
class TrackResult:
    info: VideoInfo
    estimator: str
    pairwise: np.ndarray  # (N-1, 3, 3), frame t -> t+1, full-resolution pixels
    confidence: np.ndarray  # (N-1,)
    meta: dict = field(default_factory=dict)
    paths: list[str] | None = None  # the learned estimator: which path made each pair
    # --rolling-shutter: the "rolling_shutter" block of the track file (see rolling_block)
    rolling: dict | None = None

    @property
    def frames(self) -> int:
        return len(self.pairwise) + 1

    def to_json(self) -> dict:
        doc = self._header()
        doc["pairwise"] = [[[float(v) for v in row] for row in H] for H in self.pairwise]
        doc["confidence"] = [float(c) for c in self.confidence]
        if self.paths is not None:
            doc["path"] = list(self.paths)
        if self.rolling is not None:
            doc["rolling_shutter"] = self.rolling
        doc["meta"] = self.meta
        return doc

    def _header(self) -> dict:
        return {
            "version": TRACK_FORMAT_VERSION,
            "frames": self.frames,
            "size": list(self.info.source_size),
            "fps": self.info.fps,
            "estimator": self.estimator,
            "direction": "t_to_t+1",
        }

    def write_json(self, fh) -> None:
        """The :meth:`to_json` document, written matrix by matrix: a long video's track is never
        held as one big list of Python floats and one big string."""
        fh.write(json.dumps(self._header())[:-1])
        fh.write(', "pairwise": [')
        for k, H in enumerate(self.pairwise):
            fh.write((", " if k else "") + json.dumps(np.asarray(H, dtype=np.float64).tolist()))
        fh.write('], "confidence": ')
        fh.write(json.dumps(np.asarray(self.confidence, dtype=np.float64).tolist()))
        if self.paths is not None:
            fh.write(', "path": ' + json.dumps(list(self.paths)))
        if self.rolling is not None:
            fh.write(', "rolling_shutter": ' + json.dumps(self.rolling))
        fh.write(', "meta": ' + json.dumps(self.meta) + "}\n")


def track_video(
    path: str | Path,
    estimator: Estimator,
    max_frames: int | None = None,
    show_progress: bool = True,
    info: VideoInfo | None = None,
    on_pair: Callable[[np.ndarray, float], None] | None = None,
    rolling_shutter: str | float = "off",
    probe: RollingProbe | None = None,
    mask: PendingMask | None = None,
    source: Callable[[Gate], VideoStream] | None = None,
    lens: ImageFilter | None = None,
) -> TrackResult:
    """Estimate the pairwise homographies of a whole video, holding one or two frames at a time.
    ``info``: the video's probe, when the caller has it; ``on_pair(H, confidence)`` is told of
    each pair as it is estimated (stabilize plans its path meanwhile).  ``rolling_shutter``
    (auto or a readout): also each row band's motion and correction, from a pass of its own
    (:func:`estimators.rolling.plan_bands`; `auto`'s probe rides on this pass's first frames), in
    ``TrackResult.rolling``.  ``probe``: fed this pass's frames (stabilize's `auto`).

    ``mask``: the use mask while the overlays are still being looked for
    (:func:`~mosaic_cli.overlay.frame_mask_pending`): the pass starts with what is known of it,
    ``on_pair`` and the progress held back until it settles, and starts again from the first
    frame if an overlay was found (:mod:`mosaic_cli.overlay.speculate`); ``meta`` then says so
    (``overlay_restart``) and what the wait cost (``overlay_wait_seconds``: the pass's end
    waiting for the detection; ``overlay_lost_seconds``: the discarded attempt), which
    ``meta["seconds"]`` leaves out.  None: the estimator's own mask, as set.

    ``source(gate)``: each attempt's frames (a stream as ``open_video(path, width, gray=True)``
    gives them) instead of a decode of ``path`` of the attempt's own: stabilize's one decode
    (:mod:`mosaic_cli.stabilize.shared_decode`), which looks at the attempt's ``gate`` while it
    waits for a frame.  ``lens``: ``path``'s frames through this filter as they are decoded
    (``--lens``: :func:`~mosaic_cli.video.decode.open_video`'s ``lens``), the rolling shutter's
    pass's too."""
    mode = parse_rolling_shutter(rolling_shutter)
    pending = mask if mask is not None else PendingMask.settled(FrameMask(estimator.mask))
    with contextlib.ExitStack() as bar:
        tracking = _TrackPass(path, estimator, max_frames, show_progress, info, on_pair, mode, probe, bar, source, lens)
        tracked, speculation = speculate(pending, tracking.attempt)
    info, probe = tracked.info, tracking.probe
    n = len(tracked.pairwise) + 1
    meta: dict = {"ms_per_frame": 1000.0 * tracked.seconds / n, "seconds": tracked.seconds, "work_width": estimator.work_width}
    if mask is not None:
        meta.update(speculation.to_meta())
    if getattr(estimator, "path_counts", None):  # the learned estimator: which path made each pair
        meta["paths"] = dict(estimator.path_counts)
    if tracked.shortfall is not None:  # read to the end, and the end came early
        meta["input"] = tracked.shortfall.as_meta()
    rolling = None
    if mode != "off":
        clock = time.perf_counter()
        plan = plan_bands(path, info, mode, show_progress, "track: rolling shutter", max_frames=n, probe=probe, lens=lens)
        meta["rolling_seconds"] = time.perf_counter() - clock + (probe.seconds if probe is not None else 0.0)
        if plan is not None:
            rolling = rolling_block(plan, info.source_size)
    paths = tracked.paths
    return TrackResult(
        info, estimator.name, np.array(tracked.pairwise).reshape(-1, 3, 3), np.array(tracked.confidence, dtype=np.float64), meta,
        [str(p) for p in paths] if paths and all(p is not None for p in paths) else None, rolling,
    )


@dataclass
class _Tracked:
    """One tracking attempt's estimates, in frame order, and its time (its wait for the mask left out)."""

    info: VideoInfo
    pairwise: list[np.ndarray]
    confidence: list[float]
    paths: list[str | None]
    seconds: float
    shortfall: Shortfall | None


class _TrackPass:
    """What the attempts of one :func:`track_video` share: the video's info (probed by the
    first), the `auto` probe (made by the first, restarted by a second), the progress bar
    (opened by the first, on ``bar``, and kept: a discarded attempt's progress was never shown)."""

    def __init__(self, path: str | Path, estimator: Estimator, max_frames: int | None, show_progress: bool,
                 info: VideoInfo | None, on_pair: Callable[[np.ndarray, float], None] | None, mode: str | float,
                 probe: RollingProbe | None, bar: contextlib.ExitStack, source: Callable[[Gate], VideoStream] | None = None,
                 lens: ImageFilter | None = None):
        self.path, self.estimator, self.max_frames, self.show_progress = path, estimator, max_frames, show_progress
        self.info, self.on_pair, self.mode, self.probe, self.bar = info, on_pair, mode, probe, bar
        self.source, self.lens = source, lens
        self._advance: Callable[..., None] | None = None

    def attempt(self, use: np.ndarray | None, gate: Gate) -> _Tracked:
        """Track from the first frame with the use mask ``use`` (see :func:`~mosaic_cli.overlay.speculate`)."""
        self.estimator.set_mask(use)
        pairwise: list[np.ndarray] = []
        confidence: list[float] = []
        paths: list[str | None] = []
        opened = (self.source(gate) if self.source is not None else
                  open_video(self.path, width=self.estimator.input_width, gray=True, info=self.info, lens=self.lens))
        with opened as stream:
            info = self.info = stream.info
            if self.mode == "auto" and self.probe is None:
                self.probe = RollingProbe(info)
            elif gate.restarted and self.probe is not None:
                self.probe.restart()
            advance = self._progress(info)
            start = time.perf_counter()
            frames = gate.frames(itertools.islice(stream, self.max_frames))
            # (a file's pass: the estimates may come a batch late, the next batch's network beside this one's checks)
            for estimate in estimate_stream(self.estimator, frames if self.probe is None else self.probe.tap(frames), info.source_size,
                                            lookahead=True):
                pairwise.append(estimate.H)
                confidence.append(estimate.confidence)
                paths.append(estimate.path)
                if self.on_pair is not None:
                    gate.emit(self.on_pair, estimate.H, estimate.confidence)
                gate.emit(advance, 1)
            elapsed = time.perf_counter() - start
        gate.wait()  # the decoder closed (and the input's end accounted for) first
        return _Tracked(info, pairwise, confidence, paths, elapsed, stream.shortfall)

    def _progress(self, info: VideoInfo) -> Callable[..., None]:
        """The progress bar's ``advance``, the bar opened at the first attempt."""
        if self._advance is None:
            total = info.frame_count if self.max_frames is None else min(self.max_frames, info.frame_count or self.max_frames)
            self._advance = self.bar.enter_context(progress_task(f"track ({self.estimator.name})", total, disable=not self.show_progress))
            self._advance(1)  # the first frame yields no pair
        return self._advance


def rolling_block(plan: BandPlan, size: tuple[int, int]) -> dict:
    """The track file's ``rolling_shutter`` block (docs/guide/track.md): the readout, the bands'
    centre rows, each pair's band motion and each frame's band corrections, as lists."""
    K = plan.motion.shape[1]
    block: dict = {"readout": float(plan.readout), "estimated": bool(plan.estimated), "applied": bool(plan.applied), "bands": K,
                   "band_rows": [float(r) for r in band_centres(size[1], K)], "channels": list(CHANNELS)}
    if plan.applied:
        block["band_motion"] = np.round(plan.motion, 6).tolist()
        block["weights"] = [float(w) for w in plan.weights]
        block["corrections"] = np.round(plan.corrections, 6).tolist()
    return block


def save_track(result: TrackResult, out: str | Path) -> None:
    """JSON (the documented format), or ``.npy`` with the (N-1, 3, 3) pairwise array."""
    out = Path(out)
    if out.suffix.lower() == ".npy":
        with atomic_path(out) as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, result.pairwise)
    else:
        with atomic_path(out) as tmp:
            with open(tmp, "w") as fh:
                result.write_json(fh)


def read_track_file(path: str | Path) -> tuple[dict, np.ndarray, tuple[int, int] | None]:
    """The one reader of the track JSON format (also accepted: a ``mosaic simulate`` ground
    truth, which shares its keys) -> (document, pairwise (N-1, 3, 3) float64, size (w, h) or
    None when the file does not say).  BadInput for anything else."""
    p = Path(path)
    if not p.exists():
        raise BadInput(f"{p}: no such file")
    if p.is_dir():
        raise BadInput(f"{p}: is a folder, not a prediction file")
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise BadInput(f"{p}: not a JSON file ({exc.__class__.__name__})") from None
    if not isinstance(data, dict) or "pairwise" not in data:
        raise BadInput(f"{p}: not a mosaic track file (no \"pairwise\" key)")
    if data.get("kind") == "mosaic-ground-truth":
        pass  # a ground truth scored against itself is fine
    elif data.get("direction", "t_to_t+1") != "t_to_t+1":
        raise BadInput(f"{p}: pairwise direction {data.get('direction')!r} is not 't_to_t+1'")
    try:
        pairwise = np.array(data["pairwise"], dtype=np.float64).reshape(-1, 3, 3)
        size = (int(data["size"][0]), int(data["size"][1])) if "size" in data else None
    except (ValueError, TypeError, IndexError, KeyError) as exc:
        raise BadInput(f"{p}: malformed pairwise homographies ({exc.__class__.__name__})") from None
    return data, pairwise, size


def load_track(path: str | Path) -> TrackResult:
    """Read a ``mosaic track`` JSON file back."""
    data, pairwise, size = read_track_file(path)
    if size is None:
        raise BadInput(f"{path}: not a mosaic track file (no \"size\" key)")
    try:
        info = VideoInfo(str(path), size, size, float(data.get("fps", 30.0)), int(data.get("frames", len(pairwise) + 1)), 0.0)
        conf = np.array(data.get("confidence", [1.0] * len(pairwise)), dtype=np.float64)
    except (ValueError, TypeError) as exc:
        raise BadInput(f"{path}: not a mosaic track file ({exc.__class__.__name__})") from None
    paths = data.get("path")
    rolling = data.get("rolling_shutter")
    return TrackResult(info, data.get("estimator", "?"), pairwise, conf, data.get("meta", {}),
                       [str(p) for p in paths] if isinstance(paths, list) and len(paths) == len(pairwise) else None,
                       rolling if isinstance(rolling, dict) else None)
