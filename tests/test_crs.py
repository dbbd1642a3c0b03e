"""The UTM zone of a site, with the grid's exceptions (southwest Norway, Svalbard), and the one
line a user sees when the packages of the ``geo`` extra are missing."""

from __future__ import annotations

import importlib.util

import pytest

from mosaic_cli.errors import GEO_EXTRA, BadInput, require_geo
from mosaic_cli.geo.crs import Projection, utm_epsg


@pytest.mark.parametrize(("site", "lat", "lon", "epsg"), [
    ("Bergen", 60.39, 5.32, 32632),  # southwest Norway: zone 32 reaches west to 3 E (the plain band says 31)
    ("Ny-Alesund", 78.92, 11.93, 32633),  # Svalbard: zone 33 spans 9-21 E (the plain band says 32)
    ("Longyearbyen", 78.22, 15.65, 32633),
    ("Svalbard, west of 9 E", 79.0, 8.99, 32631),
    ("Kvitoya", 80.1, 32.5, 32635),
    ("Oslo", 59.91, 10.75, 32632),
    ("Shetland, west of 3 E", 60.15, -1.15, 32630),
    ("North Sea, 2.99 E", 60.0, 2.99, 32631),
    ("Tromso", 69.65, 18.96, 32634),  # north of 64 N, south of 72 N: the plain bands
    ("Zurich", 47.3977, 8.5456, 32632),
    ("Cape Town", -33.92, 18.42, 32734),
    ("antimeridian", 10.0, 180.0, 32601),
])
def test_utm_zone_of_a_site(site, lat, lon, epsg):
    assert utm_epsg(lat, lon) == epsg, site


def test_a_projection_for_bergen_is_in_zone_32():
    pytest.importorskip("pyproj")
    projection = Projection.utm_for(60.39, 5.32)
    assert projection.name == "EPSG:32632"
    east, north = projection.to_map(60.39, 5.32)[0]
    assert 290_000 < east < 300_000 and 6_690_000 < north < 6_710_000  # zone 32's false easting, 3.7 degrees west of its meridian


def test_without_the_geo_extra_a_map_is_refused_in_one_line(monkeypatch, tmp_path):
    found = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "gpxpy" else found(name, *a))
    with pytest.raises(BadInput) as refused:
        require_geo()
    assert str(refused.value) == GEO_EXTRA == "maps need the geo extra: pip install 'mosaic-cli[geo]'"
    require_geo("pyproj")  # the others are there

    from mosaic_cli.telemetry.logs import read_gpx

    log = tmp_path / "flight.gpx"
    log.write_text("<gpx></gpx>")
    with pytest.raises(BadInput, match=r"geo extra"):
        read_gpx(log)
