"""Coordinate reference systems: the UTM zone of a site, and WGS84 <-> map metres."""

from __future__ import annotations

import numpy as np

from mosaic_cli.errors import require_geo


def utm_zone(lat: float, lon: float) -> int:
    """The UTM zone (1-60) holding (lat, lon): the 6-degree band, with the grid's two exceptions
    (as MGRS draws them): southwest Norway (56-64 N, 3-12 E) is in zone 32, widened west over
    zone 31; Svalbard (72-84 N, 0-42 E) has only the odd zones, 9 and 12 degrees wide (31: 0-9,
    33: 9-21, 35: 21-33, 37: 33-42).  pyproj's ``query_utm_crs_info`` knows neither: it matches
    the zones' EPSG areas of use, the plain bands (it puts Bergen in zone 31)."""
    lat, lon = float(lat), float(lon)
    zone = int(np.floor((lon + 180.0) / 6.0)) % 60 + 1
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        return 32
    if 72.0 <= lat < 84.0 and 0.0 <= lon < 42.0:
        return 31 if lon < 9.0 else 33 if lon < 21.0 else 35 if lon < 33.0 else 37
    return zone


def utm_epsg(lat: float, lon: float) -> int:
    """EPSG code of the WGS84 / UTM zone holding (lat, lon) (:func:`utm_zone`)."""
    return (32600 if lat >= 0 else 32700) + utm_zone(lat, lon)


class Projection:
    """WGS84 longitude/latitude <-> a projected CRS (east, north in metres)."""

    def __init__(self, crs) -> None:
        require_geo("pyproj")
        from pyproj import CRS, Transformer

        self.crs = CRS.from_user_input(crs)
        self._forward = Transformer.from_crs("EPSG:4326", self.crs, always_xy=True)
        self._inverse = Transformer.from_crs(self.crs, "EPSG:4326", always_xy=True)

    @classmethod
    def utm_for(cls, lat: float, lon: float) -> Projection:
        return cls(f"EPSG:{utm_epsg(lat, lon)}")

    @property
    def name(self) -> str:
        epsg = self.crs.to_epsg()
        return f"EPSG:{epsg}" if epsg else self.crs.to_string()

    def to_map(self, lat, lon) -> np.ndarray:
        """(N, 2) east, north metres."""
        e, n = self._forward.transform(np.asarray(lon, float), np.asarray(lat, float))
        return np.stack([np.atleast_1d(e), np.atleast_1d(n)], -1)

    def to_wgs84(self, east, north) -> np.ndarray:
        """(N, 2) longitude, latitude degrees."""
        lon, lat = self._inverse.transform(np.asarray(east, float), np.asarray(north, float))
        return np.stack([np.atleast_1d(lon), np.atleast_1d(lat)], -1)
