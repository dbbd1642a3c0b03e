"""The estimators' options (``-e NAME:OPTION=VALUE`` and the flags that set them) are read off
their config dataclasses (mosaic_cli/estimators/options.py): every option field is accepted, a
value not of its kind or none of its choices is refused in one line that lists what it takes,
and ``--help`` lists them all with their choices and defaults."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from conftest import assert_one_line_error, run_cli
from mosaic_cli.errors import BadInput
from mosaic_cli.estimators import LEARNED, OPTIONS, make_estimator, options_help, parse_spec, typed_options
from mosaic_cli.estimators.learned_config import LearnedConfig
from mosaic_cli.estimators.options import Option, options_of
from mosaic_cli.estimators.orb import OrbConfig

# What no user sets: the polish's settings and the thresholds measured once (models/README.md).
INTERNAL = {"agreement_px", "max_area_ratio", "polish", "polish_wide", "polish_band", "polish_band_min_downscale", "corners",
            "unpolished_weight", "min_zncc", "carry_confidence"}


def written(value) -> str:
    return "none" if value is None else str(value)


def values_to_try(opt: Option) -> list:
    """Every choice, or a value of the option's kind other than its default."""
    if opt.choices is not None:
        return list(opt.choices)
    return {int: [3], float: [0.5]}[opt.kind]


def test_the_learned_options_are_the_config_fields_but_its_internal_knobs():
    fields = {f.name for f in dataclasses.fields(LearnedConfig)}
    assert set(OPTIONS["lstm"]) == fields - INTERNAL | {"weights"}
    assert set(OPTIONS["cnn"]) == set(OPTIONS["lstm"]) - {"reset_every"}  # a CNN has no state to reset
    assert set(OPTIONS["orb"]) == set(OPTIONS["orb-ransac"]) == {"refine"}


def test_the_table_reads_types_choices_and_defaults_off_the_annotations():
    lstm = OPTIONS["lstm"]
    assert lstm["patches"] == Option("patches", int, (1, 5, 9), 1)
    assert lstm["refine"] == Option("refine", str, ("lk", "ecc", None), "lk")
    assert lstm["reset_every"] == Option("reset-every", int, None, None)
    assert lstm["spoilt_ratio"] == Option("spoilt-ratio", float, None, 0.8, ablation=True)
    assert lstm["weights"] == Option("weights", Path)
    assert options_of(OrbConfig)["refine"] == lstm["refine"]


@pytest.mark.parametrize("name", LEARNED)
def test_every_option_field_is_accepted_with_every_value_it_takes(name):
    for field, opt in OPTIONS[name].items():
        if field == "weights":
            continue
        for value in values_to_try(opt):
            base, given = parse_spec(f"{name}:{opt.key.upper()}={written(value).upper()}")  # any case
            typed = typed_options(base, given)
            assert typed == {field: value}, (field, value)
            assert getattr(LearnedConfig(**typed), field) == value


def test_a_flag_gives_its_value_already_typed():
    assert typed_options("lstm", {"patches": 5, "reset_every": 300, "refine": None, "chunk": 4}) == {
        "patches": 5, "reset_every": 300, "chunk": 4}
    assert typed_options("lstm", {"weights": "Run/Weights.safetensors"}) == {"weights": "Run/Weights.safetensors"}  # case kept


@pytest.mark.parametrize("field", [f for f, opt in OPTIONS["lstm"].items() if opt.choices is not None])
def test_a_bad_choice_lists_the_valid_ones(field):
    opt = OPTIONS["lstm"][field]
    bad = "4" if opt.kind is int else "bogus"
    with pytest.raises(BadInput) as refused:
        make_estimator(f"lstm:{opt.key}={bad}", device="cpu")
    choices = ", ".join(written(c) for c in opt.choices if c is not None) + (" or none" if None in opt.choices else "")
    assert str(refused.value) == f"{opt.key} must be one of {choices}, got {int(bad) if opt.kind is int else bad!r}"


def test_the_choices_are_written_as_before():
    with pytest.raises(BadInput, match=r"^refine must be one of lk, ecc or none, got 'sift'$"):
        OrbConfig(refine="sift")
    with pytest.raises(BadInput, match=r"^patches must be one of 1, 5, 9, got 4$"):
        LearnedConfig(patches=4)


