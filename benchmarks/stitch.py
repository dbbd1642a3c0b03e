"""Stitch: placement accuracy, throughput, memory, revisits and photo folders of ``mosaic stitch``; drift control's solver."""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares

from benchmarks.common import ORTHOPHOTO, ROOT, SHARED_DATA, make_parser, placement_errors, plain_chain, run_commands
from mosaic_cli.estimators import DEFAULT_ESTIMATOR, make_estimator
from mosaic_cli.geometry import frame_corners, project
from mosaic_cli.simulate import FlightPlan, load_ground_truth, load_map, plan_flight, procedural_map, write_flight
from mosaic_cli.simulate.trajectory import camera_homography
from mosaic_cli.stitch import CanvasOptions, RegistrationOptions, StitchOptions, registration, stitch
from mosaic_cli.stitch.registration import RegistrationReport, refine_placements

SUITE = "stitch"


# -- python -m benchmarks stitch -------------------------------------------------------------------

DEFAULT_WORKDIR = ROOT / ".dev" / "bench_stitch"
GAP = 60  # frames: placement accuracy is measured between used frames at least this far apart


def here(args: argparse.Namespace, command: str) -> str:
    workdir = "" if args.workdir == DEFAULT_WORKDIR else f" --workdir {args.workdir}"
    return f"python -m benchmarks stitch {command}{workdir}"


# -- flights -----------------------------------------------------------------------------------


def survey_flight(workdir: Path, frames: int, size: tuple[int, int], seed: int, image: Path = ORTHOPHOTO) -> Path:
    """A lawnmower survey over ``image`` (the simulator's 'survey' profile; a procedural map when
    the image is absent), cached."""
    known = image.exists()
    tag = "" if image == ORTHOPHOTO or not known else f"_{image.stem}"
    path = workdir / f"survey_{size[0]}x{size[1]}_{frames}_s{seed}{tag}.mp4"
    if not path.exists():
        ground = load_map(image if known else None, seed=seed)
        plan = plan_flight((ground.shape[1], ground.shape[0]), "survey", frames, size, seed)
        write_flight(path, ground, plan, map_name=image.name if known else "procedural", preset="veryfast")
    return path


def long_survey_plan(frames: int, size: tuple[int, int], speed: float = 8.0, line: int = 7000, seed: int = 0) -> FlightPlan:
    """A survey whose covered area grows with its length: lines ``line`` map pixels long,
    0.55 frame heights apart, at one map pixel per frame pixel, turning at the ends."""
    w, h = size
    spacing = 0.55 * h
    margin = 0.75 * np.hypot(w, h)
    path_len = frames * speed
    turn = np.pi * spacing / 2
    lines = int(np.ceil(path_len / (line + turn))) + 1
    pts, headings = [], []
    for k in range(lines):
        y = margin + k * spacing
        xs = np.arange(0, line, speed)
        xs = margin + (xs if k % 2 == 0 else line - xs)
        pts += [(x, y) for x in xs]
        headings += [0.0 if k % 2 == 0 else np.pi] * len(xs)
        centre = (xs[-1], y + spacing / 2)
        angles = np.arange(0, np.pi, speed / (spacing / 2))
        side = 1 if k % 2 == 0 else -1
        pts += [(centre[0] + side * spacing / 2 * np.sin(a), centre[1] - spacing / 2 * np.cos(a)) for a in angles]
        headings += [(0.0 if k % 2 == 0 else np.pi) + a for a in angles]
    pts, headings = np.array(pts[:frames]), np.array(headings[:frames])
    rng = np.random.default_rng(seed)
    tilt = np.radians(1.0) * np.sin(np.arange(frames) / 90.0 + rng.uniform(0, 6))
    M = np.stack([camera_homography(size, float(w), x, y, 1.0, a, p, 0.0) for (x, y), a, p in zip(pts, headings, tilt)])
    map_size = (int(line + 2 * margin + 1), int(pts[:, 1].max() + margin + 1))
    return FlightPlan(M, M.copy(), size, "long-survey", seed, map_size, 30.0)


def long_name(frames: int, speed: float) -> str:
    return f"long_1920x1080_{frames}" + ("" if speed == 8.0 else f"_v{speed:g}")


def long_flight(workdir: Path, frames: int, speed: float) -> Path:
    path = workdir / f"{long_name(frames, speed)}.mp4"
    if not path.exists():
        plan = long_survey_plan(frames, (1920, 1080), speed)
        ground = procedural_map(plan.map_size, seed=11)
        write_flight(path, ground, plan, preset="ultrafast", crf=20)
    return path


# -- placement accuracy ------------------------------------------------------------------------


def accuracy(args) -> dict:
    rows = []
    for seed in args.seeds:
        video = survey_flight(args.workdir, args.frames, (1280, 720), seed)
        gt = load_ground_truth(video.with_suffix(".gt.json"))
        row = {"flight": video.name, "estimator": args.estimator}
        for label, enabled in (("drift control", True), ("no drift control", False)):
            options = StitchOptions(registration=RegistrationOptions(enabled=enabled))
            out = args.workdir / f"{video.stem}_{'dc' if enabled else 'chain'}.png"
            result = stitch(video, out, make_estimator(args.estimator), options, transforms=out.with_suffix(".json"), show_progress=False)
            indices = [i for i, _ in result.transforms]
            errors = placement_errors(indices, [H for _, H in result.transforms], gt.map_to_frame, gt.size, GAP)
            row[label] = float(np.median(errors))
            if enabled:
                row["used frames"], row["pairs"], row["loops"] = len(indices), len(errors), result.registration.loops
                plain = placement_errors(indices, plain_chain(video, indices), gt.map_to_frame, gt.size, GAP)
                row["plain chaining"] = float(np.median(plain))
        rows.append(row)
        print(
            f"{row['flight']} ({args.estimator}): {row['used frames']} used frames, {row['pairs']} pairs >= {GAP} frames apart, {row['loops']} loop closures; "
            f"median corner error  drift control {row['drift control']:.2f} px | plain chaining (full-res ORB+RANSAC, "
            f"chained) {row['plain chaining']:.2f} px | --no-drift-control {row['no drift control']:.2f} px",
            flush=True,
        )
    print(f"  reproduce: {here(args, 'accuracy')} --frames {args.frames} --seeds {' '.join(map(str, args.seeds))} --estimator {args.estimator}")
    return {"accuracy": rows}


