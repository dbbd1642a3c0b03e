"""DJI ``.SRT`` flight logs: one subtitle cue per video frame (newer drones) or per second (older ones).

The variants seen in the field, all read by the same rules:

* bracketed fields, per frame (Mavic Air 2/3, Mini 2/3, Air 2S, Matrice)::

    FrameCnt: 1, DiffTime: 33ms
    2023-03-17 15:41:35.367
    [iso: 100] [shutter: 1/1000.0] [fnum: 2.8] [ev: 0] [focal_len: 24.00] [dzoom_ratio: 1.00]
    [latitude: 41.403130] [longitude: 2.174480] [rel_alt: 51.300 abs_alt: 175.800]
    [gb_yaw: -12.3 gb_pitch: -90.0 gb_roll: 0.0]

  with the misspelling ``[longtitude : 2.17]`` and ``[altitude: 27.6]`` in early firmware;
* ``GPS(lon, lat, alt)`` with ``BAROMETER:h``, per second (Mavic Pro, Phantom 4)::

    HOME(149.0251,-20.2532) 2017.08.05 14:11:51
    GPS(149.0251,-20.2533,16) BAROMETER:1.9

* the comma-separated style ``F/2.8, SS 1000, ISO 100, EV 0, GPS (8.66, 47.20, 17), D 45.49m,
  H 30.50m, ...`` (Phantom 4 Pro, Inspire 2).

A cue's time is its start time.  ``0, 0`` coordinates mean "no fix" (the drone writes them
before it has one).  ``focal_len`` is the 35 mm-equivalent focal length, which DJI writes
times ten on some models (``280`` = 28 mm); the horizontal field of view is taken over a
36 mm-wide frame.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from mosaic_cli.errors import BadInput
from mosaic_cli.telemetry.flight_log import FlightLog, FlightLogBuilder

_TIMING = re.compile(r"(\d+):(\d+):(\d+)[,.](\d+)\s*-->\s*(\d+):(\d+):(\d+)[,.](\d+)")
_TAG = re.compile(r"<[^>]*>")
_NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"
_FIELD = re.compile(r"([A-Za-z][A-Za-z_]*)\s*:\s*(" + _NUMBER + r")")
_GPS = re.compile(r"\bGPS\s*\(\s*(" + _NUMBER + r")\s*,\s*(" + _NUMBER + r")\s*(?:,\s*(" + _NUMBER + r")\s*)?\)")
_HEIGHT = re.compile(r"(?:^|[\s,])H\s+(" + _NUMBER + r")\s*m\b")

# field name (lower case, spaces removed) -> FlightLog column
_NAMES = {
    "latitude": "lat", "lat": "lat",
    "longitude": "lon", "longtitude": "lon", "lon": "lon", "lng": "lon",
    "rel_alt": "height", "barometer": "height", "height": "height",
    "abs_alt": "alt", "altitude": "alt", "alt": "alt",
    "gb_yaw": "yaw", "gb_pitch": "pitch", "gb_roll": "roll",
    "focal_len": "focal_len", "dzoom_ratio": "dzoom",
}


def looks_like_srt(text: str) -> bool:
    return bool(_TIMING.search(text[:2000]))


def hfov_from_focal(focal_35mm: float, zoom: float = 1.0) -> float | None:
    """Horizontal field of view (degrees) of a 35 mm-equivalent focal length, digital zoom included."""
    if not focal_35mm or focal_35mm <= 0:
        return None
    if focal_35mm > 200:  # written times ten
        focal_35mm /= 10.0
    if zoom and zoom > 100:  # written times 10000 on some models
        zoom /= 10000.0
    zoom = zoom if zoom and zoom > 0 else 1.0
    return math.degrees(2 * math.atan(18.0 / (focal_35mm * zoom)))


def parse_cue(text: str) -> dict[str, float]:
    """The telemetry fields of one cue's text (tags stripped); empty when it has none."""
    text = _TAG.sub(" ", text)
    values: dict[str, float] = {}
    for name, number in _FIELD.findall(text):
        key = _NAMES.get(name.lower())
        if key is not None and key not in values:
            values[key] = float(number)
    gps = _GPS.search(text)
    if gps:
        values["lon"], values["lat"] = float(gps.group(1)), float(gps.group(2))
        if gps.group(3) is not None:
            values.setdefault("alt", float(gps.group(3)))
    height = _HEIGHT.search(text)
    if height:
        values.setdefault("height", float(height.group(1)))
    focal = values.pop("focal_len", None)
    zoom = values.pop("dzoom", 1.0)
    if focal is not None:
        hfov = hfov_from_focal(focal, zoom)
        if hfov is not None:
            values["hfov"] = hfov
    return values


def parse_srt_text(text: str, source: str) -> FlightLog:
    """Every cue of an SRT document with at least one telemetry field, as a ``FlightLog``."""
    builder = FlightLogBuilder()
    cues = 0
    for block in re.split(r"\r?\n\s*\r?\n", text.replace("\ufeff", "")):
        m = _TIMING.search(block)
        if not m:
            continue
        cues += 1
        g = [int(v) for v in m.groups()[:4]]
        start = g[0] * 3600 + g[1] * 60 + g[2] + g[3] / 10 ** len(m.group(4))
        values = parse_cue(block[m.end():])
        if values:
            builder.add(start, **values)
    if cues == 0:
        raise BadInput(f"{source}: not an SRT file (no subtitle cue)")
    if not builder.rows:
        raise BadInput(f"{source}: no GPS telemetry in its {cues} subtitle cues (not a DJI flight log?)")
    track = builder.build(source)
    if len(track) > 1:
        step = float(sorted(track.time[1:] - track.time[:-1])[len(track) // 2 - 1])
        track.source = f"{source} (DJI SRT, {'per-frame' if step < 0.2 else 'per-second'})"
    return track


def read_srt(path: str | Path) -> FlightLog:
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8", errors="replace")
    except OSError as exc:
        raise BadInput(f"{p}: cannot read ({exc.strerror})") from None
    return parse_srt_text(text, str(p))
