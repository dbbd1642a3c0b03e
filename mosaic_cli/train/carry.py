"""Training the carry head (``mosaic train --variant carry``): the sequence model that carries the
motion across the frames that carry none (issue 38; the head: :class:`mosaic_cli.model.network.CarryHead`).

The backbone, first Linear and regressor are the frozen BASE of ``--init``, so a training window
costs the backbone once, ever: its features are computed once into a cache and the head trains on
them at over a thousand windows a second on one CPU thread.

    1. teacher tracks   the product's own estimator (the --init BASE, its Lucas-Kanade polish and
                        ORB fallback) run once over every clean clip of the frame cache: a
                        homography per consecutive pair, kept where it confirmed the pair
    2. windows          W frames of one clip, with (in a share ``bursts`` of them) 1-2 events
                        where only the sequence can place the pairs: 1-3 frames spoilt (glare,
                        blur, dark, flat: :mod:`.bursts`), a dropped frame (the pair spans two
                        intervals), a duplicated one (no motion); time-reversed and mirrored as
                        the other variants' windows; one patch position per window (with
                        ``blown_glare``, a share of the glare frames blown out entirely)
    3. feature cache    the features of every pair the network reads (spoilt frames included),
                        and the teacher's offsets of the same pair at the same patch, composed
                        over a drop, inverted when reversed, mirrored when flipped (exact), the
                        identity on a duplicate (exact); RUN_DIR/features/*.npy
    4. objective        Huber distance (working px, per corner) between the head's offsets and
                        the teacher's on the event pairs it knows (where the photometric loss
                        has no basin to pull from, the teacher still says where the pair lies),
                        and the BASE's own answer on the clean pairs (leaving it must cost);
                        with ``forcing``, the teacher's motion fed back as the head's previous
                        output after the pairs the frames would confirm (as the estimator's
                        carry-state=confirmed feeds it the confirmed motion)

No label is read: the teacher is the product's own estimate from the clean frames, which the head
never sees on a spoilt pair.  Each window starts from no state, as a video does; the state is then
carried through the whole video, and the cell's forget gates start at timescales of up to W frames
(models/README.md, "The carry head").
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from mosaic_cli.atomic import write_json
from mosaic_cli.model.checkpoint import file_sha256
from mosaic_cli.model.network import HomographyNet
from mosaic_cli.model.patches import crop, homography_to_offsets
from mosaic_cli.progress import progress_task
from mosaic_cli.train.bursts import GLARE, LEVELS, NOISE, spoil
from mosaic_cli.train.config import CARRY_BLENDS
from mosaic_cli.train.data import CachedClip

WINDOW = 32  # frames a training window spans (31 pairs)
EVENTS = ("clean", "glare", "blur", "dark", "flat", "drop", "duplicate")  # a pair's event code: its index
DROP, DUPLICATE = EVENTS.index("drop"), EVENTS.index("duplicate")
WARM_UP = 3  # pairs before a window's first event: there is a motion to carry
HUBER_PX = 1.0  # the loss is quadratic within this corner distance, linear beyond (teacher outliers)
GATE_TARGET_PX = 2.0  # gate supervision: a BASE answer this far from the teacher (mean corner, working px) is one to distrust
CACHE_FORMAT = 1
FEATURE_BATCH = 1024  # pairs through the backbone at once while the cache is built


# ----------------------------------------------------------------------------- 1. teacher tracks


def teacher_track(clip: CachedClip, weights: str) -> tuple[np.ndarray, np.ndarray]:
    """The product's estimate of every consecutive pair of ``clip``'s cached frames, working px:
    (n-1, 3, 3) homographies frame t -> t+1 and (n-1,) whether the estimator confirmed each (a
    pair across a segment boundary of the cache is never confirmed)."""
    from mosaic_cli.estimators.base import estimate_stream
    from mosaic_cli.estimators.learned import make_learned_estimator

    frames = np.load(clip.file, mmap_mode="r")
    n, h, w = frames.shape
    H = np.repeat(np.eye(3)[None], max(n - 1, 0), axis=0)
    ok = np.zeros(max(n - 1, 0), bool)
    for first, length in clip.segments:
        estimator = make_learned_estimator("", weights=weights, device="cpu")  # the checkpoint's own head
        estimates = estimate_stream(estimator, (np.asarray(f) for f in frames[first:first + length]), (w, h))
        for k, e in enumerate(estimates):
            if e.confidence > 0 and e.path in ("learned", "fallback"):
                H[first + k], ok[first + k] = e.H, True
    return H, ok


def _teacher_job(job: tuple[CachedClip, str, str]) -> str:
    """:func:`teacher_track` of one clip, saved to ``path`` (in a worker process)."""
    clip, weights, path = job
    H, ok = teacher_track(clip, weights)
    tmp = Path(path).with_name(f".{Path(path).stem}.part.npz")
    np.savez(tmp, H=H, ok=ok)
    tmp.replace(path)
    return path


def teacher_tracks(clips: Sequence[CachedClip], weights: str, folder: Path, show_progress: bool,
                   workers: int = 1) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`teacher_track` of every clip, on ``workers`` processes, each kept in ``folder`` (a
    resumed run reads them back)."""
    folder.mkdir(parents=True, exist_ok=True)
    key = _digest({"weights": file_sha256(weights), "format": CACHE_FORMAT})
    paths = [str(folder / f"{Path(clip.file).stem}-{key}.npz") for clip in clips]
    jobs = [(clip, weights, path) for clip, path in zip(clips, paths) if not Path(path).is_file()]
    with progress_task("teacher tracks", len(clips), unit="clips", disable=not show_progress) as advance:
        advance(len(clips) - len(jobs))
        if workers > 1 and len(jobs) > 1:
            # spawn, not fork: the parent's torch (its thread pool, perhaps CUDA) must not be forked.
            with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=get_context("spawn")) as pool:
                for _ in pool.map(_teacher_job, jobs):
                    advance(1)
        else:
            for job in jobs:
                _teacher_job(job)
                advance(1)
    out = []
    for path in paths:
        with np.load(path) as saved:
            out.append((saved["H"], saved["ok"]))
    return out


