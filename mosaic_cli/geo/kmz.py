"""A KMZ that Google Earth opens: the map as a Region-based super-overlay (a KML pyramid of
PNG/JPEG tiles, each level shown by its <Region>/<Lod> and reached through NetworkLinks, as
GDAL's KMLSUPEROVERLAY driver writes it: a large map stays light), with the flight track, the
GPS fixes dropped as outliers (points of their own, not in the track) and the keyframes'
footprints as KML layers (Placemarks in WGS84 lon/lat)."""

from __future__ import annotations

import contextlib
import zipfile
from pathlib import Path
from xml.etree import ElementTree as ET

from mosaic_cli.atomic import atomic_path, interruptible, signals_held, temporary_beside
from mosaic_cli.errors import ProcessingError, gdal_writing

KML_NS = "http://www.opengis.net/kml/2.2"


def _el(parent: ET.Element, tag: str, text: str | None = None, **attrs: str) -> ET.Element:
    el = ET.SubElement(parent, f"{{{KML_NS}}}{tag}", attrs)
    if text is not None:
        el.text = text
    return el


def _coordinates(points) -> str:
    return " ".join(f"{lon:.9f},{lat:.9f},0" for lon, lat in points)


def _style(doc: ET.Element, ident: str, colour: str, width: str, fill: str | None = None) -> None:
    """KML colours are aabbggrr."""
    style = _el(doc, "Style", id=ident)
    line = _el(style, "LineStyle")
    _el(line, "color", colour)
    _el(line, "width", width)
    poly = _el(style, "PolyStyle")
    _el(poly, "color", fill or "00000000")
    _el(poly, "fill", "1" if fill else "0")


def add_layers(doc_kml: bytes, features: dict, name: str) -> bytes:
    """GDAL's root doc.kml named ``name``, with folders added: the GPS track (a LineString), the
    fixes dropped as outliers (a Point each, when there are any) and the keyframes' footprints (a
    Polygon each, named by frame, with its time and centre)."""
    ET.register_namespace("", KML_NS)
    ET.register_namespace("gx", "http://www.google.com/kml/ext/2.2")
    root = ET.fromstring(doc_kml)
    doc = root.find(f"{{{KML_NS}}}Document")
    if doc is None:
        raise ProcessingError("GDAL's KML super-overlay has no Document")
    title = doc.find(f"{{{KML_NS}}}name")
    if title is not None:  # GDAL names it after the file it wrote (a temporary one)
        title.text = name
    _style(doc, "track", "ff0000ff", "3")  # red
    _style(doc, "footprint", "ff00ffff", "1.5", fill="2200ffff")  # yellow outline, faint fill
    _style(doc, "footprint-outlier", "ff0080ff", "1.5", fill="220080ff")  # orange: the fix disagreed
    track = [f for f in features["features"] if f["properties"].get("kind") == "gps track"]
    if track:
        folder = _el(doc, "Folder")
        _el(folder, "name", "Flight track")
        for part in track:  # one line a flight
            place = _el(folder, "Placemark")
            flight = f"flight {part['properties'].get('flight', 0) + 1}, " if len(track) > 1 else ""
            _el(place, "name", f"GPS track ({flight}{part['properties'].get('source', '')})")
            _el(place, "styleUrl", "#track")
            line = _el(place, "LineString")
            _el(line, "tessellate", "1")
            _el(line, "coordinates", _coordinates(part["geometry"]["coordinates"]))
    dropped = [f for f in features["features"] if f["properties"].get("kind") == "dropped gps fix"]
    if dropped:
        style = _el(doc, "Style", id="dropped")  # magenta dots
        icon = _el(style, "IconStyle")
        _el(icon, "color", "fff53dff")
        _el(icon, "scale", "0.6")
        _el(_el(icon, "Icon"), "href", "http://maps.google.com/mapfiles/kml/shapes/shaded_dot.png")
        folder = _el(doc, "Folder")
        _el(folder, "name", f"GPS fixes dropped as outliers ({len(dropped)})")
        for f in dropped:
            p = f["properties"]
            place = _el(folder, "Placemark")
            _el(place, "name", f"dropped fix {p['sample']}")
            _el(place, "description", f"time {p['time']:.2f} s in the log: an outlier, left out of the track and the placement")
            _el(place, "styleUrl", "#dropped")
            _el(_el(place, "Point"), "coordinates", _coordinates([f["geometry"]["coordinates"]]))
    prints = [f for f in features["features"] if f["properties"].get("kind") == "footprint"]
    if prints:
        folder = _el(doc, "Folder")
        _el(folder, "name", "Footprints")
        for f in prints:
            p = f["properties"]
            place = _el(folder, "Placemark")
            _el(place, "name", f"frame {p['frame']}")
            lon, lat = p.get("centre", f["geometry"]["coordinates"][0][0])
            _el(place, "description", f"time {p['time']:.2f} s, centre {lat:.7f} N, {lon:.7f} E, GPS fix: {p['gps']}")
            _el(place, "styleUrl", "#footprint" if p["gps"] != "outlier" else "#footprint-outlier")
            polygon = _el(place, "Polygon")
            ring = _el(_el(polygon, "outerBoundaryIs"), "LinearRing")
            _el(ring, "coordinates", _coordinates(f["geometry"]["coordinates"][0]))
    return ET.tostring(root, encoding="utf-8", xml_declaration=True)


def write_kmz(out: str | Path, geotiff: str | Path, features: dict) -> None:
    """``geotiff`` as a tiled KMZ super-overlay (GDAL, tiles PNG where transparent else JPEG)
    with ``features`` (the footprints GeoJSON's) as layers; written atomically."""
    from rasterio.shutil import copy

    out = Path(out)
    staging = None
    try:
        with signals_held():
            staging = temporary_beside(out, ".staging.kmz")
        staging.unlink()  # GDAL makes the archive
        with gdal_writing(out, "the KML super-overlay"):
            interruptible(lambda: copy(str(geotiff), str(staging), driver="KMLSUPEROVERLAY", FORMAT="AUTO"))
        with atomic_path(out) as tmp, zipfile.ZipFile(staging) as src, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as dst:
            # doc.kml first: Google Earth opens the first .kml of the archive
            dst.writestr("doc.kml", add_layers(src.read("doc.kml"), features, out.stem))
            for info in src.infolist():
                if info.filename != "doc.kml" and not info.is_dir():
                    dst.writestr(info.filename, src.read(info), compress_type=zipfile.ZIP_STORED if info.filename.endswith((".png", ".jpg")) else zipfile.ZIP_DEFLATED)
    finally:
        if staging is not None:
            with contextlib.suppress(FileNotFoundError):
                staging.unlink()
