"""One module per command: a plain function whose parameters declare its flags, registered by
:mod:`mosaic_cli.cli`.  A command parses its flags into the library's options, calls one
pipeline and prints; it imports neither ``mosaic_cli.cli`` nor another command (the flags they
share are in :mod:`.options`)."""
