"""``mosaic bench``: see the module docstring once implemented."""
