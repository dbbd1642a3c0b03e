"""Lens files: ``--lens FILE`` and ``mosaic simulate --lens FILE`` read three formats as they are.

* mosaic's own (docs/guide/stitch.md, "Lenses")::

    {"model": "pinhole" | "fisheye", "size": [w, h], "camera_matrix": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
     "coefficients": [k1, k2, p1, p2, k3] | [k1, k2, k3, k4]}

* a Gyroflow lens profile (its lens_profiles database, its calibrator's output):
  ``calib_dimension: {w, h}``, ``fisheye_params: {camera_matrix, distortion_coeffs}`` and
  ``distortion_model`` ("opencv_fisheye", the default, or "opencv_standard"; older profiles
  say ``use_opencv_standard: true`` instead).  Gyroflow's other models (poly3, poly5, ptlens,
  insta360, sony) are refused by name.
* an ODM / OpenSfM ``cameras.json`` (one camera): ``{"<camera id>": {"projection_type", "width",
  "height", ...}}`` with the focal lengths and principal point offset normalised by
  max(width, height) (OpenSfM's normalised image coordinates: pixel x = x_n * max(w, h) + w / 2
  - 0.5 in OpenCV pixel centres).  ``brown``: focal_x, focal_y, c_x, c_y, k1, k2, p1, p2, k3
  (OpenCV's radial-tangential model, the same order); ``perspective``: focal, k1, k2 (radial
  only); ``fisheye``: focal, k1, k2 (equidistant, OpenCV's fisheye with k3 = k4 = 0).

A simulated flight's ground truth (``<stem>.gt.json`` with a ``"lens"``) is read as its lens.

Every failure is one :class:`~mosaic_cli.errors.BadInput` line naming the file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.geometry.lens import Lens

GYROFLOW_MODELS = {"opencv_fisheye": "fisheye", "opencv_standard": "pinhole"}


def read_lens(path: str | Path) -> Lens:
    """The lens described by ``path`` (any of the three formats, told apart by their keys)."""
    p = Path(path)
    if not p.is_file():
        raise BadInput(f"--lens {p}: no such file")
    try:
        doc = json.loads(p.read_text())
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise BadInput(f"--lens {p}: not a JSON file ({exc.__class__.__name__})") from None
    try:
        if not isinstance(doc, dict):
            raise ValueError("a JSON object was expected")
        if doc.get("kind") == "mosaic-ground-truth" and isinstance(doc.get("lens"), dict):
            return mosaic_lens(doc["lens"])  # a simulated flight's truth: the lens it was rendered through
        if "calib_dimension" in doc or "fisheye_params" in doc:
            return gyroflow_lens(doc)
        if "camera_matrix" in doc and "model" in doc:
            return mosaic_lens(doc)
        if doc and all(isinstance(v, dict) and "projection_type" in v for v in doc.values()):
            return opensfm_lens(doc)
        raise ValueError("not a lens file: a mosaic lens (model, size, camera_matrix, coefficients), "
                         "a Gyroflow lens profile or an OpenSfM/ODM cameras.json was expected")
    except (ValueError, TypeError, KeyError, IndexError) as exc:
        why = f"missing {exc}" if isinstance(exc, KeyError) else str(exc)
        raise BadInput(f"--lens {p}: {why}") from None


def mosaic_lens(doc: dict) -> Lens:
    return Lens.make(doc["model"], _size(doc["size"]), doc["camera_matrix"], doc["coefficients"])


def gyroflow_lens(doc: dict) -> Lens:
    dim = doc["calib_dimension"]
    size = (int(dim["w"]), int(dim["h"]))
    name = doc.get("distortion_model") or ("opencv_standard" if doc.get("use_opencv_standard") else "opencv_fisheye")
    if name not in GYROFLOW_MODELS:
        raise ValueError(f"Gyroflow's {name!r} distortion model is not supported (opencv_fisheye, opencv_standard)")
    stretch = (float(doc.get("input_horizontal_stretch") or 1.0), float(doc.get("input_vertical_stretch") or 1.0))
    if stretch != (1.0, 1.0):
        raise ValueError(f"an anamorphic profile (input stretch {stretch[0]:g} x {stretch[1]:g}) is not supported")
    params = doc["fisheye_params"]
    coefficients = [float(c) for c in params["distortion_coeffs"]]
    model = GYROFLOW_MODELS[name]
    if model == "fisheye":
        coefficients = coefficients[:4]  # (some profiles pad the list)
    elif len(coefficients) not in (4, 5, 8):  # OpenCV's order, padded or cut to its 8
        if any(coefficients[8:]):
            raise ValueError("thin-prism or tilt coefficients (past the 8th) are not supported")
        coefficients = (coefficients + [0.0] * 8)[:8]
    return Lens.make(model, size, params["camera_matrix"], coefficients)


def opensfm_lens(doc: dict) -> Lens:
    if len(doc) != 1:
        raise ValueError(f"{len(doc)} cameras in the file ({', '.join(sorted(doc))}): keep the video's one")
    cam = next(iter(doc.values()))
    kind = cam["projection_type"]
    w, h = int(cam["width"]), int(cam["height"])
    if w < 1 or h < 1:
        raise ValueError("width and height must be positive")
    scale = float(max(w, h))

    def matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
        return np.array([[fx * scale, 0.0, cx * scale + w / 2 - 0.5], [0.0, fy * scale, cy * scale + h / 2 - 0.5], [0.0, 0.0, 1.0]])

    if kind == "brown":
        K = matrix(cam["focal_x"], cam["focal_y"], cam.get("c_x", 0.0), cam.get("c_y", 0.0))
        return Lens.make("pinhole", (w, h), K, [cam.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")])
    if kind == "perspective":
        f = cam["focal"]
        return Lens.make("pinhole", (w, h), matrix(f, f, 0.0, 0.0), [cam.get("k1", 0.0), cam.get("k2", 0.0), 0.0, 0.0, 0.0])
    if kind == "fisheye":
        f = cam["focal"]
        return Lens.make("fisheye", (w, h), matrix(f, f, 0.0, 0.0), [cam.get("k1", 0.0), cam.get("k2", 0.0), 0.0, 0.0])
    raise ValueError(f"OpenSfM projection {kind!r} is not supported (brown, perspective, fisheye)")


def _size(value: list) -> tuple[int, int]:
    w, h = (int(v) for v in value)
    return w, h
