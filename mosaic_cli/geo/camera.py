"""The camera model telemetry is read with: a pinhole looking down, tilted by the gimbal.

Frame pixels follow the OpenCV pixel-centre convention; the principal point is the frame
centre and the focal length (pixels) comes from the horizontal field of view.  Angles are in
the convention of :class:`mosaic_cli.telemetry.FlightLog`: ``pitch`` -90 looks straight down and
above -90 tilts toward the frame's top; ``roll`` positive tilts toward the frame's right;
``yaw`` is the compass bearing of the frame's top edge.  With

    Rx(a) = rotation about the camera x axis,  Ry(b) = about its y axis,
    a = -(pitch + 90) degrees,  b = -roll degrees,

a ground plane seen by the camera maps to the frame by ``K @ Rx(a) @ Ry(b) @ (similarity)``,
so ``K @ Ry(b)^T @ Rx(a)^T @ K^-1`` undoes the tilt (a nadir view up to a similarity), and
the point straight below the camera shows at pixel ``K @ Rx(a) @ Ry(b) @ [0, 0, 1]``.
"""

from __future__ import annotations

import math

import numpy as np


def focal_pixels(width: int, hfov_deg: float) -> float:
    return (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)


def hfov_degrees(width: int, focal: float) -> float:
    return math.degrees(2.0 * math.atan((width / 2.0) / focal))


def intrinsics(size: tuple[int, int], focal: float) -> np.ndarray:
    w, h = size
    return np.array([[focal, 0, (w - 1) / 2.0], [0, focal, (h - 1) / 2.0], [0, 0, 1.0]])


def tilt_rotation(pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Rx(a) @ Ry(b) for the gimbal's pitch and roll (NaN: straight down)."""
    a = -math.radians(pitch_deg + 90.0) if math.isfinite(pitch_deg) else 0.0
    b = -math.radians(roll_deg) if math.isfinite(roll_deg) else 0.0
    ca, sa, cb, sb = math.cos(a), math.sin(a), math.cos(b), math.sin(b)
    Rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    Ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    return Rx @ Ry


def gimbal_angles(a_rad: float, b_rad: float) -> tuple[float, float]:
    """(pitch, roll) degrees of the rotation Rx(a) @ Ry(b) (the inverse of tilt_rotation)."""
    return -90.0 - math.degrees(a_rad), -math.degrees(b_rad)


def nadir_pixel(size: tuple[int, int], focal: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Pixel (x, y) straight below the camera."""
    p = intrinsics(size, focal) @ tilt_rotation(pitch_deg, roll_deg) @ np.array([0.0, 0.0, 1.0])
    return p[:2] / p[2]


def untilt(size: tuple[int, int], focal: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Frame pixels -> pixels of the same camera looking straight down (a homography)."""
    K = intrinsics(size, focal)
    H = K @ tilt_rotation(pitch_deg, roll_deg).T @ np.linalg.inv(K)
    return H / H[2, 2]
