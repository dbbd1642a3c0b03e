"""The stage seconds a mosaic command prints on its final line ("... (overlays 1.2 s, track 3.4 s)"),
read back by the benchmarks that run it (scripts/bench_speed.py, scripts/gpu_session.py)."""

from __future__ import annotations

import re

STAGE = re.compile(r"(overlays|track|path|render|scan|register|compose|write) ([0-9.]+) s")


def stage_seconds(stderr: str) -> dict[str, float]:
    """The stage seconds of a mosaic command's final line that names any (empty where none does)."""
    lines = [line for line in stderr.strip().splitlines() if STAGE.search(line)]
    return {name: float(value) for name, value in STAGE.findall(lines[-1])} if lines else {}
