"""``python -m benchmarks compare`` (benchmarks/compare_outputs.py): the comparison of two runs' JSON outputs (no commands run)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


def load_script():
    from benchmarks import compare_outputs

    return compare_outputs


def write_run(folder: Path, pairwise, frames, warps, canvas=(400, 300)) -> Path:
    folder.mkdir()
    (folder / "track.json").write_text(json.dumps({"pairwise": pairwise}))
    (folder / "stitch.json").write_text(json.dumps({"canvas_size": list(canvas), "frames": frames}))
    (folder / "warps.json").write_text(json.dumps({"warps": warps}))
    return folder


def test_outputs_compare_by_their_largest_difference_and_a_changed_frame_set_is_never_the_same(tmp_path):
    c = load_script()
    rng = np.random.default_rng(0)
    H = [np.eye(3) + 0.01 * rng.standard_normal((3, 3)) for _ in range(4)]
    pairwise = [h.tolist() for h in H]
    frames = [{"index": i, "H": h.tolist()} for i, h in zip((0, 5, 9), H)]
    mine = write_run(tmp_path / "mine", pairwise, frames, pairwise)
    # The same homographies scaled (the same projective maps), and one warp moved by 1e-6.
    moved = [h.copy() for h in H]
    moved[2][0, 2] += 1e-6 * moved[2][2, 2]
    scaled = [{"index": f["index"], "H": (3 * np.array(f["H"])).tolist()} for f in frames]
    theirs = write_run(tmp_path / "theirs", [(2 * h).tolist() for h in H], scaled, [h.tolist() for h in moved])
    rows = {command: diff for command, _, diff, _ in c.compare(mine, theirs)}
    assert rows["track"] < 1e-12 and rows["stitch"] < 1e-12
    assert abs(rows["stabilize"] - 1e-6) < 1e-12  # H[2, 2] = 1 in both: exactly the move
    other = write_run(tmp_path / "other", pairwise[:3], frames[:2], pairwise)
    rows = {command: diff for command, _, diff, _ in c.compare(mine, other)}
    assert rows["track"] == math.inf and rows["stitch"] == math.inf and rows["stabilize"] == 0.0
