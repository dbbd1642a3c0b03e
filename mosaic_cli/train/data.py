"""Training data: raw clips -> a decoded-frame cache -> random windows of consecutive frames.

Stages:

1. ``discover_clips``: the video files and image folders under CLIPS_DIR.
2. ``build_frame_cache``: decode every clip once, in worker processes, as a stream at the
   working size in gray, into ``RUN_DIR/cache/<clip>-<key>.npy`` (uint8, (n, h, w)) with a
   ``.json`` beside it.  The cache is what makes training cheap: later steps, epochs and
   resumed runs read frames from memory-mapped files instead of running ffmpeg again, and
   the operating system keeps only the pages in use in RAM.  Its disk size is bounded by
   ``--cache-gb`` (57.6 KB per 320x180 frame, so 8 GB hold about 39 minutes of 60 fps
   video): clips longer than their share keep evenly spread segments of consecutive frames.
3. ``WindowDataset``: sample ``index`` is a window of K consecutive frames of a random clip
   at a random start, time-reversed half of the time (free augmentation: the reversed
   sequence is as valid a flight as the forward one), with M random patch top-lefts, and with
   ``flip``, mirrored left-right and/or upside down (each half of the time: a mirrored flight
   is a flight over the mirrored ground, its homographies the mirrored ones), and with
   ``bursts``, a burst of spoilt frames in that share of the windows (:mod:`.bursts`).  Every
   random choice comes from ``(seed, index)`` alone, so a resumed run sees exactly the
   samples an uninterrupted run would have seen, whatever the number of loader workers.
4. ``StepBatches``: the indices of step s for rank r of a W-process run, from step s on.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from mosaic_cli.atomic import write_json
from mosaic_cli.errors import BadInput, MosaicError
from mosaic_cli.inputs import VIDEO_SUFFIXES
from mosaic_cli.model.patches import crop
from mosaic_cli.progress import console, progress_task
from mosaic_cli.train.bursts import BURST_KEYS, draw_burst, draw_bursts
from mosaic_cli.video.reader import IMAGE_SUFFIXES, VideoInfo, open_video, probe

CACHE_FORMAT = 1
NPY_HEADER_BYTES = 128  # np.lib.format v1 header length for any (n, h, w) uint8 shape
SEGMENT_FRAMES = 128  # frames per kept segment when a clip is longer than its cache share


# ----------------------------------------------------------------------------- discovery


def _is_image_folder(path: Path) -> bool:
    return path.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir())


def discover_clips(root: str | os.PathLike) -> list[Path]:
    """The clips under ``root``: video files and folders of numbered images, recursively.

    ``root`` itself may be one video file or one image folder."""
    root = Path(root)
    if not root.exists():
        raise BadInput(f"{root}: no such file or folder")
    if root.is_file():
        return [root]
    if _is_image_folder(root) and not any(p.suffix.lower() in VIDEO_SUFFIXES for p in root.iterdir()):
        return [root]
    clips = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        here = Path(dirpath)
        for name in sorted(filenames):
            if Path(name).suffix.lower() in VIDEO_SUFFIXES and not name.startswith("."):
                clips.append(here / name)
        for d in list(dirnames):
            if _is_image_folder(here / d):
                clips.append(here / d)
                dirnames.remove(d)  # a frame folder is one clip, not a tree to search
    if not clips:
        raise BadInput(f"{root}: holds no video files ({', '.join(sorted(VIDEO_SUFFIXES))}) or image folders")
    return clips


# ----------------------------------------------------------------------------- frame fitting


def decode_width(source_size: tuple[int, int], work_size: tuple[int, int]) -> int:
    """The width to ask the decoder for so that the frame covers ``work_size`` (aspect kept)."""
    sw, sh = source_size
    ww, wh = work_size
    return max(ww, int(np.ceil(wh * sw / sh)))


def fit_to_work_size(frame: np.ndarray, work_size: tuple[int, int]) -> np.ndarray:
    """Scale ``frame`` to cover ``work_size`` and crop its centre: a similarity transform, so
    consecutive frames stay related by a homography (a plain resize would change aspect)."""
    ww, wh = work_size
    h, w = frame.shape[:2]
    if w < ww or h < wh or (w > ww and h > wh):
        scale = max(ww / w, wh / h)
        size = (max(ww, int(round(w * scale))), max(wh, int(round(h * scale))))
        interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
        frame = cv2.resize(frame, size, interpolation=interp)
        h, w = frame.shape[:2]
    x0, y0 = (w - ww) // 2, (h - wh) // 2
    return np.ascontiguousarray(frame[y0:y0 + wh, x0:x0 + ww])


# ----------------------------------------------------------------------------- cache


@dataclass(frozen=True)
class CachedClip:
    """One decoded clip: ``frames`` rows of ``file`` (uint8 (n, h, w)), split into segments of
    consecutive frames ((offset, length) pairs); windows never cross a segment boundary."""

    clip: str
    file: str
    frames: int
    segments: tuple[tuple[int, int], ...]

    def windows(self, k: int) -> int:
        return sum(max(0, length - k + 1) for _, length in self.segments)


@dataclass(frozen=True)
class DecodeJob:
    clip: str
    file: str
    work_size: tuple[int, int]
    keep: tuple[tuple[int, int], ...] | None  # frame ranges to keep; None keeps all
    max_frames: int
    info: VideoInfo  # the clip's probe, from planning the cache


def _cache_key(clip: Path, work_size: tuple[int, int], cap: int) -> str:
    st = clip.stat()
    text = json.dumps([CACHE_FORMAT, str(clip.resolve()), st.st_size, st.st_mtime_ns, list(work_size), cap])
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def _keep_ranges(estimated: int | None, cap: int) -> tuple[tuple[int, int], ...] | None:
    """Evenly spread segments of consecutive frames adding up to ``cap`` (None: keep all)."""
    if estimated is None or estimated <= cap:
        return None
    length = min(SEGMENT_FRAMES, cap)
    count = max(1, cap // length)
    starts = np.linspace(0, estimated - length, count).round().astype(int)
    return tuple((int(s), int(s) + length) for s in starts)


def share_budget(estimates: Sequence[int | None], budget_frames: int) -> list[int]:
    """Water-filling: every clip gets up to an equal share; what short clips leave is
    shared among the longer ones.  Unknown lengths count as unbounded."""
    caps = [0] * len(estimates)
    open_ = [i for i in range(len(estimates))]
    left = budget_frames
    while open_ and left > 0:
        share = left // len(open_)
        if share == 0:
            break
        still = []
        for i in open_:
            need = estimates[i] if estimates[i] is not None else float("inf")
            if need <= share + caps[i]:
                left -= int(need) - caps[i]
                caps[i] = int(need)
            else:
                still.append(i)
        if len(still) == len(open_):  # nobody is satisfied: split what is left evenly
            for i in still:
                caps[i] += share
            left -= share * len(still)
            break
        open_ = still
    return caps


def _write_npy_stream(path: Path, frames: Iterator[np.ndarray], work_size: tuple[int, int]) -> int:
    """Write uint8 frames as an .npy file without knowing their count beforehand: reserve
    the header, stream the rows, then write the header with the final shape."""
    ww, wh = work_size
    n = 0
    with open(path, "wb") as fh:
        fh.write(b"\0" * NPY_HEADER_BYTES)
        for frame in frames:
            fh.write(frame.tobytes())
            n += 1
        fh.seek(0)
        np.lib.format.write_array_header_1_0(fh, {"descr": "|u1", "fortran_order": False, "shape": (n, wh, ww)})
        if fh.tell() != NPY_HEADER_BYTES:
            raise RuntimeError("unexpected .npy header size")
    return n


def decode_clip(job: DecodeJob) -> tuple[str, CachedClip | None, str | None]:
    """Decode one clip into the cache (runs in a worker process). Returns (clip, entry, error)."""
    clip, target = Path(job.clip), Path(job.file)
    segments: list[tuple[int, int]] = []

    def kept_frames(stream) -> Iterator[np.ndarray]:
        last, kept = None, 0
        for index, frame in enumerate(stream):
            if job.keep is not None and not any(a <= index < b for a, b in job.keep):
                if index >= job.keep[-1][1]:
                    return
                continue
            if last is None or index != last + 1:  # a gap in the source starts a new segment
                segments.append((kept, 0))
            segments[-1] = (segments[-1][0], segments[-1][1] + 1)
            last, kept = index, kept + 1
            yield fit_to_work_size(frame, job.work_size)
            if kept >= job.max_frames:
                return

    tmp = target.with_name(f".{target.name}.part")
    try:
        with open_video(clip, width=decode_width(job.info.source_size, job.work_size), gray=True, info=job.info) as stream:
            n = _write_npy_stream(tmp, kept_frames(stream), job.work_size)
    except (MosaicError, OSError, RuntimeError, ValueError) as exc:
        tmp.unlink(missing_ok=True)
        return job.clip, None, _reason(job.clip, exc)
    entry = CachedClip(job.clip, str(target), n, tuple(segments))
    os.replace(tmp, target)
    write_json(target.with_suffix(".json"), asdict(entry))
    return job.clip, entry, None


def _load_entry(target: Path) -> CachedClip | None:
    meta = target.with_suffix(".json")
    if not (target.is_file() and meta.is_file()):
        return None
    try:
        data = json.loads(meta.read_text())
        return CachedClip(data["clip"], str(target), int(data["frames"]), tuple(tuple(s) for s in data["segments"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _probe(clip: str) -> tuple[str, VideoInfo | None, str | None]:
    try:
        return clip, probe(clip), None
    except (MosaicError, OSError, RuntimeError, ValueError) as exc:
        return clip, None, _reason(clip, exc)


def _reason(clip: str, exc: Exception) -> str:
    """Why ``clip`` is unusable, in one line that names it once (the reader's messages name it)."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else exc.__class__.__name__
    return text if clip in text else f"{clip}: {text}"


def _ignore_sigint() -> None:
    # Ctrl-C is handled once, by the main process; workers must not die half way through a file.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _pool(workers: int) -> ProcessPoolExecutor:
    return ProcessPoolExecutor(max_workers=workers, mp_context=get_context("fork"), initializer=_ignore_sigint)


def _map(fn, items: list, workers: int) -> Iterator:
    """``fn`` over ``items`` (results in completion order), in worker processes when asked."""
    if workers <= 0 or len(items) <= 1:
        yield from map(fn, items)
        return
    with _pool(min(workers, len(items))) as pool:
        futures = [pool.submit(fn, item) for item in items]
        from concurrent.futures import as_completed

        for future in as_completed(futures):
            yield future.result()


def build_frame_cache(
    clips: Sequence[Path],
    cache_dir: Path,
    work_size: tuple[int, int],
    window: int,
    budget_bytes: float,
    workers: int = 1,
    show_progress: bool = True,
) -> list[CachedClip]:
    """Decode every clip once into ``cache_dir`` (reusing what is already there) and return the
    usable ones; unreadable or too short clips are skipped with a warning."""
    cache_dir.mkdir(parents=True, exist_ok=True)
    frame_bytes = work_size[0] * work_size[1]
    budget_frames = int(budget_bytes // frame_bytes)
    if budget_frames < window * len(clips):
        raise BadInput(f"--cache-gb {budget_bytes / 1e9:g} cannot hold even one {window}-frame window per clip")

    infos, estimates, problems = {}, {}, {}
    for clip, info, error in _map(_probe, [str(c) for c in clips], workers):
        infos[clip], estimates[clip], problems[clip] = info, info.frame_count if info is not None else None, error
    readable = [str(c) for c in clips if problems[str(c)] is None]
    caps = dict(zip(readable, share_budget([estimates[c] for c in readable], budget_frames)))

    entries: dict[str, CachedClip] = {}
    jobs = []
    for clip in readable:
        key = _cache_key(Path(clip), work_size, caps[clip])
        target = cache_dir / f"{Path(clip).stem[:40]}-{key}.npy"
        entry = _load_entry(target)
        if entry is not None:
            entries[clip] = entry
        else:
            jobs.append(DecodeJob(clip, str(target), work_size, _keep_ranges(estimates[clip], caps[clip]), caps[clip], infos[clip]))

    if jobs:
        total = sum(min(estimates[j.clip] or 0, j.max_frames) for j in jobs) or None
        with progress_task(f"decode {len(jobs)} clips", total, unit="fr/s", disable=not show_progress) as advance:
            for clip, entry, error in _map(decode_clip, jobs, workers):
                if error is not None:
                    problems[clip] = error
                else:
                    entries[clip] = entry
                    advance(entry.frames)

    usable, skipped = [], []
    for clip in (str(c) for c in clips):
        entry = entries.get(clip)
        if problems.get(clip) is not None:
            skipped.append(problems[clip])
        elif entry is None or entry.windows(window) == 0:
            skipped.append(f"{clip}: fewer than {window} consecutive frames")
        else:
            usable.append(entry)
    if not usable:
        more = f" (and {len(skipped) - 1} more clips)" if len(skipped) > 1 else ""
        raise BadInput(f"no usable clips: {skipped[0]}{more}")
    for reason in skipped:
        console.print(f"[yellow]warning:[/] skipping {reason}")
    return usable


# ----------------------------------------------------------------------------- sampling


class WindowDataset(Dataset):
    """Sample ``index``: {"frames": uint8 (K, 1, h, w), "positions": int64 (M, 2) patch
    top-lefts (x, y), each patch fully inside the frame}."""

    def __init__(self, clips: Sequence[CachedClip], window: int, positions: int, patch: int, seed: int,
                 reverse_probability: float = 0.5, flip: bool = False, bursts: float = 0.0):
        self.clips = list(clips)
        self.window = int(window)
        self.positions = int(positions)
        self.patch = int(patch)
        self.seed = int(seed)
        self.reverse_probability = float(reverse_probability)
        self.flip = bool(flip)
        self.bursts = float(bursts)
        # Every window start of every segment, flattened: (clip index, first row) by cumulative count.
        self._segments = [(c, off, length) for c, clip in enumerate(self.clips) for off, length in clip.segments
                          if length >= self.window]
        self._cumulative = np.cumsum([length - self.window + 1 for _, _, length in self._segments])
        self._arrays: dict[int, np.ndarray] = {}  # opened lazily, per process (memory maps do not pickle)

    def __len__(self) -> int:
        return int(self._cumulative[-1])

    def _array(self, c: int) -> np.ndarray:
        if c not in self._arrays:
            self._arrays[c] = np.load(self.clips[c].file, mmap_mode="r")
        return self._arrays[c]

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_arrays"] = {}
        return state

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng([self.seed, int(index)])
        flat = int(rng.integers(len(self)))
        s = int(np.searchsorted(self._cumulative, flat, side="right"))
        c, offset, _ = self._segments[s]
        start = offset + flat - (int(self._cumulative[s - 1]) if s else 0)
        frames = np.array(self._array(c)[start:start + self.window])
        if rng.random() < self.reverse_probability:
            frames = frames[::-1].copy()
        h, w = frames.shape[1:]
        xs = rng.integers(0, w - self.patch + 1, self.positions)
        ys = rng.integers(0, h - self.patch + 1, self.positions)
        if self.flip:  # drawn last, so that a run without it sees the samples it always did
            left_right, upside_down = rng.random(2) < 0.5
            frames = np.ascontiguousarray(frames[:, ::-1 if upside_down else 1, ::-1 if left_right else 1])
        item = {
            "frames": torch.from_numpy(frames)[:, None],
            "positions": torch.from_numpy(np.stack([xs, ys], axis=1).astype(np.int64)),
        }
        if self.bursts > 0:  # drawn after everything else, like flip (see mosaic_cli.train.bursts)
            item.update({k: torch.from_numpy(v) for k, v in draw_burst(rng, self.window, self.bursts).items()})
        return item


class DeviceWindows:
    """The whole frame cache held in one uint8 tensor on the training device, and every batch of
    windows cut there with tensor indexing (``--data device``): no per-sample Python, no worker
    processes, no host-to-device copy per step.  What a GPU needs to stay busy: at 320x180 a
    million frames take 58 GB, so the cache of any run here fits an H100's memory many times.

    The draws are those of :class:`WindowDataset` (a window of consecutive frames within one
    segment, time-reversed half of the time, M patch positions, and with ``flip`` / ``bursts``
    the mirrors and the burst of :mod:`.bursts`), made in batch on the device by a generator
    seeded from ``(seed, step, rank)`` alone: a resumed run draws what an uninterrupted one did.
    ``batch`` returns what :func:`to_model_input` would: frames float in [-1, 1] on the device."""

    def __init__(self, clips: Sequence[CachedClip], window: int, positions: int, patch: int, seed: int,
                 device: torch.device, flip: bool = False, bursts: float = 0.0, reverse_probability: float = 0.5):
        self.window, self.positions, self.patch, self.seed = int(window), int(positions), int(patch), int(seed)
        self.device, self.flip, self.bursts = torch.device(device), bool(flip), float(bursts)
        self.reverse_probability = float(reverse_probability)
        parts, starts, offset = [], [], 0
        for clip in clips:
            array = np.load(clip.file, mmap_mode="r")
            for first, length in clip.segments:
                if length >= self.window:
                    parts.append(torch.from_numpy(np.array(array[first:first + length])))  # read out of the memory map
                    starts.append(torch.arange(offset, offset + length - self.window + 1))
                    offset += length
        if not parts:
            raise BadInput(f"no clip holds {self.window} consecutive frames")
        self.frames = torch.cat(parts).to(self.device)  # (N, h, w) uint8
        self.starts = torch.cat(starts).to(self.device)  # the first frame of every possible window
        self._steps = torch.arange(self.window, device=self.device)

    def __len__(self) -> int:
        return len(self.starts)

    def batch(self, step: int, batch_size: int, rank: int = 0, world: int = 1) -> dict[str, torch.Tensor]:
        g = torch.Generator(device=self.device)
        g.manual_seed((self.seed * 1_000_003 + step) * 4099 + rank * 131 + world)
        B, K, M, P = int(batch_size), self.window, self.positions, self.patch
        dev = self.device

        def uniform(*shape: int) -> torch.Tensor:
            return torch.rand(shape, generator=g, device=dev)

        first = self.starts[torch.randint(len(self.starts), (B,), generator=g, device=dev)]
        order = torch.where(uniform(B, 1) < self.reverse_probability, self._steps.flip(0), self._steps)  # (B, K)
        frames = self.frames[first[:, None] + order]  # (B, K, h, w)
        h, w = frames.shape[-2:]
        xs = torch.randint(0, w - P + 1, (B, M), generator=g, device=dev)
        ys = torch.randint(0, h - P + 1, (B, M), generator=g, device=dev)
        if self.flip:
            mirror = uniform(B, 2) < 0.5
            frames = torch.where(mirror[:, 0, None, None, None], frames.flip(-1), frames)
            frames = torch.where(mirror[:, 1, None, None, None], frames.flip(-2), frames)
        out = {"frames": frames[:, :, None].float().div_(127.5).sub_(1.0), "positions": torch.stack([xs, ys], dim=-1)}
        if self.bursts > 0:
            out.update(draw_bursts(g, B, K, self.bursts, dev))
        return out


class StepBatches(Sampler):
    """Batches of sample indices for steps ``start..steps-1`` of rank ``rank`` of ``world``:
    step s, rank r uses indices ((s * world + r) * batch) + 0..batch-1, never reused."""

    def __init__(self, start: int, steps: int, batch_size: int, rank: int = 0, world: int = 1):
        self.start, self.steps, self.batch_size, self.rank, self.world = start, steps, batch_size, rank, world

    def __iter__(self) -> Iterator[list[int]]:
        for step in range(self.start, self.steps):
            first = (step * self.world + self.rank) * self.batch_size
            yield list(range(first, first + self.batch_size))

    def __len__(self) -> int:
        return max(0, self.steps - self.start)


def _worker_init(_: int) -> None:
    _ignore_sigint()


def make_loader(dataset: WindowDataset, sampler: StepBatches, num_workers: int, pin_memory: bool = False) -> DataLoader:
    return DataLoader(
        dataset,
        batch_sampler=sampler,
        num_workers=num_workers,
        pin_memory=pin_memory,
        worker_init_fn=_worker_init if num_workers else None,
        persistent_workers=False,
        prefetch_factor=2 if num_workers else None,
        multiprocessing_context=get_context("fork") if num_workers else None,
    )


def sample_pairs(windows, count: int, seed: int = 0) -> torch.Tensor:
    """``count`` patch pairs (N, 2, P, P) in [-1, 1] from a training dataset whose items are
    ``{"frames": (K, 1, h, w) uint8, "positions": (M, 2)}`` windows: consecutive frames, the
    first position of each window, a random pair of its frames."""
    rng = np.random.default_rng(seed)
    pairs = []
    patch = windows.patch
    for index in rng.choice(len(windows), size=count, replace=len(windows) < count):
        item = windows[int(index)]
        frames = item["frames"].float() / 127.5 - 1.0  # (K, 1, h, w)
        t = int(rng.integers(len(frames) - 1))
        pos = item["positions"][:1][None].expand(2, 1, 2)
        crops = crop(frames[t : t + 2], pos, patch)  # (2, 1, 1, P, P)
        pairs.append(crops[:, 0, 0])
    return torch.stack(pairs)


def to_model_input(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    """Move a loader batch to ``device`` as the objective wants it: frames float in [-1, 1]
    (converted on the device, so only uint8 crosses the bus)."""
    frames = batch["frames"].to(device, non_blocking=True).float().div_(127.5).sub_(1.0)
    out = {"frames": frames, "positions": batch["positions"].to(device, non_blocking=True)}
    for key in BURST_KEYS:
        if key in batch:
            out[key] = batch[key].to(device, non_blocking=True)
    return out