@pytest.mark.parametrize("spec, line", [
    ("lstm:chunk=many", "estimator 'lstm': chunk must be a whole number, got 'many'"),
    ("cnn:spoilt-ratio=high", "estimator 'cnn': spoilt-ratio must be a number, got 'high'"),
    ("orb:refine=2", "refine must be one of lk, ecc or none, got '2'"),
])
def test_a_wrong_type_is_one_line(capsys, tiny_clip, tmp_path, spec, line):
    code, err = run_cli(capsys, "track", tiny_clip, "-o", tmp_path / "t.json", "-e", spec, "-q")
    assert_one_line_error(code, err)
    assert err.strip() == f"mosaic: error: {line}"
    assert not (tmp_path / "t.json").exists()


def test_an_option_it_does_not_take_is_refused_listing_those_it_does():
    for spec, key in (("cnn:reset-every=3", "reset-every"), ("lstm:min-zncc=0.2", "min-zncc"), ("orb:chunk=4", "chunk")):
        name = spec.partition(":")[0]
        with pytest.raises(BadInput) as refused:
            make_estimator(spec, device="cpu")
        listed = ", ".join(opt.usage() for opt in OPTIONS[name].values())
        assert str(refused.value) == f"estimator {name!r} has no option {key!r} (its options: {listed})"
    assert OPTIONS["orb"]["refine"].usage() == "refine=lk|ecc|none (lk)"
    with pytest.raises(BadInput, match=r"^estimator 'identity' has no option 'refine' \(its options: none\)$"):
        make_estimator("identity:refine=lk")


def test_help_lists_every_user_option_with_its_choices_and_no_ablation_setting(monkeypatch):
    from typer.testing import CliRunner

    from mosaic_cli.cli import app

    text = options_help()
    for name in ("lstm", "orb"):
        for opt in OPTIONS[name].values():
            assert (opt.usage() in text) != opt.ablation, opt.key
    # What a user sets, and not the experiments' knobs (accepted, documented for developers).
    user = {key for key, opt in OPTIONS["lstm"].items() if not opt.ablation}
    assert user == {"patches", "chunk", "reset_every", "precision", "refine", "weights"}
    assert "carry" not in text and "spoilt" not in text and "seed=" not in text
    assert "reset-every=N (lstm only)" in text and "refine=lk|ecc|none (lk)" in text
    monkeypatch.setenv("COLUMNS", "2000")  # one line per option: nothing wrapped
    for command in ("track", "stitch", "stabilize"):
        shown = CliRunner().invoke(app, [command, "--help"], terminal_width=2000).output
        assert " ".join(text.split()) in " ".join(shown.split()), command


@pytest.mark.slow
def test_an_estimator_is_checked_without_torch_and_built_later(fresh_interpreter_build):
    """plan_estimator finds every mistake before any work without importing torch; the build
    (torch, the weights, the int8 network) is what the commands run beside overlay detection.
    (A fresh interpreter's, conftest's.)"""
    run = fresh_interpreter_build
    assert not run["planned"]["torch"]
    assert run["built"] == "LearnedEstimator" and run["after_build"]["torch"]


def test_the_build_beside_overlay_detection_gives_both_or_the_error(tmp_path):
    import numpy as np

    from conftest import write_clip
    from mosaic_cli.overlay import MaskOptions, frame_mask, frame_mask_while

    rng = np.random.default_rng(0)
    clip = write_clip(tmp_path / "c.mp4", [rng.integers(0, 255, (90, 160, 3), dtype=np.uint8) for _ in range(12)], fps=10)
    mask, built = frame_mask_while(lambda: "built", clip, MaskOptions())
    alone = frame_mask(clip, MaskOptions())
    assert built == "built"
    assert {k: v for k, v in mask.to_json().items() if k != "seconds"} == {k: v for k, v in alone.to_json().items() if k != "seconds"}

    def failing():
        raise BadInput("no such weights file")

    with pytest.raises(BadInput, match="no such weights file"):
        frame_mask_while(failing, clip, MaskOptions())


def test_the_polish_start_s_old_name_is_refused_naming_the_new_one():
    """``seed`` named what the polish starts from, beside every command's random ``--seed``: the
    old spelling is one line that names the new one, and the new one is taken."""
    from mosaic_cli.estimators import plan_estimator

    with pytest.raises(BadInput, match="-e lstm:seed is now -e lstm:polish-start"):
        plan_estimator("lstm:seed=velocity")
    plan_estimator("lstm:polish-start=velocity")  # checked, not built
