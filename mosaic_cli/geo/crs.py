"""Coordinate reference systems: the UTM zone of a site, and WGS84 <-> map metres."""

from __future__ import annotations

import numpy as np


def utm_epsg(lat: float, lon: float) -> int:
    """EPSG code of the WGS84 / UTM zone holding (lat, lon)."""
    zone = int(np.floor((float(lon) + 180.0) / 6.0)) % 60 + 1
    return (32600 if lat >= 0 else 32700) + zone


class Projection:
    """WGS84 longitude/latitude <-> a projected CRS (east, north in metres)."""

    def __init__(self, crs) -> None:
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
