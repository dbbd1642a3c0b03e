"""mosaic's benchmarks, figure makers and developer tools, run as ``python -m benchmarks SUITE``
from the repository's root (``python -m benchmarks`` lists the suites).  Not part of the wheel:
mosaic_cli never imports this package (an import-linter contract in pyproject.toml)."""
