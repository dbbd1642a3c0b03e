"""Georeferencing: the site's projected CRS, the camera model telemetry is read with, the robust
fit of a mosaic to a GPS track, GPS drift correction, and the georeferenced outputs (COG,
footprints GeoJSON).  See docs/measurements/georef.md."""
