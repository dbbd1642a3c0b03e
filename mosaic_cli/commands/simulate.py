"""``mosaic simulate``: see the module docstring once implemented."""