# ----------------------------------------------------------------------------- 2. windows


@dataclass
class Window:
    """One training window: the clip, the frames it reads (rows of the clip's cache, in reading
    order: a drop skips a row, a duplicate repeats one, a reversed window runs backwards), each
    frame's burst code, level and blur angle (:mod:`.bursts`), each pair's event code
    (:data:`EVENTS`), the mirrors and the patch's top-left."""

    clip: int
    rows: np.ndarray  # (W,)
    burst: np.ndarray  # (W,) 0 clean, else the pixel kind's code
    level: np.ndarray  # (W,)
    angle: np.ndarray  # (W,)
    events: np.ndarray  # (W - 1,)
    left_right: bool
    upside_down: bool
    position: tuple[int, int]


def draw_window(rng: np.random.Generator, segments: list[tuple[int, int, int]], cumulative: np.ndarray,
                frame_size: tuple[int, int], patch: int, bursts: float, flip: bool, window: int = WINDOW,
                blown_glare: float = 0.0, blown_by_burst: bool = False, turns: float = 0.0) -> Window:
    """A window drawn from ``rng`` alone.  ``segments`` are (clip, first row, length) with room for
    ``window + 2`` rows (two drops), ``cumulative`` their running count of starts.  ``blown_glare``:
    the share of glare frames blown out entirely (level 0, no residue of the ground), as some of
    the encoded flights' glare frames are (clipped white; most keep a faint residue:
    scripts/spoilt_cues.py); the same draws as without it, so that 0 draws the windows it always
    did.  ``blown_by_burst``: the first frame's draw decides for its whole burst (a burst clipped
    white is white throughout: pairs of two white frames, never of a white and a faint one).  ``turns``: the
    share of windows that turn back on themselves at a pair in their second half (the camera
    reverses, as at the end of a survey line: the motion flips from one pair to the next), drawn
    after everything else so that the other windows are the ones drawn without it."""
    T = window - 1
    steps = np.ones(T, np.int64)
    burst = np.zeros(window, np.int64)
    level = np.zeros(window, np.float32)
    angle = np.zeros(window, np.float32)
    events = np.zeros(T, np.int64)
    if rng.random() < bursts:
        count = int(rng.integers(1, 3))
        for _ in range(count):
            kind = int(rng.integers(1, len(EVENTS)))
            t = int(rng.integers(WARM_UP, T - 1))
            if kind in (DROP, DUPLICATE):
                steps[t] = 2 if kind == DROP else 0
                events[t] = kind
                continue
            length = int(rng.integers(1, 4))
            blown: bool | None = None
            for f in range(t, min(t + length, window - 1)):  # never the window's last frame
                burst[f] = kind
                level[f], was_blown = _level(rng, kind, blown_glare, blown)
                blown = was_blown if blown_by_burst else None
                angle[f] = rng.uniform(0.0, 180.0)
                events[f - 1] = events[f - 1] or kind  # the pairs on both sides of a spoilt frame
                events[f] = events[f] or kind
    flat = int(rng.integers(int(cumulative[-1])))
    s = int(np.searchsorted(cumulative, flat, side="right"))
    clip, first, length = segments[s]
    start = first + flat - (int(cumulative[s - 1]) if s else 0)  # a segment has room for WINDOW + 2 rows from it
    rows = start + np.concatenate([[0], np.cumsum(steps)])
    if rng.random() < 0.5:  # time-reversed: read backwards, the events with it
        rows, burst, level, angle, events = rows[::-1], burst[::-1], level[::-1], angle[::-1], events[::-1]
    w, h = frame_size
    position = (int(rng.integers(0, w - patch + 1)), int(rng.integers(0, h - patch + 1)))
    left_right, upside_down = (rng.random(2) < 0.5) if flip else (False, False)
    if turns > 0.0 and rng.random() < turns:
        rows = _turned(rows, int(rng.integers((T + 5) // 2, T - 1)))
    return Window(clip, rows.copy(), burst.copy(), level.copy(), angle.copy(), events.copy(),
                  bool(left_right), bool(upside_down), position)


def _turned(rows: np.ndarray, k: int) -> np.ndarray:
    """``rows`` turning back at frame k: after it the window retraces its steps, so pair k moves
    the way pair k-1 did, reversed.  A turn past the middle stays within the rows the window
    spans (the rows its segment has room for); the window is left as it was if it would not."""
    turned = rows.copy()
    turned[k + 1:] = 2 * rows[k] - rows[k + 1:]
    if turned.min() < rows.min() or turned.max() > rows.max():
        return rows
    return turned


def _level(rng: np.random.Generator, kind: int, blown_glare: float, blown: bool | None = None) -> tuple[float, bool]:
    """A spoilt frame's level, the simulator's range, and whether it was blown out (level 0): glare
    is, in a share ``blown_glare`` of the draws; where ``blown`` says, as its burst's first frame
    was (the level in the range then drawn plainly).  One draw of ``rng`` in every case."""
    if kind != GLARE or blown_glare <= 0.0:
        return float(rng.uniform(*LEVELS[kind])), False
    low, high = LEVELS[kind]
    u = float(rng.random())  # one draw, as uniform's
    if blown is not None:
        return (0.0, True) if blown else (low + (high - low) * u, False)
    if u < blown_glare:
        return 0.0, True
    return low + (high - low) * (u - blown_glare) / (1.0 - blown_glare), False


def teacher_offsets(window: Window, H: np.ndarray, ok: np.ndarray, frame_size: tuple[int, int], patch: int) -> tuple[np.ndarray, np.ndarray]:
    """The teacher's corner offsets (W-1, 4, 2) of every pair of ``window`` at its patch, and
    whether the teacher knows each pair: composed over a drop, the exact identity on a
    duplicate, inverted when the window runs backwards, mirrored with it."""
    w, h = frame_size
    mirror = np.diag([-1.0 if window.left_right else 1.0, -1.0 if window.upside_down else 1.0, 1.0])
    mirror[0, 2] = w - 1 if window.left_right else 0.0  # pixel centres on integers: x -> w - 1 - x
    mirror[1, 2] = h - 1 if window.upside_down else 0.0
    pairs, known = [], []
    for a, b in zip(window.rows[:-1], window.rows[1:]):
        lo, hi = min(a, b), max(a, b)
        M = np.eye(3)
        good = True
        for t in range(lo, hi):
            M = H[t] @ M
            good = good and bool(ok[t])
        if b < a:
            M = np.linalg.inv(M)
        pairs.append(mirror @ M @ mirror)
        known.append(good)
    Hs = torch.from_numpy(np.stack(pairs))
    position = torch.tensor(window.position, dtype=torch.float64)
    offsets = homography_to_offsets(Hs, position, patch).numpy().astype(np.float32)
    return offsets, np.array(known) & np.isfinite(offsets).all(axis=(1, 2))


# ----------------------------------------------------------------------------- 3. feature cache


@dataclass
class FeatureCache:
    """The cached training windows: features (N, W-1, F) float16 of the pairs the network reads,
    the teacher's offsets (N, W-1, 8), whether it knows each pair (N, W-1) and each pair's event
    code (N, W-1)."""

    features: np.ndarray
    teacher: np.ndarray
    known: np.ndarray
    events: np.ndarray

    def __len__(self) -> int:
        return len(self.features)


def build_feature_cache(net: HomographyNet, features, clips: Sequence[CachedClip], teachers, count: int, patch: int,
                        seed: int, bursts: float, flip: bool, folder: Path, identity: dict,
                        show_progress: bool, blown_glare: float = 0.0, blown_by_burst: bool = False,
                        turns: float = 0.0, noise: float = NOISE) -> FeatureCache:
    """Draw ``count`` windows and cache what the head trains on (in ``folder``, reused by a run
    with the same ``identity``: the weights, clips, seed and options).  ``features`` turns patch
    pairs (N, 2, P, P) in [-1, 1] into (N, F): the network's own, or the estimator's int8 one."""
    folder.mkdir(parents=True, exist_ok=True)
    key = _digest({**identity, "count": count, "format": CACHE_FORMAT, "window": WINDOW})
    names = ("features", "teacher", "known", "events")
    paths = {name: folder / f"{name}-{key}.npy" for name in names}
    if all(p.is_file() for p in paths.values()):
        return FeatureCache(*(np.load(paths[n], mmap_mode="r") for n in names))
    arrays = [np.load(c.file, mmap_mode="r") for c in clips]
    h, w = arrays[0].shape[1:]
    segments = [(c, first, length) for c, clip in enumerate(clips) for first, length in clip.segments if length >= WINDOW + 2]
    if not segments:
        from mosaic_cli.errors import BadInput

        raise BadInput(f"no clip holds {WINDOW + 2} consecutive frames, the carry head's training window")
    cumulative = np.cumsum([length - WINDOW - 1 for _, _, length in segments])
    T, F = WINDOW - 1, net.config.embed + net.config.carry_cues
    feats = np.lib.format.open_memmap(_part(paths["features"]), "w+", np.float16, (count, T, F))
    teacher = np.zeros((count, T, 8), np.float32)
    known = np.zeros((count, T), bool)
    events = np.zeros((count, T), np.int8)
    per_batch = max(1, FEATURE_BATCH // T)
    with progress_task("feature cache", count, unit="windows", disable=not show_progress) as advance, torch.inference_mode():
        for first in range(0, count, per_batch):
            batch = range(first, min(count, first + per_batch))
            read, positions = [], []
            for i in batch:
                rng = np.random.default_rng([seed, i, 38])
                win = draw_window(rng, segments, cumulative, (w, h), patch, bursts, flip, blown_glare=blown_glare,
                                  blown_by_burst=blown_by_burst, turns=turns)
                H, ok = teachers[win.clip]
                offsets, known[i] = teacher_offsets(win, H, ok, (w, h), patch)
                teacher[i] = offsets.reshape(T, 8)
                events[i] = win.events
                frames = np.asarray(arrays[win.clip][win.rows])
                frames = frames[:, ::-1 if win.upside_down else 1, ::-1 if win.left_right else 1]
                clean = torch.from_numpy(np.ascontiguousarray(frames))[None, :, None].float() / 127.5 - 1.0
                spoilt = spoil(clean, *(torch.from_numpy(v)[None] for v in (win.burst, win.level, win.angle)),
                               generator=torch.Generator().manual_seed(seed * 7919 + i), noise=noise)
                read.append(spoilt[0])
                positions.append(win.position)
            frames = torch.stack(read)  # (b, W, 1, h, w)
            pos = torch.tensor(positions)[:, None].expand(len(read), WINDOW, 2).reshape(-1, 1, 2)
            crops = crop(frames.flatten(0, 1), pos, patch)[:, 0, 0].unflatten(0, (len(read), WINDOW))  # (b, W, P, P)
            pairs = torch.stack([crops[:, :-1], crops[:, 1:]], dim=2).flatten(0, 1)  # (b*T, 2, P, P)
            read_by_head = net.head_inputs(pairs, features(pairs))
            feats[batch.start:batch.stop] = read_by_head.unflatten(0, (len(read), T)).numpy().astype(np.float16)
            advance(len(read))
    feats.flush()
    del feats
    _part(paths["features"]).replace(paths["features"])
    for name, array in (("teacher", teacher), ("known", known), ("events", events)):
        np.save(_part(paths[name]), array)
        _part(paths[name]).replace(paths[name])
    write_json(folder / f"cache-{key}.json", {**identity, "count": count, "window": WINDOW,
                                              "known": float(known.mean()), "event_pairs": int((events > 0).sum())})
    return FeatureCache(*(np.load(paths[n], mmap_mode="r") for n in names))


class FeatureWindows:
    """Batches of cached windows for step s, drawn from ``(seed, step)`` alone (so that a resumed
    run draws what an uninterrupted one did), on ``device``, as :class:`CarryObjective` reads them.
    With ``base`` (the net's frozen :meth:`~mosaic_cli.model.network.HomographyNet.base_offsets`),
    each window's BASE answer is computed once here, not at every step: over LSTM-REG-T's LSTM it
    costs more than the head's own step."""

    def __init__(self, cache: FeatureCache, seed: int, device: torch.device, base=None, embed: int | None = None):
        self.cache, self.seed, self.device = cache, int(seed), torch.device(device)
        # The cache is a few hundred MB: held in memory (as float16) for random access.
        self.features = torch.from_numpy(np.array(cache.features)).to(self.device)
        self.teacher = torch.from_numpy(np.array(cache.teacher)).to(self.device)
        self.known = torch.from_numpy(np.array(cache.known)).to(self.device)
        self.events = torch.from_numpy(np.array(cache.events)).long().to(self.device)
        self.base = None
        if base is not None:
            with torch.no_grad():  # each window from no state, as the objective would run it
                self.base = torch.cat([base(self.features[i : i + FEATURE_BATCH, :, :embed].float())[0]
                                       for i in range(0, len(self.features), FEATURE_BATCH)])

    def batch(self, step: int, batch_size: int, rank: int = 0, world: int = 1) -> dict[str, Tensor]:
        g = torch.Generator()
        g.manual_seed((self.seed * 1_000_003 + step) * 4099 + rank * 131 + world)
        index = torch.randint(len(self.cache), (int(batch_size),), generator=g).to(self.device)
        draw = torch.rand(int(batch_size), generator=g).to(self.device)  # after the index: the same windows as before it
        batch = {"features": self.features[index].float(), "teacher": self.teacher[index].unflatten(-1, (4, 2)),
                 "known": self.known[index], "events": self.events[index], "draw": draw}
        if self.base is not None:
            batch["base"] = self.base[index]
        return batch


# ----------------------------------------------------------------------------- 4. objective


class CarryObjective:
    """``objective(model, batch)`` -> the loss terms of the carry head: ``total``, the Huber
    distance (per corner, working px) to the teacher on the event pairs it knows (a spoilt,
    dropped or duplicated frame: what only the sequence can place) and to the BASE's own answer
    on every clean pair (leaving it must cost: trained towards the teacher there too, the head
    learned to smooth the BASE's answers with its carried motion, and lagged behind the turns of
    flights over ground it never saw; models/README.md, "The carry head"); and, for the log, the
    mean corner error (working px) against the teacher on clean and on event pairs, and the
    gate's mean weight on the carried motion on each."""

    variant = "carry"
    head = "carry"
    window = WINDOW + 2  # the rows a window may span (two drops): what the frame cache must hold
    positions = 1
    check_positions = False

    def __init__(self, forcing: float = 0.0, teacher_beyond: float | None = None, gate_weight: float = 0.0,
                 blend: str = "gate", correction_weight: float = 0.0):
        if not 0.0 <= forcing <= 1.0:
            raise ValueError(f"forcing must be a share of the windows in [0, 1], got {forcing}")
        if teacher_beyond is not None and not teacher_beyond > 0.0:
            raise ValueError(f"teacher_beyond must be a positive distance (working px), got {teacher_beyond}")
        if not gate_weight >= 0.0:
            raise ValueError(f"gate_weight must be 0 or more, got {gate_weight}")
        self.forcing = float(forcing)
        self.teacher_beyond = teacher_beyond
        self.gate_weight = float(gate_weight)
        if blend not in CARRY_BLENDS:
            raise ValueError(f"blend must be one of {', '.join(CARRY_BLENDS)}, got {blend!r}")
        self.blend = blend
        if not correction_weight >= 0.0:
            raise ValueError(f"correction_weight must be 0 or more, got {correction_weight}")
        if correction_weight > 0.0 and blend != "spoilt":
            raise ValueError("correction_weight weighs the correction on the pairs that take the carried motion whole: blend='spoilt'")
        self.correction_weight = float(correction_weight)

    def __call__(self, model, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        net = getattr(model, "module", model)
        features = batch["features"]
        cnn = batch.get("base")  # frozen: the BASE's offsets of each pair, computed once (FeatureWindows)
        if cnn is None:
            with torch.no_grad():
                cnn, _ = net.base_offsets(features[..., : net.config.embed])
        # blend "spoilt": the pairs with a spoilt frame take the carried motion whole, as the
        # estimator's carry-blend=spoilt has them (its cell's correction is then all that is learnt there)
        trust = ((batch["events"] > 0) & (batch["events"] < DROP)) if self.blend == "spoilt" else None
        forced = self.forced(batch)
        offsets, _, gate = net.carry(features, cnn, **forced, trust=trust)
        known = batch["known"].float()
        event = (batch["events"] > 0).float()
        # Clean pairs: the BASE's own answer (leaving it must cost: the head is to add memory where
        # the frames show nothing, not to second-guess the BASE where they do); event pairs: the
        # teacher's, where it confirmed the pair.  With ``teacher_beyond``, also the clean pairs
        # whose BASE answer lies that far from the teacher's (mean corner distance, working px): a
        # motion too fast for the BASE, where the carried one is the better guess.
        teach = batch["known"] & (batch["events"] > 0)
        if self.teacher_beyond is not None:
            far = (cnn.unflatten(-1, (4, 2)) - batch["teacher"]).norm(dim=-1).mean(-1) > self.teacher_beyond
            teach = teach | (batch["known"] & far)
        target = torch.where(teach[..., None, None], batch["teacher"], cnn.unflatten(-1, (4, 2)))
        scored = known * event + (1 - event)
        error = (offsets.unflatten(-1, (4, 2)) - target).norm(dim=-1)  # (B, T, 4) working px
        huber = torch.where(error < HUBER_PX, 0.5 * error**2 / HUBER_PX, error - 0.5 * HUBER_PX).mean(-1)
        corner = error.mean(-1).detach()

        def mean(values: Tensor, weights: Tensor) -> Tensor:
            return (values * weights).sum() / weights.sum().clamp(min=1.0)

        total = mean(huber, scored)
        if self.gate_weight > 0.0:
            # The gate told directly which answer to take: the carried motion where the BASE's lies
            # GATE_TARGET_PX or more from the teacher on an event pair, the BASE's where it is
            # right (an event pair it reads, as a drop; every clean pair it gets right).  The blend's
            # own loss pulls the gate only as far as the two answers differ (models/README.md, run
            # 14: it did not make the gate sharper on the flights).
            base_off = (cnn.unflatten(-1, (4, 2)) - batch["teacher"]).norm(dim=-1).mean(-1)
            wrong = base_off >= GATE_TARGET_PX
            supervised = batch["known"] & ((batch["events"] > 0) | ~wrong)
            bce = torch.nn.functional.binary_cross_entropy(gate.clamp(1e-6, 1 - 1e-6), wrong.float(), reduction="none")
            total = total + self.gate_weight * mean(bce, supervised.float())
        if self.correction_weight > 0.0 and trust is not None:
            # An L1 price on the cell's correction of the carried motion, where the pair takes it
            # whole: the correction moves only where the teacher pulls harder than the price, so that
            # it stays at zero where the rule (the motion carried as it is) is already right.
            correction = (offsets - self.previous_outputs(offsets, cnn, forced)).unflatten(-1, (4, 2)).norm(dim=-1).mean(-1)
            total = total + self.correction_weight * mean(correction, trust.float())
        return {
            "total": total,
            "clean_px": mean(corner, known * (1 - event)),
            "event_px": mean(corner, known * event),
            "gate_clean": mean(gate.detach(), 1 - event),
            "gate_event": mean(gate.detach(), event),
        }


    @staticmethod
    def previous_outputs(offsets: Tensor, cnn: Tensor, forced: dict[str, Tensor]) -> Tensor:
        """The previous output each pair of a window read (B, T, 8), as :class:`CarryHead` feeds
        it: the BASE's answer before the first pair, then the head's output or, after a confirmed
        pair, the confirmed motion.  Not detached: on a trusted pair ``offsets - previous`` is the
        cell's correction itself, with its gradient alone."""
        previous = offsets[:, :-1]
        if forced:
            previous = torch.where(forced["confirm"][:, :-1, None], forced["confirmed"][:, :-1], previous)
        return torch.cat([cnn[:, :1], previous], dim=1)

    def forced(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """Teacher forcing (``forcing``: the share of windows it applies to, drawn per window):
        after each pair the frames would confirm, a clean pair or a dropped or duplicated frame
        that the teacher knows, the head reads the teacher's motion as its previous output, as the
        estimator feeds it the confirmed motion (``-e lstm:carry-state=confirmed``); after a
        spoilt pair, its own.  Nothing where no window is drawn."""
        if self.forcing <= 0.0:
            return {}
        events = batch["events"]
        placed = (events == 0) | (events == DROP) | (events == DUPLICATE)
        confirm = batch["known"] & placed & (batch["draw"] < self.forcing)[:, None]
        return {"confirmed": batch["teacher"].flatten(-2), "confirm": confirm}


# ----------------------------------------------------------------------------- helpers


def _digest(data: dict) -> str:
    return hashlib.sha1(json.dumps(data, sort_keys=True).encode()).hexdigest()[:12]


def _part(path: Path) -> Path:
    return path.with_name(f".{path.stem}.part.npy")


__all__ = ["WINDOW", "EVENTS", "CarryObjective", "FeatureCache", "FeatureWindows", "Window", "build_feature_cache",
           "draw_window", "teacher_offsets", "teacher_track", "teacher_tracks"]
