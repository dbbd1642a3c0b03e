"""Options validate themselves (docs/architecture.md, "Options").

Every options dataclass checks its values when it is made (``__post_init__`` calls
``validate()``): a value a user sets is refused with ``BadInput`` naming the flag, an internal
knob no flag sets with ``ValueError``; the defaults pass.  Each command therefore turns an
out-of-range flag into exactly one ``mosaic: error:`` line naming it, exit 2, before any work.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
from pathlib import Path

import pytest

import mosaic_cli
from conftest import assert_one_line_error, run_cli
from mosaic_cli.bench import BenchOptions
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators.learned import LearnedConfig
from mosaic_cli.estimators.orb import OrbConfig
from mosaic_cli.estimators.paper_orb import PaperOrbConfig
from mosaic_cli.estimators.refine import CornerConfig, PolishConfig
from mosaic_cli.evaluate import EvalOptions
from mosaic_cli.geo.drift import DriftOptions
from mosaic_cli.geo.georef import GeorefOptions
from mosaic_cli.model.network import NetConfig
from mosaic_cli.overlay import MaskOptions, OverlayOptions
from mosaic_cli.simulate import SimulateOptions
from mosaic_cli.simulate.telemetry import GpsErrors, TelemetryOptions
from mosaic_cli.stabilize import StabilizeOptions
from mosaic_cli.stitch import CanvasOptions, ComposeOptions, KeyframeOptions, RegistrationOptions, StitchOptions
from mosaic_cli.stitch.cluster import ClusterOptions
from mosaic_cli.stitch.features import FeatureOptions
from mosaic_cli.stitch.guide import GuideOptions
from mosaic_cli.stitch.live import PreviewOptions
from mosaic_cli.stitch.segments import JoinOptions
from mosaic_cli.telemetry.align import AlignOptions
from mosaic_cli.track import TrackOptions
from mosaic_cli.train.config import TrainConfig

# Every options dataclass, with what it needs to be made (its required fields).
OPTIONS = {
    AlignOptions: {},
    BenchOptions: {},
    CanvasOptions: {},
    ClusterOptions: {},
    GuideOptions: {},
    ComposeOptions: {},
    CornerConfig: {},
    DriftOptions: {},
    EvalOptions: {"gt": Path("flight.gt.json")},
    FeatureOptions: {},
    GeorefOptions: {},
    GpsErrors: {},
    JoinOptions: {},
    KeyframeOptions: {},
    LearnedConfig: {},
    MaskOptions: {},
    NetConfig: {},
    OrbConfig: {},
    OverlayOptions: {},
    PaperOrbConfig: {},
    PolishConfig: {},
    PreviewOptions: {},
    RegistrationOptions: {},
    SimulateOptions: {},
    StabilizeOptions: {},
    StitchOptions: {},
    TelemetryOptions: {},
    TrackOptions: {},
    TrainConfig: {"clips": "clips", "out": "run"},
}

# (class, values, the error, a fragment of its message: the flag a user set, or the field).
BAD = [
    (KeyframeOptions, {"new_ground": 0.99}, BadInput, "--overlap"),
    (RegistrationOptions, {"max_loop_pairs": -1}, BadInput, "--max-loop-pairs"),
    (CanvasOptions, {"reference": "left"}, BadInput, "--reference"),
    (CanvasOptions, {"reference": "-2"}, BadInput, "--reference"),
    (CanvasOptions, {"max_size": 10}, BadInput, "--max-size"),
    (CanvasOptions, {"gsd": -0.05}, BadInput, "--gsd"),
    (ClusterOptions, {"workers": 0}, BadInput, "--workers"),
    (ClusterOptions, {"scheduler": "localhost"}, BadInput, "--scheduler"),
    (ComposeOptions, {"blend": "average"}, BadInput, "--blend"),
    (ComposeOptions, {"seam": "x"}, BadInput, "--seam"),
    (ComposeOptions, {"exposure": "x"}, BadInput, "--exposure"),
    (StitchOptions, {"start": -1}, BadInput, "--start"),
    (StitchOptions, {"max_frames": 1}, BadInput, "--max-frames"),
    (StitchOptions, {"timeout": 0.0}, BadInput, "--timeout"),
    (PreviewOptions, {"path": Path("preview.gif")}, BadInput, "--preview"),
    (PreviewOptions, {"every": 0.0}, BadInput, "--every"),
    (StabilizeOptions, {"radius": 0}, BadInput, "--radius"),
    (StabilizeOptions, {"smoothing": "kalman"}, BadInput, "--smoothing"),
    (StabilizeOptions, {"model": "rigid"}, BadInput, "--model"),
    (StabilizeOptions, {"crop": "0.2"}, BadInput, "--crop"),
    (StabilizeOptions, {"border": "white"}, BadInput, "--border"),
    (StabilizeOptions, {"crf": 52}, BadInput, "--crf"),
    (StabilizeOptions, {"preset": "fastest"}, BadInput, "--preset"),
    (StabilizeOptions, {"work_width": 16}, BadInput, "--work-width"),
    (StabilizeOptions, {"work_width": 100_000}, BadInput, "--work-width"),
    (StabilizeOptions, {"device": "tpu"}, BadInput, "--device"),
    (StabilizeOptions, {"latency": 0.0}, BadInput, "--latency"),
    (StabilizeOptions, {"timeout": -1.0}, BadInput, "--timeout"),
    (TrackOptions, {"max_frames": 1}, BadInput, "--max-frames"),
    (TrackOptions, {"threads": 0}, BadInput, "--threads"),
    (TrackOptions, {"timeout": 0.0}, BadInput, "--timeout"),
    (MaskOptions, {"file": Path("/nonexistent/mask.png")}, BadInput, "--mask"),
    (MaskOptions, {"file": Path("/")}, BadInput, "--mask"),
    (MaskOptions, {"file_margin": -1}, BadInput, "--mask"),
    (LearnedConfig, {"patches": 4}, BadInput, "patches"),
    (LearnedConfig, {"chunk": 0}, BadInput, "chunk"),
    (LearnedConfig, {"reset_every": 0}, BadInput, "reset-every"),
    (LearnedConfig, {"refine": "sift"}, BadInput, "refine"),
    (LearnedConfig, {"precision": "fp8"}, BadInput, "precision"),
    (LearnedConfig, {"polish_start": "zero"}, BadInput, "polish-start"),
    (LearnedConfig, {"prior": "gps"}, BadInput, "prior"),
    (LearnedConfig, {"fallback": "sift"}, BadInput, "fallback"),
    (OrbConfig, {"refine": "sift"}, BadInput, "refine"),
    (EvalOptions, {"gt": None}, BadInput, "--gt"),
    (EvalOptions, {"every": 0}, BadInput, "--every"),
    (SimulateOptions, {"profile": "wobbly"}, BadInput, "--profile"),
    (SimulateOptions, {"frames": 1}, BadInput, "--frames"),
    (SimulateOptions, {"fps": 0.0}, BadInput, "--fps"),
    (SimulateOptions, {"seed": -1}, BadInput, "--seed"),
    (SimulateOptions, {"crf": 52}, BadInput, "--crf"),
    (SimulateOptions, {"preset": "fastest"}, BadInput, "--preset"),
    (TelemetryOptions, {"format": "kml"}, BadInput, "--telemetry"),
    (TelemetryOptions, {"rate": -1.0}, BadInput, "--telemetry-rate"),
    (TelemetryOptions, {"origin": "north"}, BadInput, "--origin"),
    (TelemetryOptions, {"origin": "95,0"}, BadInput, "--origin"),
    (TelemetryOptions, {"gsd": 0.0}, BadInput, "--gsd"),
    (GpsErrors, {"rms": -1.0}, BadInput, "--gps-noise"),
    (GpsErrors, {"dropouts": 1.0}, BadInput, "--gps-dropouts"),
    (GpsErrors, {"height_bias": -0.5}, BadInput, "--baro-bias"),
    (BenchOptions, {"estimators": [" "]}, BadInput, "--estimators"),
    (BenchOptions, {"estimators": ["orb", "orb"]}, BadInput, "--estimators"),
    (BenchOptions, {"flights": Path("f"), "video": Path("v.mp4")}, BadInput, "--flights"),
    (BenchOptions, {"video": Path("v.mp4"), "map_image": Path("m.png")}, BadInput, "--video"),
    (BenchOptions, {"work_width": 8}, BadInput, "--work-width"),
    (BenchOptions, {"device": "tpu"}, BadInput, "--device"),
    (BenchOptions, {"threads": 0}, BadInput, "--threads"),
    (TrainConfig, {"variant": "huge"}, BadInput, "--variant"),
    (TrainConfig, {"preset": "huge"}, BadInput, "--preset"),
    (TrainConfig, {"device": "tpu"}, BadInput, "--device"),
    (TrainConfig, {"steps": 0}, BadInput, "--steps"),
    (TrainConfig, {"batch_size": 0}, BadInput, "--batch-size"),
    (TrainConfig, {"lr": 0.0}, BadInput, "--lr"),
    (TrainConfig, {"seed": -1}, BadInput, "--seed"),
    (TrainConfig, {"threads": 0}, BadInput, "--threads"),
    (TrainConfig, {"patch": 8}, BadInput, "--patch"),
    (TrainConfig, {"work_size": (100, 60)}, BadInput, "--work-size"),
    (TrainConfig, {"num_workers": -1}, BadInput, "--num-workers"),
    (TrainConfig, {"checkpoint_every": 0}, BadInput, "--checkpoint-every"),
    (TrainConfig, {"checkpoint_minutes": 0.0}, BadInput, "--checkpoint-minutes"),
    (TrainConfig, {"val_every": 0}, BadInput, "--val-every"),
    (TrainConfig, {"cache_gb": 0.0}, BadInput, "--cache-gb"),
    (GeorefOptions, {"hfov": 200.0}, BadInput, "--hfov"),
    (GeorefOptions, {"offset": float("nan")}, BadInput, "--telemetry-offset"),
    (GeorefOptions, {"footprints": Path("footprints.txt")}, BadInput, "--footprints"),
    (GeorefOptions, {"height_accuracy": -1.0}, BadInput, "accuracies"),
    (GeorefOptions, {"fov_accuracy": 2.0}, BadInput, "accuracies"),
    (GeorefOptions, {"compass_accuracy": 0.0}, BadInput, "accuracies"),
    # Knobs no flag sets: a bad value is a bug.
    (OrbConfig, {"method": "lmeds"}, ValueError, "method"),
    (OverlayOptions, {"samples": 2}, ValueError, "sample frames"),
    (OverlayOptions, {"width": 8}, ValueError, "width"),
    (FeatureOptions, {"ratio": 1.5}, ValueError, "ratio"),
    (JoinOptions, {"picks": 0}, ValueError, "picks"),
    (GuideOptions, {"gps_error": 0.0}, ValueError, "guide options"),
    (GuideOptions, {"max_tilt": 95.0}, ValueError, "guide options"),
    (DriftOptions, {"correlation": 0.0}, ValueError, "positive"),
    (AlignOptions, {"max_gap": 0.0}, ValueError, "positive"),
    (PaperOrbConfig, {"wta_k": 5}, ValueError, "wta_k"),
    (PolishConfig, {"window": 1}, ValueError, "window"),
    (CornerConfig, {"quality": 0.0}, ValueError, "quality"),
    (NetConfig, {"head": "gru"}, ValueError, "head"),
]


def options_dataclasses() -> set[tuple[str, str]]:
    """(module, class) of every dataclass under mosaic_cli named ...Options or ...Config."""
    root = Path(mosaic_cli.__file__).parent
    found = set()
    for path in root.rglob("*.py"):
        module = ".".join(("mosaic_cli", *path.relative_to(root).with_suffix("").parts))
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and node.name.endswith(("Options", "Config")):
                decorators = [d.func if isinstance(d, ast.Call) else d for d in node.decorator_list]
                if any(getattr(d, "id", getattr(d, "attr", None)) == "dataclass" for d in decorators):
                    found.add((module.removesuffix(".__init__"), node.name))
    return found


def test_every_options_dataclass_is_checked_here():
    """A new options dataclass is listed above, and so gets the tests below."""
    listed = {(cls.__module__, cls.__name__) for cls in OPTIONS}
    assert options_dataclasses() | {(GpsErrors.__module__, "GpsErrors")} == listed
    for module, name in listed:
        assert getattr(importlib.import_module(module), name) in OPTIONS


@pytest.mark.parametrize("cls", list(OPTIONS), ids=lambda c: c.__name__)
def test_the_defaults_pass_and_validate_runs_when_made(cls, monkeypatch):
    options = cls(**OPTIONS[cls])
    options.validate()
    calls = []
    monkeypatch.setattr(cls, "validate", lambda self: calls.append(self))
    made = cls(**OPTIONS[cls])
    assert len(calls) == 1 and calls[0] is made  # once, by __post_init__


def test_every_class_above_has_a_rejected_value():
    assert {cls for cls, *_ in BAD} == set(OPTIONS)


@pytest.mark.parametrize("cls, values, error, fragment", BAD, ids=lambda v: v.__name__ if isinstance(v, type) else None)
def test_validate_rejects_the_value_naming_the_flag(cls, values, error, fragment):
    with pytest.raises(error, match=fragment.replace("-", r"\-")):
        cls(**{**OPTIONS[cls], **values})
    # A value set after the fact is refused by validate() as well.
    options = cls(**OPTIONS[cls])
    for key, value in values.items():
        object.__setattr__(options, key, value)
    with pytest.raises(error, match=fragment.replace("-", r"\-")):
        options.validate()


def test_a_lower_overlap_lowers_the_forced_keyframe_overlap_too():
    assert KeyframeOptions(new_ground=0.3).force_overlap == 0.3
    assert KeyframeOptions().force_overlap == 0.35


def test_a_derived_copy_is_checked_too():
    with pytest.raises(BadInput, match="--radius"):
        dataclasses.replace(StabilizeOptions(), radius=0)


# --------------------------------------------------------------------------- on the command line

# Per command: (flags, the flag the one line names).  Each is refused before any work.
CLI_CASES = {
    "track": [
        (["--max-frames", "1"], "--max-frames"),
        (["--threads", "0"], "--threads"),
        (["--timeout", "0"], "--timeout"),
        (["--work-width", "16"], "--work-width"),
        (["--device", "tpu"], "--device"),
        (["-e", "orb:refine=sift"], "refine"),
        (["-e", "lstm:patches=4"], "patches"),
        (["-e", "lstm:chunk=0"], "chunk"),
        (["-e", "lstm:reset-every=0"], "reset-every"),
        (["--refine", "none"], "--refine is an estimator setting now: -e lstm:refine=none"),
    ],
    "stitch": [
        (["--overlap", "0.99"], "--overlap"),
        (["--max-loop-pairs", "-1"], "--max-loop-pairs"),
        (["--reference", "left"], "--reference"),
        (["--max-size", "10"], "--max-size"),
        (["--blend", "average"], "--blend"),
        (["--seam", "x"], "--seam"),
        (["--exposure", "x"], "--exposure"),
        (["--start", "-1"], "--start"),
        (["--max-frames", "1"], "--max-frames"),
        (["--timeout", "0"], "--timeout"),
        (["--live", "--every", "0"], "--every"),
        (["--preview", "{tmp}/preview.gif"], "--preview"),
        (["--hfov", "200"], "--hfov"),
        (["--footprints", "{tmp}/footprints.txt"], "--footprints"),
        (["--work-width", "100000"], "--work-width"),
    ],
    "stabilize": [
        (["--radius", "0"], "--radius"),
        (["--smoothing", "kalman"], "--smoothing"),
        (["--model", "rigid"], "--model"),
        (["--crop", "0.2"], "--crop"),
        (["--border", "white"], "--border"),
        (["--crf", "52"], "--crf"),
        (["--preset", "fastest"], "--preset"),
        (["--work-width", "16"], "--work-width"),
        (["--device", "tpu"], "--device"),
        (["--latency", "0"], "--latency"),
        (["--timeout", "0"], "--timeout"),
    ],
    "eval": [
        ([], "--gt"),
        (["--gt", "{tmp}/flight.gt.json", "--every", "0"], "--every"),
        (["--annotations", "{tmp}/ann.txt", "--size", "4x4"], "--size"),
    ],
    "bench": [
        (["--frames", "1"], "--frames"),
        (["--profile", "wobbly"], "--profile"),
        (["--seed", "-1"], "--seed"),
        (["--threads", "0"], "--threads"),
        (["--work-width", "16"], "--work-width"),
        (["--device", "tpu"], "--device"),
        (["-e", "orb,orb"], "--estimators"),
        (["--size", "8x8"], "--size"),
    ],
    "simulate": [
        (["--frames", "1"], "--frames"),
        (["--fps", "0"], "--fps"),
        (["--seed", "-1"], "--seed"),
        (["--crf", "52"], "--crf"),
        (["--preset", "fastest"], "--preset"),
        (["--profile", "wobbly"], "--profile"),
        (["--size", "8x8"], "--size"),
        (["--telemetry", "kml"], "--telemetry"),
        (["--telemetry", "gpx", "--telemetry-rate", "-1"], "--telemetry-rate"),
        (["--telemetry", "gpx", "--gps-noise", "-1"], "--gps-noise"),
        (["--telemetry", "gpx", "--gps-dropouts", "1"], "--gps-dropouts"),
        (["--telemetry", "gpx", "--origin", "95,0"], "--origin"),
        (["--telemetry", "gpx", "--gsd", "0"], "--gsd"),
    ],
    "train": [
        (["--steps", "0"], "--steps"),
        (["--batch-size", "0"], "--batch-size"),
        (["--lr", "0"], "--lr"),
        (["--seed", "-1"], "--seed"),
        (["--threads", "0"], "--threads"),
        (["--patch", "8"], "--patch"),
        (["--work-size", "100x60"], "--work-size"),
        (["--num-workers", "-1"], "--num-workers"),
        (["--checkpoint-every", "0"], "--checkpoint-every"),
        (["--checkpoint-minutes", "0"], "--checkpoint-minutes"),
        (["--val-every", "0"], "--val-every"),
        (["--cache-gb", "0"], "--cache-gb"),
        (["--variant", "huge"], "--variant"),
    ],
}


def command_line(command: str, clip: Path, tmp: Path) -> list:
    """The command with everything it needs but the flag under test."""
    return {
        "track": ["track", clip, "-o", tmp / "t.json", "-q"],
        "stitch": ["stitch", clip, "-o", tmp / "p.png", "-e", "orb", "-q"],
        "stabilize": ["stabilize", clip, tmp / "s.mp4", "-e", "orb", "-q"],
        "eval": ["eval", tmp / "track.json", "-q"],
        "bench": ["bench", "-e", "identity", "-q"],
        "simulate": ["simulate", "-o", tmp / "f.mp4", "-q"],
        "train": ["train", clip.parent, "-o", tmp / "run", "-q"],
    }[command]


@pytest.mark.parametrize("command, flags, flag", [(c, f, n) for c, cases in CLI_CASES.items() for f, n in cases],
                         ids=lambda v: " ".join(v) if isinstance(v, list) else None)
def test_an_out_of_range_flag_is_one_line_naming_it_exit_2_and_no_output(capsys, tiny_clip, tmp_path, command, flags, flag):
    work = tmp_path / "work"
    work.mkdir()
    if command == "eval":
        (work / "track.json").write_text("{}")
    args = [*command_line(command, tiny_clip, work), *(f.format(tmp=work) for f in flags)]
    before = sorted(work.iterdir())
    code, err = run_cli(capsys, *args)
    assert_one_line_error(code, err, flag)
    assert sorted(work.iterdir()) == before
