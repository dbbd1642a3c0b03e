"""``--html``: one self-contained quick-look page of a map, that works offline.

The page holds everything it shows: Leaflet (vendored in geo/vendor/leaflet with its
licence, inlined), the map warped to Web Mercator and downsampled (a WebP data URI placed by
its bounds: Leaflet draws in Web Mercator, so a north-up image between two latitudes and two
longitudes lands exactly), the GPS track, the fixes georeferencing dropped as outliers (points
of their own colour, never joined into the track), the keyframes' footprints and centres (click
one for its frame, time and position), a legend in the layers control, a metric scale bar and a
north arrow.  An OpenStreetMap layer
is offered, off by default: with it off the page asks nothing of the network."""

from __future__ import annotations

import base64
import html
import json
from importlib import resources
from pathlib import Path

import numpy as np

from mosaic_cli.atomic import atomic_path
from mosaic_cli.errors import ProcessingError

MAX_SIDE = 2048  # the embedded image's longest side, pixels
WEBP_QUALITY = 85


def map_image(geotiff: str | Path, max_side: int = MAX_SIDE) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The map warped to Web Mercator (GDAL, averaged), at most ``max_side`` pixels long:
    (RGBA H x W x 4, (west, south, east, north) in degrees of its outer edges)."""
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.transform import Affine
    from rasterio.vrt import WarpedVRT
    from rasterio.warp import calculate_default_transform, transform_bounds

    with rasterio.open(geotiff) as src:
        transform, width, height = calculate_default_transform(src.crs, "EPSG:3857", src.width, src.height, *src.bounds)
        scale = max(1.0, max(width, height) / max_side)
        w, h = max(1, round(width / scale)), max(1, round(height / scale))
        res_x, res_y = transform.a * width / w, transform.e * height / h
        fitted = Affine(res_x, 0, transform.c, 0, res_y, transform.f)
        with WarpedVRT(src, crs="EPSG:3857", transform=fitted, width=w, height=h, resampling=Resampling.average) as vrt:
            bands = vrt.read()
    if bands.shape[0] == 3:
        bands = np.concatenate([bands, np.full_like(bands[:1], 255)])
    left, top = fitted.c, fitted.f
    right, bottom = left + res_x * w, top + res_y * h
    west, south, east, north = transform_bounds("EPSG:3857", "EPSG:4326", left, bottom, right, top)
    return np.ascontiguousarray(bands[:4].transpose(1, 2, 0)), (west, south, east, north)


def data_uri(rgba: np.ndarray) -> str:
    import cv2

    ok, data = cv2.imencode(".webp", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA), [cv2.IMWRITE_WEBP_QUALITY, WEBP_QUALITY])
    if not ok:
        raise ProcessingError("OpenCV could not encode the quick-look image (WebP)")
    return "data:image/webp;base64," + base64.b64encode(data.tobytes()).decode("ascii")


def _vendored(name: str) -> str:
    return resources.files("mosaic_cli.geo").joinpath("vendor", "leaflet", name).read_text(encoding="utf-8")


def _script_safe(text: str) -> str:
    """Text inside <script>/<style>: no early end tag."""
    return text.replace("</", "<\\/")


def page(geotiff: str | Path, features: dict, title: str) -> str:
    rgba, (west, south, east, north) = map_image(geotiff)
    data = {"image": data_uri(rgba), "bounds": [[south, west], [north, east]], "features": features, "title": title}
    return TEMPLATE.format(
        title=html.escape(title),
        leaflet_css=_vendored("leaflet.css").replace("</", "<\\/"),
        leaflet_js=_script_safe(_vendored("leaflet.js")),
        licence=html.escape(_vendored("LICENSE")).replace("--", "- -"),
        data=_script_safe(json.dumps(data)),
        script=SCRIPT,
    )


def write_quicklook(out: str | Path, geotiff: str | Path, features: dict, title: str = "map") -> None:
    """The quick-look page of ``geotiff`` with ``features`` (the footprints GeoJSON's), atomically."""
    text = page(geotiff, features, title)
    with atomic_path(out) as tmp:
        tmp.write_text(text, encoding="utf-8")


SCRIPT = r"""
(function () {
  var errors = [];
  window.addEventListener("error", function (e) { errors.push(String(e.message)); document.body.setAttribute("data-errors", errors.join(" | ")); });
  var data = JSON.parse(document.getElementById("mosaic-data").textContent);
  var map = L.map("map", {zoomSnap: 0.25, maxZoom: 24});
  var none = L.layerGroup();  // no basemap: the page works offline
  var osm = L.tileLayer("https://tile.openstreetmap.org/{z}/{x}/{y}.png", {
    maxNativeZoom: 19, maxZoom: 24, attribution: '&copy; <a href="https://www.openstreetmap.org/copyright">OpenStreetMap</a> contributors'});
  none.addTo(map);
  var image = L.imageOverlay(data.image, data.bounds, {alt: "map"}).addTo(map);
  function fmt(v, n) { return Number(v).toFixed(n); }
  function framePopup(p, lonlat) {
    return "<b>frame " + p.frame + "</b><br>time " + fmt(p.time, 2) + " s<br>" +
      fmt(lonlat[1], 7) + " N, " + fmt(lonlat[0], 7) + " E<br>GPS fix: " + p.gps;
  }
  var feats = data.features.features;
  function kind(k) { return feats.filter(function (f) { return f.properties.kind === k; }); }
  var colour = {footprint: "#ffd400", outlier: "#ff8000", track: "#e8112d", dropped: "#ff3df5", droppedEdge: "#5b0a66", centre: "#1f6fe5"};
  var prints = L.geoJSON({type: "FeatureCollection", features: kind("footprint")}, {
    style: function (f) { return {color: f.properties.gps === "outlier" ? colour.outlier : colour.footprint, weight: 1.5, fillOpacity: 0.04}; },
    onEachFeature: function (f, layer) { layer.bindPopup(framePopup(f.properties, f.properties.centre || f.geometry.coordinates[0][0])); }
  }).addTo(map);
  var track = L.geoJSON({type: "FeatureCollection", features: kind("gps track")}, {
    style: function () { return {color: colour.track, weight: 3}; }
  }).addTo(map);
  // the fixes georeferencing dropped as outliers: points apart, never a vertex of the track's line
  var droppedFixes = kind("dropped gps fix");
  var dropped = L.layerGroup(droppedFixes.map(function (f) {
    var c = f.geometry.coordinates, p = f.properties;
    return L.circleMarker([c[1], c[0]], {radius: 5, color: colour.droppedEdge, weight: 2, fillColor: colour.dropped, fillOpacity: 1})
      .bindPopup("<b>GPS fix dropped as an outlier</b><br>sample " + p.sample + ", time " + fmt(p.time, 2) + " s in the log<br>" +
        fmt(c[1], 7) + " N, " + fmt(c[0], 7) + " E");
  })).addTo(map);
  var centres = L.layerGroup(kind("footprint").filter(function (f) { return f.properties.centre; }).map(function (f) {
    var c = f.properties.centre;
    return L.circleMarker([c[1], c[0]], {radius: 5, color: "#fff", weight: 1.5, fillColor: colour.centre, fillOpacity: 1})
      .bindPopup(framePopup(f.properties, c));
  })).addTo(map);
  // the layers control is the legend: each entry with its colour
  function swatch(fill, edge, round) {
    return '<span class="swatch' + (round ? " round" : "") + '" style="background:' + fill + ';border-color:' + (edge || fill) + '"></span>';
  }
  var overlays = {"Map": image};
  var outliers = kind("footprint").some(function (f) { return f.properties.gps === "outlier"; });
  overlays[swatch(colour.footprint) + "Footprints" + (outliers ? " (" + swatch(colour.outlier) + "fix disagreed)" : "")] = prints;
  overlays[swatch(colour.track) + "GPS track"] = track;
  if (droppedFixes.length) {
    overlays[swatch(colour.dropped, colour.droppedEdge, true) + "GPS fixes dropped as outliers (" + droppedFixes.length + ")"] = dropped;
  }
  overlays[swatch(colour.centre, "#fff", true) + "Frame centres"] = centres;
  L.control.layers({"No basemap (offline)": none, "OpenStreetMap (online)": osm}, overlays, {collapsed: false}).addTo(map);
  L.control.scale({imperial: false, maxWidth: 200}).addTo(map);
  var North = L.Control.extend({options: {position: "topright"}, onAdd: function () {
    var div = L.DomUtil.create("div", "north-arrow");
    div.title = "north";
    div.innerHTML = '<svg width="34" height="46" viewBox="0 0 34 46"><polygon points="17,3 28,34 17,27 6,34" fill="#222" stroke="#fff" stroke-width="1.5"/>' +
      '<text x="17" y="45" text-anchor="middle" font-family="sans-serif" font-size="12" font-weight="bold" fill="#222">N</text></svg>';
    return div;
  }});
  new North().addTo(map);
  map.fitBounds(data.bounds, {padding: [12, 12]});
  map.on("click", function (e) {
    L.popup().setLatLng(e.latlng).setContent(fmt(e.latlng.lat, 7) + " N, " + fmt(e.latlng.lng, 7) + " E").openOn(map);
  });
  document.body.setAttribute("data-ready", "1");
})();
"""

TEMPLATE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<!-- Leaflet 1.9.4 (https://leafletjs.com), inlined; its licence:
{licence}
-->
<style>
{leaflet_css}
html, body {{ margin: 0; height: 100%; }}
#map {{ position: absolute; inset: 0; background: #dddddd; }}
.swatch {{ display: inline-block; width: 14px; height: 6px; margin: 0 5px 1px 2px; border: 1px solid; vertical-align: middle; }}
.swatch.round {{ width: 8px; height: 8px; border-radius: 50%; border-width: 2px; margin: 0 7px 1px 4px; }}
.north-arrow {{ background: rgba(255, 255, 255, 0.8); border-radius: 4px; padding: 2px 3px 0; line-height: 0; }}
.title {{ position: absolute; left: 54px; top: 10px; z-index: 1000; background: rgba(255, 255, 255, 0.85); padding: 4px 8px;
         border-radius: 4px; font: 14px sans-serif; }}
</style>
</head>
<body>
<div id="map"></div>
<div class="title">{title}</div>
<script>
{leaflet_js}
</script>
<script type="application/json" id="mosaic-data">{data}</script>
<script>
{script}
</script>
</body>
</html>
"""
