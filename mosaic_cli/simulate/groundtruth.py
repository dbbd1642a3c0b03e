"""The ground truth of a simulated flight: its JSON format, reading and writing.

``flight.gt.json`` sits next to ``flight.mp4``::

    {"version": 1, "kind": "mosaic-ground-truth", "frames": N, "size": [w, h], "fps": f,
     "profile": p, "seed": s, "map": name, "map_size": [W, H], "direction": "t_to_t+1",
     "map_to_frame": [N 3x3], "smooth_map_to_frame": [N 3x3], "pairwise": [N-1 3x3]}

``map_to_frame[t]`` maps map pixels to pixels of frame t; ``pairwise[t]`` maps frame t to
frame t+1 (= map_to_frame[t+1] @ inv(map_to_frame[t])); ``smooth_map_to_frame`` is the path
without the shake of the 'shaky' and 'shaky-tilt' profiles (equal to ``map_to_frame`` otherwise).

A rolling-shutter flight (``mosaic simulate --rolling-shutter R --vibration HZ,PX``) adds::

    "rolling_shutter": {"readout": R, "vibration_hz": f, "vibration_px": a, "bands": K,
                        "band_rows": [K], "row_bands": [N [K 3x3]]}

A flight with broadband vibration (several tones, or ``noise:LO-HI,PX,DEG``) adds
``"vibration"``: its ``--vibration`` text (``vibration_hz``, ``vibration_px``: the first tone,
0 for noise alone).  ``row_bands[t][k]`` maps map pixels to frame t as seen by the rows of band k (the camera at
time t + R * band_rows[k] / h); rows between band centres blend the two bands' inverses
linearly (:mod:`mosaic_cli.geometry.rolling_shutter`).  ``map_to_frame`` is then the camera at
the frame's mid time (its centre row) and ``smooth_map_to_frame`` that path without shake or
vibration.  Global-shutter flights have no ``rolling_shutter`` key.

A flight seen through a lens (``mosaic simulate --lens``) adds ``"lens"``: the camera in mosaic's
lens format (:mod:`mosaic_cli.geometry.lens_files`).  ``map_to_frame`` and ``pairwise`` are then
those of the *pinhole* frame of the lens's camera matrix: frame pixel p shows the pinhole pixel
``undistort_points(lens, p, lens.K)`` (the file is itself a ``--lens FILE``).  All pixel
coordinates follow the OpenCV pixel-centre convention at full frame resolution.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mosaic_cli.atomic import write_json
from mosaic_cli.errors import BadInput
from mosaic_cli.geometry.rolling_shutter import band_centres
from mosaic_cli.inputs import ground_truth_path
from mosaic_cli.simulate.trajectory import FlightPlan, pairwise_from_absolute

GT_VERSION = 1
GT_KIND = "mosaic-ground-truth"


@dataclass
class GroundTruth:
    map_to_frame: np.ndarray  # (N, 3, 3)
    smooth_map_to_frame: np.ndarray  # (N, 3, 3)
    pairwise: np.ndarray  # (N-1, 3, 3)
    size: tuple[int, int]  # (w, h)
    fps: float
    profile: str
    seed: int
    map_name: str
    map_size: tuple[int, int]
    bursts: list[dict] = field(default_factory=list)  # {"frame": t, "kind": k}: frames without a motion cue
    # Rolling shutter: {"readout", "vibration_hz", "vibration_px"[, "vibration"]} and the bands' map -> frame
    # (N, K, 3, 3); empty and None for a global-shutter flight.
    rolling: dict = field(default_factory=dict)
    row_bands: np.ndarray | None = None
    lens: dict | None = None  # the lens the frames were rendered through (mosaic's lens format); None: a pinhole

    @property
    def readout(self) -> float:
        return float(self.rolling.get("readout", 0.0))

    @property
    def frames(self) -> int:
        return len(self.map_to_frame)

    @classmethod
    def from_plan(cls, plan: FlightPlan, fps: float | None = None, map_name: str = "procedural") -> GroundTruth:
        return cls(
            np.array(plan.map_to_frame, dtype=np.float64),
            np.array(plan.smooth_map_to_frame, dtype=np.float64),
            plan.pairwise,
            (int(plan.size[0]), int(plan.size[1])),
            float(plan.fps if fps is None else fps),
            plan.profile,
            int(plan.seed),
            str(map_name),
            (int(plan.map_size[0]), int(plan.map_size[1])),
            [{"frame": int(b.frame), "kind": str(b.kind)} for b in plan.bursts],
            {} if plan.rolling is None else {"readout": float(plan.rolling.readout), "vibration_hz": float(plan.rolling.vibration_hz),
                                             "vibration_px": float(plan.rolling.vibration_px),
                                             **({"vibration": plan.rolling.describe()} if plan.rolling.broadband else {})},
            None if plan.row_bands is None else np.array(plan.row_bands, dtype=np.float64),
        )

    def with_lens(self, lens) -> GroundTruth:
        """The same truth, its frames rendered through ``lens`` (a :class:`~mosaic_cli.geometry.lens.Lens`, or None)."""
        self.lens = None if lens is None else lens.to_json()
        return self

    def to_json(self) -> dict:
        def mats(a):
            return [[[float(v) for v in row] for row in m] for m in a]

        doc = {
            "version": GT_VERSION,
            "kind": GT_KIND,
            "frames": self.frames,
            "size": list(self.size),
            "fps": self.fps,
            "profile": self.profile,
            "seed": self.seed,
            "map": self.map_name,
            "map_size": list(self.map_size),
            "direction": "t_to_t+1",
            "map_to_frame": mats(self.map_to_frame),
            "smooth_map_to_frame": mats(self.smooth_map_to_frame),
            "pairwise": mats(self.pairwise),
        }
        if self.bursts:  # flights without bursts keep the format they always had
            doc["bursts"] = [dict(b) for b in self.bursts]
        if self.row_bands is not None:  # likewise global-shutter flights
            h, K = self.size[1], self.row_bands.shape[1]
            doc["rolling_shutter"] = {**self.rolling, "bands": K, "band_rows": [float(r) for r in band_centres(h, K)],
                                      "row_bands": [mats(bands) for bands in self.row_bands]}
        if self.lens is not None:  # likewise pinhole flights
            doc["lens"] = self.lens
        return doc

    def save(self, path: str | Path) -> None:
        write_json(path, self.to_json())


def load_ground_truth(path: str | Path) -> GroundTruth:
    """Read a ``.gt.json`` file (or, given a video or a folder of frames, the ``.gt.json`` beside it)."""
    p = Path(path)
    if p.is_dir() and not ground_truth_path(p).is_file():
        raise BadInput(f"{p}: a folder, not a ground-truth file (.gt.json), and no {ground_truth_path(p).name} beside it")
    if p.is_dir() or not p.name.endswith(".json"):  # a video, or a folder of frames: the truth beside it
        p = ground_truth_path(p)
    if not p.exists():
        raise BadInput(f"{p}: no such file")
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise BadInput(f"{p}: not a JSON file ({exc.__class__.__name__})") from None
    if not isinstance(data, dict) or data.get("kind") != GT_KIND:
        raise BadInput(f"{p}: not a mosaic ground-truth file (no \"kind\": \"{GT_KIND}\")")
    if int(data.get("version", 0)) > GT_VERSION:
        raise BadInput(f"{p}: ground-truth version {data.get('version')} is newer than this mosaic understands ({GT_VERSION})")
    try:
        M = np.array(data["map_to_frame"], dtype=np.float64).reshape(-1, 3, 3)
        smooth = np.array(data.get("smooth_map_to_frame", data["map_to_frame"]), dtype=np.float64).reshape(-1, 3, 3)
        if "pairwise" in data:
            pairwise = np.array(data["pairwise"], dtype=np.float64).reshape(-1, 3, 3)
        else:
            pairwise = pairwise_from_absolute(M)
        size = (int(data["size"][0]), int(data["size"][1]))
        map_size = tuple(int(v) for v in data.get("map_size", (0, 0)))
        gt = GroundTruth(
            M, smooth, pairwise, size, float(data.get("fps", 30.0)), str(data.get("profile", "?")),
            int(data.get("seed", 0)), str(data.get("map", "?")), (map_size[0], map_size[1]),
            [{"frame": int(b["frame"]), "kind": str(b["kind"])} for b in data.get("bursts", [])],
        )
        if "rolling_shutter" in data:
            rs = data["rolling_shutter"]
            gt.rolling = {key: float(rs[key]) for key in ("readout", "vibration_hz", "vibration_px")}
            if "vibration" in rs:  # broadband vibration: the --vibration text
                gt.rolling["vibration"] = str(rs["vibration"])
            gt.row_bands = np.array(rs["row_bands"], dtype=np.float64).reshape(len(M), int(rs["bands"]), 3, 3)
        if isinstance(data.get("lens"), dict):
            gt.lens = dict(data["lens"])
    except (KeyError, ValueError, TypeError, IndexError) as exc:
        raise BadInput(f"{p}: malformed ground-truth file ({exc.__class__.__name__}: {exc})") from None
    if len(M) < 2 or len(smooth) != len(M) or len(pairwise) != len(M) - 1:
        raise BadInput(f"{p}: inconsistent ground truth ({len(M)} frames, {len(pairwise)} pairwise matrices)")
    if not (np.all(np.isfinite(M)) and np.all(np.isfinite(pairwise))):
        raise BadInput(f"{p}: ground truth holds non-finite numbers")
    return gt
