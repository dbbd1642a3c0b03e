"""GPX tracks (gpxpy) and simple CSV logs.

CSV: a header row naming the columns, any order, case-insensitive: ``time`` (seconds, or an
ISO 8601 date-time), ``lat``/``latitude``, ``lon``/``lng``/``longitude``, ``alt``/``altitude``
(absolute), and optionally ``height``/``rel_alt`` (above the ground), ``yaw``/``heading``,
``pitch``, ``roll``, ``hfov``.  Empty cells are unknown.
"""

from __future__ import annotations

import csv
import math
from datetime import datetime
from pathlib import Path

from mosaic_cli.errors import BadInput, require_geo
from mosaic_cli.telemetry.flight_log import FlightLog, FlightLogBuilder

_CSV_COLUMNS = {
    "time": "time", "t": "time", "timestamp": "time", "seconds": "time",
    "lat": "lat", "latitude": "lat",
    "lon": "lon", "lng": "lon", "long": "lon", "longitude": "lon",
    "alt": "alt", "altitude": "alt", "abs_alt": "alt", "ele": "alt",
    "height": "height", "rel_alt": "height",
    "yaw": "yaw", "heading": "yaw", "gb_yaw": "yaw",
    "pitch": "pitch", "gb_pitch": "pitch",
    "roll": "roll", "gb_roll": "roll",
    "hfov": "hfov",
}


def _time_value(text: str) -> tuple[float, bool]:
    """(seconds, is a clock time) of a CSV time cell."""
    try:
        return float(text), False
    except ValueError:
        pass
    try:
        stamp = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(f"time {text!r} is neither seconds nor an ISO 8601 date-time") from None
    return stamp.timestamp(), True


def read_csv(path: str | Path) -> FlightLog:
    p = Path(path)
    try:
        handle = p.open(newline="", encoding="utf-8-sig", errors="replace")
    except OSError as exc:
        raise BadInput(f"{p}: cannot read ({exc.strerror})") from None
    with handle:
        reader = csv.reader(handle)
        header = next(reader, None)
        if not header:
            raise BadInput(f"{p}: empty CSV file")
        columns = {i: _CSV_COLUMNS.get(name.strip().lower()) for i, name in enumerate(header)}
        found = set(columns.values())
        missing = [c for c in ("time", "lat", "lon") if c not in found]
        if missing:
            raise BadInput(f"{p}: the CSV header must name time, lat and lon columns (missing: {', '.join(missing)}; header: {','.join(header)})")
        builder = FlightLogBuilder()
        clock = None
        for line, row in enumerate(reader, start=2):
            if not any(cell.strip() for cell in row):
                continue
            values: dict[str, float] = {}
            time = None
            try:
                for i, cell in enumerate(row):
                    key = columns.get(i)
                    if key is None or not cell.strip():
                        continue
                    if key == "time":
                        time, is_clock = _time_value(cell)
                        if clock is None:
                            clock = is_clock
                        elif clock != is_clock:
                            raise ValueError("mixes seconds and date-times")
                    else:
                        values[key] = float(cell)
            except ValueError as exc:
                raise BadInput(f"{p}, line {line}: {exc}") from None
            if time is None:
                raise BadInput(f"{p}, line {line}: no time")
            builder.add(time, **values)
    if not builder.rows:
        raise BadInput(f"{p}: no rows under the CSV header")
    track = builder.build(f"{p} (CSV)", clock_time=bool(clock))
    if clock:
        track.time = track.time - track.time[0]
    return track


def read_gpx(path: str | Path) -> FlightLog:
    require_geo("gpxpy")
    import gpxpy
    import gpxpy.gpx

    p = Path(path)
    try:
        with p.open(encoding="utf-8", errors="replace") as handle:
            gpx = gpxpy.parse(handle)
    except OSError as exc:
        raise BadInput(f"{p}: cannot read ({exc.strerror})") from None
    except gpxpy.gpx.GPXException as exc:
        raise BadInput(f"{p}: not a GPX file ({str(exc).splitlines()[0] if str(exc) else 'parse error'})") from None
    builder = FlightLogBuilder()
    untimed = 0
    points = [pt for track in gpx.tracks for seg in track.segments for pt in seg.points]
    points = points or [pt for route in gpx.routes for pt in route.points]
    for pt in points:
        if pt.time is None:
            untimed += 1
            continue
        yaw = pt.course if getattr(pt, "course", None) is not None else None
        fixed = (pt.type_of_gpx_fix or "").lower() != "none"
        builder.add(pt.time.timestamp(), lat=pt.latitude if fixed else None, lon=pt.longitude if fixed else None,
                    alt=pt.elevation if pt.elevation is not None and math.isfinite(pt.elevation) else None, yaw=yaw)
    if not builder.rows:
        what = f"{untimed} track points without times" if untimed else "no track points"
        raise BadInput(f"{p}: {what}: a GPX track needs timed points (<trkpt> with <time>)")
    track = builder.build(f"{p} (GPX)", clock_time=True)
    track.time = track.time - track.time[0]
    if untimed:
        track.notes.append(f"{untimed} GPX points without a time were skipped")
    return track
