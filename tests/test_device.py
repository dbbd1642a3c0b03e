"""``--device``: one rule (mosaic_cli/device.py) for the learned estimators and training, and one
line for a device that is misspelt or not on this machine, whichever command was given it."""

from __future__ import annotations

import pytest
import torch

from conftest import assert_one_line_error, run_cli
from mosaic_cli.device import check_device, resolve_device
from mosaic_cli.errors import BadInput
from mosaic_cli.train.distributed import Distributed

NO_GPU = "--device cuda: no CUDA GPU is available (use --device cpu or auto)"
MISSPELT = "--device must be auto, cpu, cuda or cuda:N, got 'tpu'"


@pytest.fixture
def no_gpu(monkeypatch):
    """A machine without CUDA, whatever this one has."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)


@pytest.fixture
def two_gpus(monkeypatch):
    """A machine with two GPUs, as far as the resolver asks (a torch.device is made without one)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)


@pytest.mark.parametrize("given, name", [(None, "auto"), ("AUTO", "auto"), ("cpu", "cpu"), ("Cuda", "cuda"), ("cuda:12", "cuda:12")])
def test_every_spelling_is_accepted_in_any_case(given, name):
    assert check_device(given) == name


@pytest.mark.parametrize("given", ["tpu", "gpu", "cuda:", "cuda:x", "cuda:-1", "cpu:0", "mps", " cpu"])
def test_other_spellings_are_refused_in_one_line(given):
    with pytest.raises(BadInput) as refused:
        check_device(given)
    assert str(refused.value) == f"--device must be auto, cpu, cuda or cuda:N, got {given!r}"


def test_without_cuda_auto_is_the_cpu_and_a_gpu_is_refused(no_gpu):
    assert resolve_device(None) == resolve_device("auto") == resolve_device("cpu") == torch.device("cpu")
    for name in ("cuda", "cuda:0", "cuda:1"):
        with pytest.raises(BadInput) as refused:
            resolve_device(name)
        assert str(refused.value) == f"--device {name}: no CUDA GPU is available (use --device cpu or auto)"
    with pytest.raises(BadInput, match="^--device must be"):
        resolve_device("tpu")


def test_with_gpus_auto_and_cuda_are_the_gpu_asked_for(two_gpus):
    assert resolve_device("auto") == resolve_device("cuda") == torch.device("cuda")
    assert resolve_device("auto", gpu=1) == resolve_device("cuda", gpu=1) == resolve_device("cuda:1") == torch.device("cuda", 1)
    assert resolve_device("cuda:0", gpu=1) == torch.device("cuda", 0)  # named: as named
    assert resolve_device("cpu", gpu=1) == torch.device("cpu")
    with pytest.raises(BadInput) as refused:
        resolve_device("cuda:2")
    assert str(refused.value) == "--device cuda:2: no GPU cuda:2 here, the GPUs are cuda:0..cuda:1 (use --device cpu or auto)"


def test_training_takes_the_gpu_of_its_local_rank(two_gpus, monkeypatch):
    monkeypatch.setenv("LOCAL_RANK", "1")  # one process of a torchrun on a bigger machine; WORLD_SIZE 1: no process group
    assert Distributed.start("auto").device == Distributed.start("cuda").device == torch.device("cuda", 1)
    assert Distributed.start("cpu").device == torch.device("cpu")


def test_training_without_cuda_is_refused_as_the_estimators_are(no_gpu):
    with pytest.raises(BadInput) as refused:
        Distributed.start("cuda")
    assert str(refused.value) == NO_GPU


def _command(command, clip, work):
    """The command with a learned estimator (a device matters only to the network) and all it needs."""
    return {
        "track": ["track", clip, "-o", work / "t.json", "-e", "lstm", "-q"],
        "stitch": ["stitch", clip, "-o", work / "p.png", "-e", "lstm", "-q"],
        "stabilize": ["stabilize", clip, work / "s.mp4", "-e", "lstm", "-q"],
        "bench": ["bench", "--video", clip, "-e", "lstm", "-q"],
        "train": ["train", clip.parent, "-o", work / "run", "--steps", "1", "-q"],
    }[command]


@pytest.mark.parametrize("command", ["track", "stitch", "stabilize", "bench", "train"])
@pytest.mark.parametrize("device, line", [("cuda", NO_GPU), ("tpu", MISSPELT)], ids=["no gpu", "misspelt"])
def test_every_command_says_the_same_line(capsys, no_gpu, tiny_clip, tmp_path, command, device, line):
    work = tmp_path / "work"
    work.mkdir()
    code, err = run_cli(capsys, *_command(command, tiny_clip, work), "--device", device)
    assert_one_line_error(code, err)
    assert err.strip() == f"mosaic: error: {line}"
    assert list(work.iterdir()) == []


def test_a_commands_network_runs_on_one_cpu_thread_unless_told(monkeypatch):
    """One torch thread by default (two wait on each other on a busy machine), --threads N
    when given, and a network made for training's validation leaves training's threads alone."""
    import torch

    import mosaic_cli.device as device
    from mosaic_cli.commands.options import use_threads
    from mosaic_cli.estimators import make_estimator
    from mosaic_cli.estimators.learned import LearnedEstimator

    before = torch.get_num_threads()
    monkeypatch.setitem(device._cpu_threads, "asked", None)
    try:
        torch.set_num_threads(2)
        make_estimator("lstm", device="cpu")
        assert torch.get_num_threads() == 1
        use_threads(2)  # --threads 2, after the estimator was made
        assert torch.get_num_threads() == 2
        make_estimator("cnn", device="cpu")
        assert torch.get_num_threads() == 2
        torch.set_num_threads(2)
        shipped = make_estimator("lstm", device="cpu")
        monkeypatch.setitem(device._cpu_threads, "asked", None)
        LearnedEstimator(shipped.model, shipped.meta, device="cpu")  # as train/validate.py makes it
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
