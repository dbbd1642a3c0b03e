"""``mosaic stabilize``: see the module docstring once implemented."""
