from mosaic_cli.cli import main

main()
