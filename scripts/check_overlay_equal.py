#!/usr/bin/env python3
"""The overlay detector's mask against another revision's, on the same clips: equal to the
pixel, with the detector's time and the peak of the memory its arrays take (docs/measurements/stitch.md,
"Burned-in overlays").

    python scripts/check_overlay_equal.py --rev dca4fcd a.mp4 b.mp4 photos/ --seek --unknown-length

For each clip (a video or a folder of photos), ``frame_mask`` as every command runs it, with
the current code and with ``mosaic_cli/overlay.py`` as it was at ``--rev`` (loaded from git
beside it; the rest of mosaic_cli is the current one).  ``--seek`` also samples each video as a
long clip (by seeking), ``--unknown-length`` as one whose container gives no frame count.
Time: wall and CPU (ffmpeg's included) of one run each, the reference first; memory: the
peak of Python's allocations during the run (tracemalloc: numpy's arrays, not ffmpeg's).
Exits 1 when any mask differs.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import mosaic_cli.overlay as current  # noqa: E402
from mosaic_cli.video import probe  # noqa: E402


def module_at(rev: str):
    """mosaic_cli/overlay.py as it was at ``rev``, as a module of its own."""
    source = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:mosaic_cli/overlay.py"], check=True,
                            capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp(prefix="overlay-ref-")) / "overlay_ref.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("overlay_ref", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # (dataclasses look their module up there)
    spec.loader.exec_module(module)
    return module


def cpu_seconds() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def run(module, clip: Path, info, seek: bool):
    """(FrameMask, wall s, CPU s, peak MiB of Python's allocations)."""
    holder = getattr(module, "samples", module)  # the package's sampling lives in mosaic_cli/overlay/samples.py
    saved = holder.DECODE_ALL_BELOW
    holder.DECODE_ALL_BELOW = 10 if seek else saved
    try:
        clock, used = time.perf_counter(), cpu_seconds()
        mask = module.frame_mask(clip, module.MaskOptions(), info)
        wall, cpu = time.perf_counter() - clock, cpu_seconds() - used
        tracemalloc.start()
        module.frame_mask(clip, module.MaskOptions(), info)
        peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    finally:
        holder.DECODE_ALL_BELOW = saved
    return mask, wall, cpu, peak


def same(a, b) -> bool:
    if (a.use is None) != (b.use is None) or (a.use is not None and not np.array_equal(a.use, b.use)):
        return False
    da, db = a.detection, b.detection
    return (dataclasses.astuple(da.letterbox) == dataclasses.astuple(db.letterbox) and da.static_fraction == db.static_fraction
            and da.rejected == db.rejected and da.samples == db.samples and da.too_few == db.too_few)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("clips", type=Path, nargs="+")
    parser.add_argument("--rev", required=True, help="the reference revision of mosaic_cli/overlay.py (a revision before it became the package mosaic_cli/overlay/)")
    parser.add_argument("--seek", action="store_true", help="also sample each video by seeking, as a long clip")
    parser.add_argument("--unknown-length", action="store_true", help="also sample each video as if its length were unknown")
    args = parser.parse_args()
    reference = module_at(args.rev)
    differ = 0
    print(f"{'clip':28s} {'sampling':9s} {'masked %':>8s}  equal  {'wall s ref/now':>15s}  {'CPU s ref/now':>15s}  {'peak MiB ref/now':>17s}")
    for clip in args.clips:
        info = probe(clip)
        modes = [("as is", info, False)]
        if not info.is_image_folder:
            if args.seek:
                modes.append(("seeking", info, True))
            if args.unknown_length:
                modes.append(("unknown", dataclasses.replace(info, frame_count=None), False))
        for name, clip_info, seek in modes:
            ref, ref_wall, ref_cpu, ref_peak = run(reference, clip, clip_info, seek)
            now, wall, cpu, peak = run(current, clip, clip_info, seek)
            equal = same(ref, now)
            differ += not equal
            print(f"{clip.name:28s} {name:9s} {100 * now.excluded:8.2f}  {'yes' if equal else 'NO':5s}  {ref_wall:7.2f}/{wall:<7.2f}  "
                  f"{ref_cpu:7.2f}/{cpu:<7.2f}  {ref_peak:8.1f}/{peak:<8.1f}", flush=True)
    print(f"reproduce: python scripts/check_overlay_equal.py --rev {args.rev} {' '.join(map(str, args.clips))}"
          + (" --seek" if args.seek else "") + (" --unknown-length" if args.unknown_length else ""))
    sys.exit(1 if differ else 0)


if __name__ == "__main__":
    main()
