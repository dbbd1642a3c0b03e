from mosaic_cli.cli import entry

entry()