# -- flights that revisit their ground ---------------------------------------------------------

REAL_FRAMES = SHARED_DATA / "aerial_video" / "teon2001_blacksea_drone_frames"
ODM = SHARED_DATA / "aerial_sequences"


def revisit_flight(workdir: Path, kind: str, frames: int, seed: int) -> tuple[Path, np.ndarray]:
    """A 1280x720 'fast' flight over the orthophoto, then the same flight backward
    (``kind='fb'``) or again from its start after a cut (``kind='loop'``): the second pass's
    exact map -> frame homographies are the first pass's, reversed or repeated."""
    path = workdir / f"{kind}_1280x720_{frames}_s{seed}.mp4"
    if not path.exists():
        known = ORTHOPHOTO.exists()
        ground = load_map(ORTHOPHOTO if known else None, seed=seed)
        plan = plan_flight((ground.shape[1], ground.shape[0]), "fast", frames, (1280, 720), seed)
        second = (lambda m: m[::-1]) if kind == "fb" else (lambda m: m)
        plan = dataclasses.replace(
            plan,
            map_to_frame=np.concatenate([plan.map_to_frame, second(plan.map_to_frame)]),
            smooth_map_to_frame=np.concatenate([plan.smooth_map_to_frame, second(plan.smooth_map_to_frame)]),
        )
        write_flight(path, ground, plan, map_name=ORTHOPHOTO.name if known else "procedural", preset="veryfast", show_progress=False)
    return path, load_ground_truth(path.with_suffix(".gt.json")).map_to_frame


def pass_offsets(transforms, truth, first_pass: int, twin, size) -> np.ndarray:
    """For each second-pass keyframe: the largest corner distance (panorama pixels) between
    where it is drawn and where the first pass puts it (the nearest first-pass keyframe's
    placement carried over by the exact relative homography; ``twin(j)``: the first-pass
    frame that sees what frame j sees)."""
    first = [(i, H) for i, H in transforms if i < first_pass]
    corners = frame_corners(*size)
    offsets = []
    for j, H_j in transforms:
        if j >= first_pass:
            i, H_i = min(first, key=lambda t: abs(t[0] - twin(j)))
            expected = H_i @ truth[i] @ np.linalg.inv(truth[j])
            offsets.append(float(np.max(np.linalg.norm(project(expected, corners) - project(H_j, corners), axis=1))))
    return np.array(offsets)


def revisits(args) -> dict:
    rows = []
    for kind in ("fb", "loop"):
        for seed in args.seeds:
            video, truth = revisit_flight(args.workdir, kind, args.revisit_frames, seed)
            n = args.revisit_frames
            twin = (lambda j, n=n: 2 * n - 1 - j) if kind == "fb" else (lambda j, n=n: j - n)
            row = {"flight": video.name, "estimator": args.estimator}
            for label, enabled in (("dc", True), ("no-dc", False)):
                options = StitchOptions(registration=RegistrationOptions(enabled=enabled))
                out = args.workdir / f"{video.stem}_{label}.png"
                result = stitch(video, out, make_estimator(args.estimator), options, show_progress=False)
                indices = [i for i, _ in result.transforms]
                errors = placement_errors(indices, [H for _, H in result.transforms], truth, (1280, 720), GAP)
                offsets = pass_offsets(result.transforms, truth, n, twin, (1280, 720))
                row[label] = {
                    "panoramas": len(result.panoramas), "canvas": list(result.canvas_size), "keyframes": len(indices),
                    "median": float(np.median(errors)), "p90": float(np.percentile(errors, 90)), "max": float(errors.max()),
                    "pass offset median": float(np.median(offsets)), "pass offset max": float(offsets.max()),
                    "loops": result.registration.loops,
                }
            rows.append(row)
            print(f"{video.name} ({args.estimator}):", flush=True)
            for label in ("dc", "no-dc"):
                r = row[label]
                print(
                    f"  {label:6s} {r['panoramas']} panorama(s) {r['canvas'][0]}x{r['canvas'][1]}, {r['keyframes']} keyframes, {r['loops']} loops; "
                    f"corner error of keyframes >= {GAP} frames apart median {r['median']:.2f} p90 {r['p90']:.2f} max {r['max']:.2f} px; "
                    f"second pass from the first: median {r['pass offset median']:.2f} max {r['pass offset max']:.2f} px",
                    flush=True,
                )
    print(f"  reproduce: {here(args, 'revisits')} --revisit-frames {args.revisit_frames} --seeds {' '.join(map(str, args.seeds))} --estimator {args.estimator}")
    return {"revisits": rows}


