"""``mosaic train``: see the module docstring once implemented."""
