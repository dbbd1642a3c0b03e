"""``mosaic evaluate``: see the module docstring once implemented."""