def real_revisits(args) -> dict:
    """The real sparse frames (6 of each video) as a photo folder: once, then forward and
    backward (the same files in reverse after them), all drawn in the first frame.  Exact
    truth for the second pass: each of its frames is a first-pass frame."""
    rows = []
    for clip in sorted(p for p in REAL_FRAMES.iterdir() if p.is_dir()):
        files = sorted(p for p in clip.iterdir() if p.suffix.lower() in (".jpg", ".png"))
        single, fb = args.workdir / f"real_{clip.name}_single", args.workdir / f"real_{clip.name}_fb"
        for folder, sequence in ((single, files), (fb, files + files[::-1])):
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            for k, f in enumerate(sequence):
                os.symlink(f, folder / f"frame_{k:04d}{f.suffix}")
        size = cv2.imread(str(files[0])).shape[1::-1]
        n = len(files)
        row = {"clip": clip.name, "frames": n}
        # Both drawn in the first frame: the extents compare only in the same reference frame.
        first_frame = CanvasOptions(reference="first")
        ref = stitch(single, args.workdir / f"{single.name}.png", make_estimator(args.estimator), StitchOptions(canvas=first_frame), show_progress=False)
        row["single"] = list(ref.canvas_size)
        for label, enabled in (("dc", True), ("no-dc", False)):
            options = StitchOptions(registration=RegistrationOptions(enabled=enabled), canvas=first_frame)
            result = stitch(fb, args.workdir / f"{fb.name}_{label}.png", make_estimator(args.estimator), options, show_progress=False)
            first = {i: H for i, H in result.transforms if i < n}
            offsets = []
            for j, H_j in result.transforms:
                if j >= n and (2 * n - 1 - j) in first:
                    c = frame_corners(*size)
                    offsets.append(float(np.max(np.linalg.norm(project(first[2 * n - 1 - j], c) - project(H_j, c), axis=1))))
            extent = np.array(result.canvas_size, float) / np.array(ref.canvas_size, float) - 1
            row[label] = {
                "panoramas": len(result.panoramas), "canvas": list(result.canvas_size), "extent change": [float(e) for e in extent],
                "used": len(result.transforms), "dropped": len(result.dropped),
                "pass offset max": max(offsets) if offsets else None,
            }
        rows.append(row)
        print(f"{clip.name}: {n} real {size[0]}x{size[1]} frames; single pass canvas {ref.canvas_size[0]}x{ref.canvas_size[1]}", flush=True)
        for label in ("dc", "no-dc"):
            r = row[label]
            offset = "n/a" if r["pass offset max"] is None else f"{r['pass offset max']:.2f} px"
            print(
                f"  forward+backward {label:6s}: {r['panoramas']} panorama(s), canvas {r['canvas'][0]}x{r['canvas'][1]} "
                f"({100 * r['extent change'][0]:+.1f}% / {100 * r['extent change'][1]:+.1f}%), {r['used']} used, {r['dropped']} dropped; "
                f"second pass from the first (same frame, corners): max {offset}",
                flush=True,
            )
    print(f"  reproduce: {here(args, 'real-revisits')} --estimator {args.estimator}")
    return {"real-revisits": rows}


@dataclasses.dataclass
class Reference:
    """A direct full-resolution registration of photo i to photo j (see ``DirectReference``)."""

    H: np.ndarray  # i -> j
    points: np.ndarray  # its inliers, in photo i
    ambiguity: float  # px: largest median distance to the registrations at the other thresholds


class DirectReference:
    """The truth the photo benchmark measures against, fixed and independent of the stitch:
    OpenCV SIFT on the full-resolution photos (20,000 features, contrast threshold 0.01: low
    contrast aerial ground keeps its points), brute-force matching with Lowe's ratio 0.75, and
    MAGSAC++ (``USAC_MAGSAC``) at 2 px, 20,000 iterations, confidence 0.9999.  A registration
    needs 50 inliers at distinct points whose hull covers at least 1% of the photo (else: none; a few
    repeated points give a degenerate exact fit).  Where the ground is not one plane (trees,
    relief) the registration depends on the threshold: it is repeated at 1 and 4 px, and the
    largest median distance to those (over the 2-px inliers) is its ``ambiguity``."""

    THRESHOLDS = (1.0, 4.0)
    MIN_INLIERS = 50
    MIN_SPREAD = 0.01
    AMBIGUOUS = 1.0  # px

    def __init__(self, files: list[Path]):
        self.files = files
        self._features: dict[int, tuple] = {}
        self._pairs: dict[tuple[int, int], Reference | None] = {}
        self._sift = cv2.SIFT_create(20000, contrastThreshold=0.01)

    def features(self, i: int):
        if i not in self._features:
            gray = cv2.imread(str(self.files[i]), cv2.IMREAD_GRAYSCALE)
            keypoints, descriptors = self._sift.detectAndCompute(gray, None)
            self._features[i] = (np.float64([k.pt for k in keypoints]), descriptors, gray.shape[1] * gray.shape[0])
        return self._features[i]

    def __call__(self, i: int, j: int) -> Reference | None:
        if (i, j) not in self._pairs:
            self._pairs[i, j] = self._register(i, j)
        return self._pairs[i, j]

    def _register(self, i: int, j: int) -> Reference | None:
        pa, da, area = self.features(i)
        pb, db, _ = self.features(j)
        pairs = [m for m, n in cv2.BFMatcher().knnMatch(da, db, k=2) if m.distance < 0.75 * n.distance]
        if len(pairs) < self.MIN_INLIERS:
            return None
        a = np.float64([pa[m.queryIdx] for m in pairs])
        b = np.float64([pb[m.trainIdx] for m in pairs])

        def fit(threshold: float):
            H, mask = cv2.findHomography(a, b, cv2.USAC_MAGSAC, threshold, maxIters=20000, confidence=0.9999)
            return (None, None) if H is None else (H / H[2, 2], mask.ravel().astype(bool))

        H, keep = fit(2.0)
        if H is None:
            return None
        inliers = np.unique(np.round(a[keep]), axis=0)
        if len(inliers) < self.MIN_INLIERS or cv2.contourArea(cv2.convexHull(inliers.astype(np.float32))) < self.MIN_SPREAD * area:
            return None
        points = a[keep]
        ambiguity = 0.0
        for threshold in self.THRESHOLDS:
            other, _ = fit(threshold)
            gap = np.inf if other is None else float(np.median(np.linalg.norm(project(other, points) - project(H, points), axis=1)))
            ambiguity = max(ambiguity, gap)
        return Reference(H, points, ambiguity)


