"""One module per command; each registers itself on :data:`mosaic_cli.cli.app`."""
