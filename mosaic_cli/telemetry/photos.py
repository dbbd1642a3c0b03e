"""Where each photo of a folder was taken: EXIF GPS, camera and time, and a DJI drone's XMP
attitude, read with Pillow (EXIF) and the standard library's XML parser (XMP), into the same
``FlightLog`` a video's telemetry becomes.

    tags = [read_photo_tags(p) for p in folder_images(folder)]
    track = photo_log(tags, fps)   # photo i at i / fps seconds, as the folder's frames are

Angles follow the ``FlightLog`` convention (:mod:`mosaic_cli.telemetry.flight_log`), which is DJI's:
``GimbalYawDegree`` is the compass direction of the frame's top edge, ``GimbalPitchDegree``
-90 looks straight down.  A photo without GPS has NaN latitude and longitude; a photo whose
EXIF or XMP cannot be read is used by its pixels, the problem kept in ``PhotoTags.problems``.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from mosaic_cli.telemetry.flight_log import FlightLog
from mosaic_cli.telemetry.photo_tags import PhotoTags
from mosaic_cli.video.info import EXIF_ORIENTATION, PhotoFit

DJI = "http://www.dji.com/drone-dji/1.0/"
# EXIF's FocalPlaneResolutionUnit: 2 inches, 3 centimetres, 4 millimetres, 5 micrometres (per unit)
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}

# EXIF tags by number (Pillow's ExifTags names them; numbers keep the lookups plain)
_MAKE, _MODEL, _DATETIME = 271, 272, 306
_GPS_LAT_REF, _GPS_LAT, _GPS_LON_REF, _GPS_LON, _GPS_ALT_REF, _GPS_ALT = 1, 2, 3, 4, 5, 6
_DATETIME_ORIGINAL, _SUBSEC_ORIGINAL, _FOCAL, _FOCAL_35 = 36867, 37521, 37386, 41989
_PLANE_X_RES, _PLANE_UNIT = 41486, 41488
_XMP_TIFF_TAG = 700
DEFAULT_PHOTO_INTERVAL = 2.0  # seconds between survey photos when their EXIF gives no time


def read_photo_tags(path: str | Path) -> PhotoTags:
    """The metadata of one JPEG or TIFF photo.  Never raises for damaged metadata: what could
    not be read is named in ``problems`` (the photo's pixels are read elsewhere)."""
    import warnings

    from PIL import Image, UnidentifiedImageError

    tags = PhotoTags(Path(path))
    with warnings.catch_warnings(record=True) as said:  # Pillow's about damaged EXIF: named, not printed
        warnings.simplefilter("always")
        try:
            with Image.open(path) as image:
                tags.width, tags.height_px = image.size
                try:
                    _read_exif(image, tags)
                except Exception as exc:  # a damaged EXIF block must not cost the photo  # noqa: BLE001
                    tags.problems.append(f"EXIF unreadable: {type(exc).__name__}")
                xmp = image.info.get("xmp") or _tiff_xmp(image)
                if xmp:
                    _read_dji_xmp(xmp, tags)
        except (OSError, UnidentifiedImageError, ValueError) as exc:
            tags.problems.append(f"metadata unreadable: {type(exc).__name__}")
    tags.problems += [str(w.message).strip() for w in said if issubclass(w.category, UserWarning)][:1]
    return tags


def photo_rate(tags: list[PhotoTags]) -> float:
    """Photos per second as the camera took them (the median interval of their EXIF times),
    else :data:`DEFAULT_PHOTO_INTERVAL`'s: the rate a folder's photos are read at for
    georeferencing, so that the track's times are seconds the flight took."""
    from datetime import datetime

    stamps = []
    for t in tags:
        if t.time is None:
            continue
        try:
            stamps.append(datetime.strptime(t.time[:26].replace("-", ":", 2), "%Y:%m:%d %H:%M:%S" + (".%f" if "." in t.time else "")).timestamp())
        except ValueError:
            continue
    steps = np.diff(np.sort(np.array(stamps)))
    steps = steps[steps > 0]
    interval = float(np.median(steps)) if len(steps) else DEFAULT_PHOTO_INTERVAL
    return 1.0 / min(max(interval, 0.05), 60.0)


def photo_log(tags: list[PhotoTags], fps: float, source: str) -> FlightLog:
    """The photos as telemetry samples: photo i at ``i / fps`` seconds, the time the folder's
    reader gives its i-th frame, so that the video path aligns fixes to keyframes unchanged."""
    n = len(tags)

    def column(name: str) -> np.ndarray:
        return np.array([getattr(t, name) for t in tags], dtype=np.float64) if n else np.zeros(0)

    hfov = np.array([_hfov_across_frame(t, tags[0]) for t in tags], dtype=np.float64) if n else np.zeros(0)
    fixed = sum(t.has_fix for t in tags)
    track = FlightLog(f"{source} (EXIF GPS of {fixed} of {n} photos)", np.arange(n, dtype=np.float64) / fps,
                      column("lat"), column("lon"), column("alt"), column("height"), column("shown_yaw"), column("pitch"),
                      column("roll"), hfov, photos=list(tags))
    return track


def _hfov_across_frame(tags: PhotoTags, first: PhotoTags) -> float:
    """The field of view across the folder's frame (the first photo's) that ``tags``'s photo
    spans once read into it (video/folders.py: another camera's photo is fitted whole into that
    frame, and may not fill its width): degrees, NaN where unknown."""
    if first.width <= 0 or tags.width <= 0 or not math.isfinite(tags.hfov):
        return tags.hfov
    frame = first.shown_size
    spans = PhotoFit.into(frame, tags.shown_size).box[2]  # frame px
    return math.degrees(2.0 * math.atan(math.tan(math.radians(tags.hfov) / 2.0) * frame[0] / spans))


def photo_log_rate(track: FlightLog) -> float:
    """The rate (photos per second) a photo folder's ``track`` was made at (:func:`photo_log`)."""
    return 1.0 / float(np.median(np.diff(track.time))) if len(track) > 1 else 1.0 / DEFAULT_PHOTO_INTERVAL


def photo_metadata_notes(tags: list[PhotoTags]) -> list[str]:
    """What a geotagged folder's metadata could not give, one line per damaged photo and one
    for the photos without GPS: they are placed by their pixels alone.  (Photos of another
    camera: video/folders.py's ``other_cameras_note``, GPS or not.)"""
    lines = [f"photo {t.path.name}: {'; '.join(t.problems)}: placed by its pixels" for t in tags if t.problems]
    missing = [t.path.name for t in tags if not t.has_fix and not t.problems]
    if missing:
        shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
        lines.append(f"{len(missing)} of {len(tags)} photos have no GPS, placed by their pixels: {shown}")
    return lines


# -- EXIF ---------------------------------------------------------------------------------
def _read_exif(image, tags: PhotoTags) -> None:
    from PIL import ExifTags

    exif = image.getexif()
    orientation = exif.get(EXIF_ORIENTATION, 1)
    tags.orientation = orientation if orientation in range(1, 9) else 1
    tags.make = _text(exif.get(_MAKE))
    tags.model = _text(exif.get(_MODEL))
    detail = exif.get_ifd(ExifTags.IFD.Exif)
    taken = _text(detail.get(_DATETIME_ORIGINAL)) or _text(exif.get(_DATETIME))
    subsec = _text(detail.get(_SUBSEC_ORIGINAL))
    tags.time = f"{taken}.{subsec}" if taken and subsec else taken
    tags.focal_mm = _number(detail.get(_FOCAL))
    tags.focal_35mm = _number(detail.get(_FOCAL_35))
    x_res, unit = _number(detail.get(_PLANE_X_RES)), detail.get(_PLANE_UNIT, 2)
    if x_res > 0 and unit in _UNIT_MM and tags.width > 0:
        tags.sensor_width_mm = tags.width / x_res * _UNIT_MM[unit]
    gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
    if not gps:
        return
    lat = _degrees(gps.get(_GPS_LAT), gps.get(_GPS_LAT_REF), "NS")
    lon = _degrees(gps.get(_GPS_LON), gps.get(_GPS_LON_REF), "EW")
    if math.isfinite(lat) and math.isfinite(lon):
        if abs(lat) > 90 or abs(lon) > 180:
            tags.problems.append(f"GPS out of range ({lat:.3f}, {lon:.3f})")
        elif lat == 0 and lon == 0:
            pass  # how many cameras write "no fix"
        else:
            tags.lat, tags.lon = lat, lon
    elif _GPS_LAT in gps or _GPS_LON in gps:
        tags.problems.append("GPS position partial or damaged")
    alt = _number(gps.get(_GPS_ALT))
    if math.isfinite(alt):
        below = gps.get(_GPS_ALT_REF) in (1, b"\x01", "1")
        tags.alt = -alt if below else alt


def _degrees(value, ref, signs: str) -> float:
    """EXIF's (degrees, minutes, seconds) rationals and their reference ('N'/'S', 'E'/'W') as
    signed degrees; NaN when missing or malformed."""
    try:
        d, m, s = (float(v) for v in value)
    except (TypeError, ValueError, ZeroDivisionError):
        return math.nan
    degrees = d + m / 60.0 + s / 3600.0
    if not math.isfinite(degrees):
        return math.nan
    ref = _text(ref)
    if ref and ref.strip().upper()[:1] == signs[1]:
        degrees = -degrees
    return degrees


def _number(value) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return math.nan
    return out if math.isfinite(out) else math.nan


def _text(value) -> str | None:
    if value is None:
        return None
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    value = str(value).strip("\x00 ").strip()
    return value or None


# -- DJI XMP ------------------------------------------------------------------------------
def _tiff_xmp(image) -> bytes | None:
    tag = getattr(image, "tag_v2", None)
    value = tag.get(_XMP_TIFF_TAG) if tag is not None else None
    return value.encode() if isinstance(value, str) else value


def _read_dji_xmp(xmp: bytes | str, tags: PhotoTags) -> None:
    """DJI's ``drone-dji:`` values, written as attributes of an rdf:Description (or as its
    elements): relative altitude and the gimbal's (else the aircraft's) attitude."""
    text = xmp.decode("utf-8", "replace") if isinstance(xmp, bytes) else xmp
    if DJI not in text:
        return
    start, end = text.find("<x:xmpmeta"), text.rfind("</x:xmpmeta>")
    body = text[start:end + len("</x:xmpmeta>")] if start >= 0 and end > start else text
    try:
        root = ET.fromstring(body)
    except ET.ParseError:
        tags.problems.append("DJI XMP unreadable")
        return
    values: dict[str, str] = {}
    for element in root.iter():
        for key, value in element.attrib.items():
            if key.startswith("{" + DJI + "}"):
                values[key[len(DJI) + 2:]] = value
        if element.tag.startswith("{" + DJI + "}") and element.text:
            values[element.tag[len(DJI) + 2:]] = element.text.strip()
    read = {name: _number(values.get(name)) for name in
            ("RelativeAltitude", "GimbalYawDegree", "GimbalPitchDegree", "GimbalRollDegree", "FlightYawDegree")}
    bad = [name for name, v in read.items() if name in values and not math.isfinite(v)]
    if bad:
        tags.problems.append(f"DJI XMP {', '.join(bad)} not a number")
    tags.height = read["RelativeAltitude"]
    tags.yaw = read["GimbalYawDegree"] if math.isfinite(read["GimbalYawDegree"]) else read["FlightYawDegree"]
    tags.pitch = read["GimbalPitchDegree"]
    tags.roll = read["GimbalRollDegree"]
