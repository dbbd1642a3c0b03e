"""``mosaic stitch``: see the module docstring once implemented."""
