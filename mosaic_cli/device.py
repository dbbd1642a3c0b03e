"""``--device``: the torch device a learned estimator or a training run computes on, one rule for
every command.

``auto`` is the GPU when torch sees one, else the CPU; ``cpu``; ``cuda`` (the GPU); ``cuda:N``
(the N-th GPU).  Any case.  :func:`check_device` checks the spelling without importing torch, so
that options can validate themselves before any work; :func:`resolve_device` also checks that
the GPU asked for is there.  Both refuse with one ``BadInput`` line naming ``--device``.
"""

from __future__ import annotations

import os
import re
from typing import TYPE_CHECKING

from mosaic_cli.errors import BadInput

if TYPE_CHECKING:
    import torch

SPELLINGS = "auto, cpu, cuda or cuda:N"
_SPELLING = re.compile(r"auto|cpu|cuda(:\d+)?")


def check_device(device: str | None) -> str:
    """``device`` (None: ``auto``) in lower case, or ``BadInput`` when it is none of :data:`SPELLINGS`."""
    name = (device or "auto").lower()
    if not _SPELLING.fullmatch(name):
        raise BadInput(f"--device must be {SPELLINGS}, got {device!r}")
    return name


def resolve_device(device: str | None, gpu: int | None = None) -> torch.device:
    """The torch device ``--device`` names.  ``gpu`` is the GPU that ``cuda`` (and ``auto`` on
    a machine with one) means: torchrun's LOCAL_RANK in training, so that each process takes its
    own; None: torch's current GPU.  ``BadInput`` when the GPU is not there."""
    import torch

    name = check_device(device)
    if name == "cpu" or (name == "auto" and not torch.cuda.is_available()):
        return torch.device("cpu")
    index = int(name.partition(":")[2]) if ":" in name else gpu
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if count == 0:
        raise BadInput(f"--device {name}: no CUDA GPU is available (use --device cpu or auto)")
    if index is not None and index >= count:
        raise BadInput(f"--device {name}: no GPU cuda:{index} here, the GPUs are cuda:0..cuda:{count - 1} (use --device cpu or auto)")
    return torch.device("cuda") if index is None else torch.device("cuda", index)


# --- CPU threads of the network and of the per-pair pool -----------------------------------------
# The network: one unless --threads says otherwise: its batches are small, and its intra-op threads
# wait on each other whenever another process holds a core (the encoder beside stabilize's
# tracking pass, anything else on a shared machine).  Under load two threads took twice the CPU
# of one for the same stitch, and a second longer to start (CHANGELOG.md, speed, 2026-11-27).
# The per-pair work of a learned estimator (polish, correlation check, fallback: OpenCV, which
# lets go of the GIL) runs on a pool of Python threads, as many as --threads says, else one a core
# (:func:`pair_threads`); its results do not depend on how many.
DEFAULT_CPU_THREADS = 1
_cpu_threads: dict[str, int | None] = {"asked": None}


def ask_cpu_threads(threads: int | None) -> None:
    """``--threads``: the CPU threads a learned estimator will run on: the network's (None:
    :data:`DEFAULT_CPU_THREADS`) and its per-pair pool's (None: every core, :func:`pair_threads`);
    the network's applied now if torch is loaded, else when the estimator is made (:func:`use_cpu_threads`)."""
    _cpu_threads["asked"] = threads
    import sys

    if "torch" in sys.modules:
        use_cpu_threads()


def use_cpu_threads() -> None:
    """Set torch's intra-op threads to what was asked (:func:`ask_cpu_threads`), or one."""
    import torch

    asked = _cpu_threads["asked"]
    torch.set_num_threads(asked if asked is not None else DEFAULT_CPU_THREADS)


def pair_threads() -> int:
    """The threads of a learned estimator's per-pair pool: what ``--threads`` asked
    (:func:`ask_cpu_threads`), else the machine's cores (``os.cpu_count()``).  One: no pool, each
    pair finished on the calling thread."""
    asked = _cpu_threads["asked"]
    return asked if asked is not None else max(1, os.cpu_count() or 1)