def photo_pairs(panorama, size: tuple[int, int], min_overlap: float = 0.2) -> tuple[list, list]:
    """(consecutive, other) pairs of used photos of one panorama: (i, j, photo i -> photo j);
    the others are those its placements predict to overlap by ``min_overlap`` of a photo."""
    from mosaic_cli.stitch.keyframes import overlap_fraction

    used = panorama.transforms
    consecutive = [(i, j, np.linalg.inv(H_j) @ H_i) for (i, H_i), (j, H_j) in zip(used, used[1:])]
    other = []
    for a, (i, H_i) in enumerate(used):
        for j, H_j in used[a + 2:]:
            relative = np.linalg.inv(H_j) @ H_i
            if overlap_fraction(relative, size) >= min_overlap:
                other.append((i, j, relative))
    return consecutive, other


def placement_gaps(pairs, reference: DirectReference) -> list[tuple[int, int, float | None, float | None]]:
    """For each pair (i, j, placed i -> j): the median distance (px) over the direct
    registration's inliers between where the panorama and where the registration put them, and
    the registration's ambiguity (None, None: no registration)."""
    out = []
    for i, j, placed in pairs:
        ref = reference(i, j)
        if ref is None:
            out.append((i, j, None, None))
            continue
        out.append((i, j, photo_pairs_gap(placed, ref), ref.ambiguity))
    return out


def photo_pairs_gap(placed: np.ndarray, ref: Reference) -> float:
    """The median distance (px) over the ruler's inliers between where ``placed`` (photo i -> j)
    and the ruler put them."""
    return float(np.median(np.linalg.norm(project(placed, ref.points) - project(ref.H, ref.points), axis=1)))


def ruler_floor(pairs: list[tuple[int, int]], reference: DirectReference) -> tuple[float, float]:
    """How close a panorama of one homography per photo can come to these rulers: placements fitted
    to the rulers themselves (each pair's RMS gap over its inliers, least squares, the pairs alike),
    then the largest of those gaps pressed down by a growing p-norm (p = 4 .. 32).  Returns the
    largest median gap of the least-squares fit and of the best fit found: a placement that
    exists, not a proof that none does better (``ruler_loops`` gives such proofs)."""
    known = {(i, j): reference(i, j) for i, j in pairs}
    known = {pair: ref for pair, ref in known.items() if ref is not None}
    if not known:
        return math.nan, math.nan
    photos = sorted({k for pair in known for k in pair})
    points = {pair: ref.points[:: max(1, len(ref.points) // 300)] for pair, ref in known.items()}
    scale = np.diag([1e-3, 1e-3, 1.0])  # unknowns of one size: better conditioned
    strongest_first = sorted(known.items(), key=lambda item: -len(item[1].points))
    placed: dict[int, np.ndarray] = {}
    while len(placed) < len(photos):  # a spanning tree of rulers, most inliers first; a new part from identity
        placed.setdefault(next(p for p in photos if p not in placed), np.eye(3))
        for _ in photos:
            for (i, j), ref in strongest_first:
                if i in placed and j not in placed:
                    placed[j] = placed[i] @ np.linalg.inv(ref.H)
                elif j in placed and i not in placed:
                    placed[i] = placed[j] @ ref.H
    free = photos[1:]

    def unpack(x: np.ndarray) -> dict[int, np.ndarray]:
        out = {photos[0]: placed[photos[0]]}
        for k, p in enumerate(free):
            out[p] = np.linalg.inv(scale) @ np.append(x[8 * k:8 * k + 8], 1.0).reshape(3, 3) @ scale
        return out

    def gaps(x: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
        P = unpack(x)
        return {(i, j): np.linalg.norm(project(np.linalg.inv(P[j]) @ P[i], pts) - project(known[i, j].H, pts), axis=1)
                for (i, j), pts in points.items()}

    def rms(x: np.ndarray) -> np.ndarray:
        return np.array([np.sqrt(np.mean(g**2)) for g in gaps(x).values()])

    def worst_median(x: np.ndarray) -> float:
        P = unpack(x)
        return max(photo_pairs_gap(np.linalg.inv(P[j]) @ P[i], ref) for (i, j), ref in known.items())

    x = np.concatenate([(m := scale @ placed[p] @ np.linalg.inv(scale)).ravel()[:8] / m[2, 2] for p in free])
    x = least_squares(lambda x: np.concatenate([g / np.sqrt(len(g)) for g in gaps(x).values()]), x, method="trf", max_nfev=2000).x
    fitted = best = worst_median(x)
    for power in (4, 8, 16, 32):
        x = least_squares(lambda x, power=power: rms(x) ** (power / 2), x, method="trf", max_nfev=2000).x
        best = min(best, worst_median(x))
    return fitted, best


def ruler_loops(photos: int, size: tuple[int, int], reference: DirectReference) -> list[tuple[int, int, int, int, float, float]]:
    """Where three photos i < j < k have rulers for all three pairs: at the inliers of i-k that
    also lie in photo j, how far apart the two ways round the loop put them (i -> j -> k against
    i -> k; median, px), and so how far, at the least, one of the three placements of any panorama
    is off its ruler at half of those points (the miss over 2 + the scale of j -> k: around the
    loop the placements compose to nothing, so the three errors, j -> k's scaled, add up to at least
    the miss).  Rows (i, j, k, points, miss, least)."""
    def H(a: int, b: int) -> np.ndarray:
        ref = reference(min(a, b), max(a, b))
        assert ref is not None
        return ref.H if a < b else np.linalg.inv(ref.H)

    rows = []
    for i, j, k in itertools.combinations(range(photos), 3):
        rulers = [reference(*pair) for pair in ((i, j), (j, k), (i, k))]
        if any(r is None for r in rulers):
            continue
        ij, jk = H(i, j), H(j, k)
        in_j = project(ij, rulers[2].points)
        inside = np.all((in_j >= 0) & (in_j < size), axis=1)
        if inside.sum() < 20:
            continue
        points, in_j = rulers[2].points[inside], in_j[inside]
        miss = np.linalg.norm(project(jk, in_j) - project(H(i, k), points), axis=1)
        at = in_j.mean(axis=0)  # j -> k's Jacobian where the points lie
        jacobian = (jk[:2, :2] - np.outer(project(jk, at[None])[0], jk[2, :2])) / (jk[2] @ [*at, 1.0])
        scale = np.linalg.svd(jacobian, compute_uv=False)[0]
        rows.append((i, j, k, len(points), float(np.median(miss)), float(np.median(miss)) / (2 + scale)))
    return rows


def _gap_summary(gaps) -> str:
    known = [(g, amb) for _, _, g, amb in gaps if g is not None]
    ambiguous = sum(amb > DirectReference.AMBIGUOUS for _, amb in known)
    text = "none"
    if known:
        text = f"median {np.median([g for g, _ in known]):.2f} max {max(g for g, _ in known):.2f} px over {len(known)} ({ambiguous} ambiguous)"
    listed = ", ".join(
        f"{i}-{j} " + ("n/a" if g is None else f"{g:.2f}" + ("" if amb <= DirectReference.AMBIGUOUS else f" (ambiguous {amb:.1f})"))
        for i, j, g, amb in gaps
    )
    return f"{text} [{listed}]"


def photos(args) -> dict:
    """Every ODM folder at full resolution: every photo used or named; used photos against a
    direct full-resolution registration (``DirectReference``): consecutive ones, and the other
    pairs the panorama makes overlap.  Stitched as ``mosaic stitch FOLDER`` does (``gps``: the
    photos' EXIF GPS guiding the pairs and the matching, and the map's fit, where they have it),
    then by their pixels alone (``--telemetry none``) with and without drift control."""
    from mosaic_cli.geo.georef import GeorefOptions
    from mosaic_cli.telemetry import read_photo_folder

    rows = []
    folders = sorted(p for p in ODM.iterdir() if p.is_dir() and (not args.folders or p.name in args.folders))
    for folder in folders:
        files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
        reference = DirectReference(files)
        size = cv2.imread(str(files[0]), cv2.IMREAD_REDUCED_GRAYSCALE_8).shape[1::-1]
        size = (size[0] * 8, size[1] * 8)
        row = {"folder": folder.name, "photos": len(files)}
        runs = [("gps", True, GeorefOptions())] if read_photo_folder(folder) is not None else []
        runs += [("dc", True, None), ("no-dc", False, None)]
        for label, enabled, georef in runs:
            options = StitchOptions(registration=RegistrationOptions(enabled=enabled, max_loop_pairs=args.max_loop_pairs), georef=georef)
            start = time.perf_counter()
            result = stitch(folder, args.workdir / f"{folder.name}_{label}.png", make_estimator(args.estimator), options, show_progress=False)
            seconds = time.perf_counter() - start
            consecutive, other = [], []
            for pano in result.panoramas:
                c, o = photo_pairs(pano, size)
                consecutive += placement_gaps(c, reference)
                other += placement_gaps(o, reference)
            used = sorted(i for p in result.panoramas for i, _ in p.transforms)
            row[label] = {
                "panoramas": [[i for i, _ in p.transforms] for p in result.panoramas],
                "dropped": [(files[i].name, why) for i, why in result.dropped],
                "all accounted": sorted(used + [i for i, _ in result.dropped]) == list(range(len(files))),
                "consecutive": consecutive, "other": other, "seconds": seconds, "loops": result.registration.loops,
            }
        first = row[runs[0][0]]
        row["floor"] = ruler_floor([(i, j) for i, j, _, _ in first["consecutive"] + first["other"]], reference)
        row["ruler loops"] = ruler_loops(len(files), size, reference)
        rows.append(row)
        print(f"{folder.name}: {len(files)} photos; one homography per photo fitted to these rulers (ruler_floor): "
              f"{row['floor'][1]:.2f} px at the worst pair (least squares: {row['floor'][0]:.2f} px)", flush=True)
        for i, j, k, n, miss, least in row["ruler loops"]:
            print(f"  rulers {i}-{j}-{k}: round the loop {miss:.2f} px apart at {n} shared points: "
                  f"any panorama is {least:.2f} px off one of them at half of those points")
        for label, _, _ in runs:
            r = row[label]
            print(
                f"  {label:6s} panoramas {r['panoramas']}, dropped {r['dropped']}, every photo accounted for: {r['all accounted']}, "
                f"{r['loops']} loops, {r['seconds']:.0f} s\n"
                f"         consecutive photos vs a direct full-res registration: {_gap_summary(r['consecutive'])}\n"
                f"         other overlapping photos: {_gap_summary(r['other'])}",
                flush=True,
            )
    names = f" --folders {' '.join(args.folders)}" if args.folders else ""
    loops = f" --max-loop-pairs {args.max_loop_pairs}" if args.max_loop_pairs != RegistrationOptions.max_loop_pairs else ""
    print(f"  reproduce: {here(args, 'photos')}{names}{loops}")
    return {"photos": rows}


# -- throughput --------------------------------------------------------------------------------


def throughput(args) -> dict:
    video = survey_flight(args.workdir, args.frames, (1280, 720), args.seeds[0])
    runs = []
    for _ in range(args.repeat):
        cpu0 = time.process_time()
        load = os.getloadavg()[0]
        result = stitch(video, args.workdir / "throughput.jpg", make_estimator(args.estimator), show_progress=False)
        total = sum(result.seconds.values())
        runs.append(
            {"fps": result.frames / total, "scan_fps": result.frames / result.seconds["scan"], "seconds": result.seconds,
             "cpu_s": time.process_time() - cpu0, "load": load, "frames": result.frames}
        )
        print(
            f"  {result.frames} frames 1280x720: {runs[-1]['fps']:.1f} fr/s overall (scan {runs[-1]['scan_fps']:.1f} fr/s), "
            f"stages {', '.join(f'{k} {v:.1f}s' for k, v in result.seconds.items())}, CPU {runs[-1]['cpu_s']:.1f}s, load {load:.1f}",
            flush=True,
        )
    fps = float(np.median([r["fps"] for r in runs]))
    print(f"throughput ({args.estimator}, 720p, median of {len(runs)}): {fps:.1f} fr/s overall; "
          f"reproduce: {here(args, 'throughput')} --repeat {args.repeat} --estimator {args.estimator}")
    return {"throughput": runs, "throughput_median_fps": fps, "estimator": args.estimator}


# -- memory ------------------------------------------------------------------------------------


def peak_rss_of(cmd: list[str]) -> tuple[float, float, str]:
    """Peak RSS (MiB) and wall time of one command, measured in a fresh child process."""
    probe = (
        "import resource, subprocess, sys, time; t = time.time(); "
        "r = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, time.time() - t, r.returncode); "
        "sys.stderr.write(r.stderr[-2000:])"
    )
    run = subprocess.run([sys.executable, "-c", probe, *cmd], capture_output=True, text=True)
    rss, seconds, code = run.stdout.split()
    if int(code) != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {run.stderr}")
    return float(rss), float(seconds), run.stderr


def memory(args) -> dict:
    rows = []
    for frames in args.lengths:
        video = long_flight(args.workdir, frames, args.speed)
        out = args.workdir / f"{long_name(frames, args.speed)}_pano.jpg"
        cmd = [sys.executable, "-m", "mosaic_cli", "stitch", str(video), "-o", str(out), "--transforms", str(out.with_suffix(".json")), "-q"]
        rss, seconds, _ = peak_rss_of(cmd)
        canvas = json.loads(out.with_suffix(".json").read_text())["canvas_size"]
        used = len(json.loads(out.with_suffix(".json").read_text())["frames"])
        rows.append({"estimator": DEFAULT_ESTIMATOR, "frames": frames, "peak_rss_mib": rss, "seconds": seconds, "canvas": canvas, "keyframes": used})
        print(f"  1920x1080, {frames} frames ({frames / 30:.0f} s of flight, {args.speed:g} px/frame): peak RSS {rss:.0f} MiB, {seconds:.0f} s, "
              f"{used} keyframes, canvas {canvas[0]}x{canvas[1]}", flush=True)
    speed = "" if args.speed == 8.0 else f" --speed {args.speed:g}"
    print(f"memory (mosaic stitch with its defaults: estimator {DEFAULT_ESTIMATOR}): reproduce: {here(args, 'memory')} --lengths {' '.join(map(str, args.lengths))}{speed}")
    return {"memory": rows}


def accuracy_long(args) -> dict:
    """Placement accuracy on the memory flights (long, over a procedural map), read from the
    transforms their ``memory`` runs wrote: run ``memory`` first."""
    rows = [long_accuracy(args.workdir, frames, args.speed) for frames in args.lengths]
    print(f"  reproduce: {here(args, 'memory')} --lengths {' '.join(map(str, args.lengths))} && "
          f"{here(args, 'accuracy-long')} --lengths {' '.join(map(str, args.lengths))}")
    return {"accuracy_long": rows}


def long_accuracy(workdir: Path, frames: int, speed: float) -> dict:
    """Placement accuracy on a memory flight (from the transforms its run wrote), and plain
    chaining between the same used frames."""
    video = workdir / f"{long_name(frames, speed)}.mp4"
    gt = load_ground_truth(video.with_suffix(".gt.json"))
    data = json.loads((workdir / f"{long_name(frames, speed)}_pano.json").read_text())
    indices = [f["index"] for f in data["frames"]]
    ours = placement_errors(indices, [np.array(f["H"]) for f in data["frames"]], gt.map_to_frame, gt.size, GAP)
    plain = placement_errors(indices, plain_chain(video, indices), gt.map_to_frame, gt.size, GAP)
    print(f"  {frames} frames: median corner error (1920x1080 px) over {len(ours)} pairs >= {GAP} frames apart: "
          f"drift control {np.median(ours):.2f} px (90th pct {np.percentile(ours, 90):.1f}) | plain chaining "
          f"{np.median(plain):.2f} px (90th pct {np.percentile(plain, 90):.1f})", flush=True)
    return {"frames": frames, "median_error": float(np.median(ours)), "plain_chaining": float(np.median(plain))}


def stitch_command(argv: list[str] | None = None) -> int | None:
    """Benchmarks of ``mosaic stitch`` on simulated flights with exact ground truth.

        python -m benchmarks stitch accuracy     # placement accuracy vs plain chaining (720p survey)
        python -m benchmarks stitch throughput   # frames/s with the ORB estimator on 720p input (or --estimator lstm)
        python -m benchmarks stitch memory       # peak RSS of 1080p flights of growing length and area
        python -m benchmarks stitch accuracy-long  # placement accuracy on those (after memory)
        python -m benchmarks stitch revisits     # forward-then-backward and looped (cut) 720p flights, exact truth
        python -m benchmarks stitch real-revisits  # the real sparse drone frames, forward then backward
        python -m benchmarks stitch photos       # the real ODM photo folders at full resolution
        python -m benchmarks stitch all

    Flights are rendered (and cached) under --workdir by ``mosaic_cli.simulate`` over the real
    NEON orthophoto in ../shared/data when present (a procedural map otherwise).  Every number is
    printed with the command that reproduces it.
    """
    parser = make_parser(SUITE, None, stitch_command.__doc__)
    parser.add_argument("what", choices=["accuracy", "throughput", "memory", "accuracy-long", "revisits", "real-revisits", "photos", "all"])
    parser.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR)
    parser.add_argument("--frames", type=int, default=900, help="frames of the 720p survey flights")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--revisit-frames", type=int, default=300, help="frames of each pass of the revisit flights")
    parser.add_argument("--estimator", default="orb", help="the estimator of the accuracy and throughput runs (the throughput goal is stated for orb)")
    parser.add_argument("--lengths", type=int, nargs="+", default=[1000, 2000, 4000], help="frames of the 1080p memory flights")
    parser.add_argument("--speed", type=float, default=8.0, help="map pixels per frame of the memory flights")
    parser.add_argument("--folders", nargs="*", default=[], help="photos: only these ODM folders (all by default)")
    parser.add_argument("--max-loop-pairs", type=int, default=RegistrationOptions.max_loop_pairs,
                        help="photos: drift control's loop pairs (0: the refinement of the consecutive registrations alone)")
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    args = parser.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    results = {"load_average_at_start": os.getloadavg()[0], "cpus": os.cpu_count()}
    steps = (("accuracy", accuracy), ("throughput", throughput), ("memory", memory), ("accuracy-long", accuracy_long), ("revisits", revisits), ("real-revisits", real_revisits), ("photos", photos))
    for what, fn in steps:
        if args.what in (what, "all"):
            results.update(fn(args))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=float))


# -- python -m benchmarks stitch drift-solver ------------------------------------------------------

SIZE = (640, 360)


def scipy_solve(problem, x0: np.ndarray, options: RegistrationOptions, tight: bool = False) -> np.ndarray:
    """Drift control's solve by ``scipy.optimize.least_squares`` (trf, sparse Jacobian)."""
    extra = {"tr_options": {"atol": 1e-10, "btol": 1e-10}, "max_nfev": 2000} if tight else {"max_nfev": options.max_steps}
    result = least_squares(
        problem.residuals,
        x0,
        jac=problem.jacobian,
        method="trf",
        loss=lambda z: problem.loss(z, options.loss_scale),
        x_scale="jac",
        tr_solver="lsmr",
        xtol=1e-10,
        ftol=options.tolerance,
        **extra,
    )
    return result.x


SOLVERS = {
    "lm": registration._solve,
    "scipy": scipy_solve,
    "scipy-tight": lambda p, x, o: scipy_solve(p, x, o, tight=True),
}


# -- flights ---------------------------------------------------------------------------------


def survey(workdir: Path, frames: int, seed: int) -> tuple[Path, np.ndarray]:
    path = workdir / f"survey_{SIZE[0]}x{SIZE[1]}_{frames}_s{seed}.mp4"
    if not path.exists():
        subprocess.run(
            [sys.executable, "-m", "mosaic_cli", "simulate", str(ORTHOPHOTO), "-p", "survey", "-n", str(frames),
             "--size", f"{SIZE[0]}x{SIZE[1]}", "--seed", str(seed), "-o", str(path), "-q"],
            check=True,
        )
    return path, load_ground_truth(path.with_suffix(".gt.json")).map_to_frame


def forward_backward(workdir: Path, frames: int, seed: int) -> tuple[Path, np.ndarray]:
    path = workdir / f"fb_{SIZE[0]}x{SIZE[1]}_{frames}_s{seed}.mp4"
    if not path.exists():
        ground = load_map(ORTHOPHOTO, seed=seed)
        plan = plan_flight((ground.shape[1], ground.shape[0]), "fast", frames, SIZE, seed)
        plan = dataclasses.replace(
            plan,
            map_to_frame=np.concatenate([plan.map_to_frame, plan.map_to_frame[::-1]]),
            smooth_map_to_frame=np.concatenate([plan.smooth_map_to_frame, plan.smooth_map_to_frame[::-1]]),
        )
        write_flight(path, ground, plan, map_name=ORTHOPHOTO.name, preset="veryfast", show_progress=False)
    return path, load_ground_truth(path.with_suffix(".gt.json")).map_to_frame


def mapping(workdir: Path, seed: int) -> tuple[Path, np.ndarray]:
    """``python -m benchmarks georef``'s mapping flight (2507 frames of 640x360 along four 410 m lines over
    a procedural map, about 118 keyframes), stitched here without its telemetry."""
    from benchmarks.georef import mapping_flight

    path = mapping_flight(workdir, seed)
    return path, load_ground_truth(path.with_suffix(".gt.json")).map_to_frame


def keyframe_errors(transforms, truth) -> np.ndarray:
    """``placement_errors`` of a stitch's ``(index, H)`` keyframes."""
    return placement_errors([i for i, _ in transforms], [H for _, H in transforms], truth, SIZE, GAP)


# -- runs ------------------------------------------------------------------------------------


def run(video: Path, truth: np.ndarray, solver, workdir: Path, captured: list | None = None) -> dict:
    """One stitch with ``solver`` in drift control: seconds in the solver, corner errors."""
    seconds = [0.0]
    real_refine = registration.refine_placements

    def timed(problem, x0, options):
        start = time.perf_counter()
        x = solver(problem, x0, options)
        seconds[0] += time.perf_counter() - start
        return x

    def capture(initial, report, reference, size, options):
        if captured is not None:
            captured.append(([P.copy() for P in initial], list(report.links), reference, size, options))
        return real_refine(initial, report, reference, size, options)

    registration._solve, registration.refine_placements = timed, capture
    try:
        result = stitch(video, workdir / f"{video.stem}.png", make_estimator("orb"), StitchOptions(), show_progress=False)
    finally:
        registration._solve, registration.refine_placements = SOLVERS["lm"], real_refine
    errors = keyframe_errors(result.transforms, truth)
    return {"solve_s": seconds[0], "median": float(np.median(errors)), "max": float(errors.max()),
            "keyframes": len(result.transforms), "loops": result.registration.loops}


def replay(captured: list, solver) -> tuple[float, float]:
    """The captured refinements solved again with ``solver``: seconds and the final robust cost."""
    seconds, cost = 0.0, 0.0
    for initial, links, reference, size, options in captured:
        report = RegistrationReport(links=[dataclasses.replace(l) for l in links], residual_before=1.0)
        registration._solve = solver
        try:
            start = time.perf_counter()
            placements = refine_placements(initial, report, reference, size, options)
            seconds += time.perf_counter() - start
        finally:
            registration._solve = SOLVERS["lm"]
        # The cost of the result on the problem's final links, from the placements themselves.
        problem = registration._Problem(placements, report.links, reference, size)
        cost += problem.cost(problem.residuals(np.zeros(problem.n_params)), options.loss_scale)
    return seconds, cost


def drift_solver_command(argv: list[str] | None = None) -> int | None:
    """Drift control's solver against scipy's: the time of the solve and the placement accuracy.

        python -m benchmarks stitch drift-solver                 # survey and forward+backward flights, 640x360
        python -m benchmarks stitch drift-solver --seeds 1 2 --survey-frames 900 --revisit-frames 300

    Flights (cached under --workdir): ``mosaic simulate -p survey`` over the NEON orthophoto of
    ../shared/data/aerial_stills (lawnmower lines that revisit their ground) and a 'fast' flight
    flown forward then backward (as ``python -m benchmarks stitch revisits``, smaller), all with the
    simulator's exact homographies.

    Each flight is stitched (``orb``, drift control on) once per solver: ``lm`` is the one in
    ``mosaic_cli/stitch/registration.py`` (Levenberg-Marquardt, exact sparse steps); ``scipy`` is
    ``scipy.optimize.least_squares`` (method "trf", the same analytic sparse Jacobian, the same
    weighted soft-L1 loss, ``x_scale="jac"``, LSMR steps), as drift control used it before commit
    45b6c42; ``scipy-tight`` is the same with LSMR run to 1e-10 and a budget of 2000 evaluations.
    Reported per flight and solver: the seconds in the solver (all refinements of the run), the
    robust cost each solver reaches on the identical problems (the first run's refinements
    replayed), and the median and largest corner error of keyframes at least 60 frames apart
    against the exact homographies (as ``python -m benchmarks stitch``).
    """
    parser = make_parser(SUITE, 'drift-solver', drift_solver_command.__doc__)
    parser.add_argument("--seeds", type=int, nargs="*", default=[1, 2], help="survey and forward+backward flights of these seeds")
    parser.add_argument("--survey-frames", type=int, default=900)
    parser.add_argument("--revisit-frames", type=int, default=300)
    parser.add_argument("--mapping", type=int, nargs="*", default=[], help="also python -m benchmarks georef's mapping flights of these seeds")
    parser.add_argument("--solvers", nargs="+", default=list(SOLVERS), choices=list(SOLVERS))
    parser.add_argument("--no-replay", dest="replay", action="store_false", help="skip solving the first run's problems again with each solver")
    parser.add_argument("--workdir", type=Path, default=ROOT / ".dev" / "bench_drift_solver")
    parser.add_argument("--json", type=Path, help="write the rows here too")
    args = parser.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    flights = [f(args.workdir, n, seed) for seed in args.seeds for f, n in ((survey, args.survey_frames), (forward_backward, args.revisit_frames))]
    flights += [mapping(args.workdir, seed) for seed in args.mapping]
    for video, truth in flights:
        captured: list = []
        for name in args.solvers:
            row = {"flight": video.name, "solver": name}
            row.update(run(video, truth, SOLVERS[name], args.workdir, captured if not captured else None))
            rows.append(row)
            print(
                f"{row['flight']:28s} {name:12s} {row['keyframes']:3d} keyframes {row['loops']:3d} loops; solve {row['solve_s']:6.2f} s; "
                f"corner error >= {GAP} apart median {row['median']:.3f} max {row['max']:.3f} px",
                flush=True,
            )
        for name in args.solvers if args.replay else ():
            seconds, cost = replay(captured, SOLVERS[name])
            print(f"{video.name:28s} {name:12s} the same {len(captured)} problems: {seconds:6.2f} s, robust cost {cost:.6g}", flush=True)
            row = next(r for r in rows if r["flight"] == video.name and r["solver"] == name)
            row.update({"replay_s": seconds, "replay_cost": cost, "refinements": len(captured)})
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


COMMANDS = {
    "drift-solver": drift_solver_command,
}


def main(argv: list[str]) -> int:
    return run_commands(SUITE, __doc__, COMMANDS, argv, default=stitch_command)
