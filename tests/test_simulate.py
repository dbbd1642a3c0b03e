"""Simulated flights: exact geometry, motion statistics per profile, ground-truth format."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import cli_exit
from mosaic_cli.cli import main
from mosaic_cli.errors import BadInput
from mosaic_cli.geometry import project
from mosaic_cli.simulate import (
    PROFILES,
    FlightPlan,
    GroundTruth,
    centre_motion,
    load_ground_truth,
    load_map,
    plan_flight,
    procedural_map,
    render_frames,
    write_flight,
)
from mosaic_cli.simulate.trajectory import footprints

SIZE = (320, 180)


@pytest.fixture(scope="module")
def small_map():
    return procedural_map((1024, 1024), seed=5)


def test_procedural_map_is_deterministic_and_textured(small_map):
    assert small_map.shape == (1024, 1024, 3) and small_map.dtype == np.uint8
    again = procedural_map((1024, 1024), seed=5)
    assert np.array_equal(small_map, again)
    assert not np.array_equal(small_map, procedural_map((1024, 1024), seed=6))
    gray = cv2.cvtColor(small_map, cv2.COLOR_RGB2GRAY)
    assert gray.std() > 15  # not flat
    assert len(cv2.ORB_create(500).detect(gray, None)) > 200  # features to track


def test_procedural_map_other_shapes():
    m = procedural_map((300, 200), seed=1)
    assert m.shape == (200, 300, 3)
    with pytest.raises(BadInput):
        procedural_map((10, 10))


def test_plan_api_and_pairwise_definition():
    plan = plan_flight((1024, 1024), "paper", frames=20, size=SIZE, seed=3)
    assert isinstance(plan, FlightPlan)
    assert plan.map_to_frame.shape == (20, 3, 3) and plan.smooth_map_to_frame.shape == (20, 3, 3)
    assert plan.pairwise.shape == (19, 3, 3)
    assert plan.size == SIZE and plan.profile == "paper" and plan.seed == 3
    for t in (0, 7, 18):
        expected = plan.map_to_frame[t + 1] @ np.linalg.inv(plan.map_to_frame[t])
        assert np.allclose(plan.pairwise[t], expected / expected[2, 2])
    np.testing.assert_array_equal(plan.map_to_frame, plan.smooth_map_to_frame)
    again = plan_flight((1024, 1024), "paper", frames=20, size=SIZE, seed=3)
    np.testing.assert_array_equal(plan.map_to_frame, again.map_to_frame)


@pytest.mark.parametrize(
    "profile,lo,hi",
    [("paper", 1.0, 2.0), ("survey", 4.0, 7.0), ("fast", 10.0, 20.0), ("hard", 1.0, 2.0), ("extreme", 25.0, 60.0)],
)
def test_profile_speed_in_range(profile, lo, hi):
    plan = plan_flight((4096, 4096), profile, frames=300, size=SIZE, seed=11)
    m = centre_motion(plan.pairwise, plan.size)
    p5, p50, p95 = np.percentile(m, [5, 50, 95])
    assert lo * 0.9 <= p5 and p95 <= hi * 1.1, (p5, p50, p95)
    assert lo <= p50 <= hi


@pytest.mark.parametrize("profile", list(PROFILES))
def test_footprint_inside_map_and_tilted(profile):
    for map_size in ((4096, 4096), (1062, 627), (700, 900)):
        plan = plan_flight(map_size, profile, frames=200, size=(1280, 720), seed=2)
        corners = footprints(plan)
        assert corners.min() >= -0.5
        assert corners[..., 0].max() <= map_size[0] - 0.5 and corners[..., 1].max() <= map_size[1] - 0.5
        # a slight perspective tilt: the footprint is not a parallelogram
        H = plan.map_to_frame[0] / plan.map_to_frame[0][2, 2]
        assert np.abs(H[2, :2]).max() > 1e-7


def test_slow_heading_changes():
    plan = plan_flight((4096, 4096), "paper", frames=300, size=(1280, 720), seed=4)
    angles = np.degrees(np.arctan2(plan.pairwise[:, 1, 0], plan.pairwise[:, 0, 0]))
    assert np.abs(angles).max() < 0.25  # degrees per frame


def test_shaky_has_3_to_8_hz_jitter_around_the_smooth_path():
    plan = plan_flight((4096, 4096), "shaky", frames=300, size=(1280, 720), seed=8)
    assert not np.allclose(plan.map_to_frame, plan.smooth_map_to_frame)
    c = np.array([[639.5, 359.5]])
    shaken = np.array([project(m, c)[0] for m in plan.map_to_frame])
    smooth = np.array([project(m, c)[0] for m in plan.smooth_map_to_frame])
    d = shaken - smooth
    amp = np.abs(d).max()
    assert 1.0 < amp < 8.0  # a few px
    spectrum = np.abs(np.fft.rfft(d[:, 0] - d[:, 0].mean()))
    freqs = np.fft.rfftfreq(len(d), 1 / plan.fps)
    band = (freqs >= 2.5) & (freqs <= 8.5)
    assert spectrum[band].sum() > 0.8 * spectrum.sum()


def test_shaky_tilt_adds_pitch_and_roll_shake():
    size, f = (1280, 720), 1280.0  # the simulator's focal length is the frame width
    for profile in ("shaky", "shaky-tilt"):
        plan = plan_flight((4096, 4096), profile, frames=300, size=size, seed=8)
        # the shake, frame of the jitter-free camera -> frame: K R(pitch, roll) K^-1 on top of
        # the in-plane shake (an affine map), so its perspective row is the tilt's alone
        shake = plan.map_to_frame @ np.linalg.inv(plan.smooth_map_to_frame)
        shake /= shake[:, 2:3, 2:3]
        tilt = np.degrees(np.arcsin(np.clip(shake[:, 2, :2] * f, -1, 1)))  # (N, 2) about the y and x axes
        if profile == "shaky":
            assert np.abs(tilt).max() < 1e-6
            continue
        for angle in tilt.T:
            assert 0.1 < np.abs(angle).max() <= 0.31  # up to 0.3 degrees (and the in-plane shake's turn of it)
            spectrum = np.abs(np.fft.rfft(angle - angle.mean()))
            freqs = np.fft.rfftfreq(len(angle), 1 / plan.fps)
            assert spectrum[(freqs >= 2.5) & (freqs <= 8.5)].sum() > 0.8 * spectrum.sum()
        # pitch and roll move the view too: by about f * angle at the centre
        c = np.array([[639.5, 359.5]])
        moved = np.array([project(m, c)[0] for m in shake]) - c
        assert np.abs(moved).max() > 0.2 * np.radians(np.abs(tilt).max()) * f


def test_survey_revisits_ground():
    plan = plan_flight((4096, 4096), "survey", frames=300, size=SIZE, seed=1)
    c = np.array([[SIZE[0] / 2 - 0.5, SIZE[1] / 2 - 0.5]])
    centres = np.array([project(np.linalg.inv(m), c)[0] for m in plan.map_to_frame])
    half_h = 0.5 * SIZE[1] * abs(np.linalg.det(np.linalg.inv(plan.map_to_frame[0])[:2, :2])) ** 0.5
    revisits = 0
    for t in range(len(centres)):
        later = centres[t + 60 :]
        if len(later) and np.linalg.norm(later - centres[t], axis=1).min() < half_h:
            revisits += 1
    assert revisits > 30
    # lawnmower: the direction of travel reverses
    v = np.diff(centres, axis=0)
    assert (v[:, 0] > 0).any() and (v[:, 0] < 0).any()


def test_map_too_small_is_refused():
    with pytest.raises(BadInput, match="too small"):
        plan_flight((100, 100), "paper", frames=10, size=(1280, 720))
    with pytest.raises(BadInput):
        plan_flight((1024, 1024), "nope", frames=10, size=SIZE)
    with pytest.raises(BadInput):
        plan_flight((1024, 1024), "paper", frames=1, size=SIZE)


def _interior_error(a, b, border=30):
    return float(np.abs(a[border:-border, border:-border].astype(float) - b[border:-border, border:-border].astype(float)).mean())


@pytest.mark.parametrize("profile", ["paper", "fast", "shaky"])
def test_rendering_matches_ground_truth(small_map, profile):
    plan = plan_flight((1024, 1024), profile, frames=12, size=SIZE, seed=9)
    frames = list(render_frames(small_map, plan))
    assert len(frames) == 12 and frames[0].shape == (SIZE[1], SIZE[0], 3) and frames[0].dtype == np.uint8
    shift = np.array([[1.0, 0, 1.0], [0, 1, 0], [0, 0, 1]])
    for t in (0, 5, 10):
        H = plan.pairwise[t]
        back = cv2.warpPerspective(frames[t + 1], H, SIZE, flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        off = cv2.warpPerspective(frames[t + 1], shift @ H, SIZE, flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
        exact, wrong = _interior_error(frames[t], back), _interior_error(frames[t], off)
        assert exact < 1.5 and exact < 0.5 * wrong, (exact, wrong)


def test_known_points_project_where_the_ground_truth_says():
    # A black map with bright dots: their centroids in the rendered frame follow map_to_frame.
    rng = np.random.default_rng(0)
    m = np.full((1024, 1024, 3), 20, np.uint8)
    pts = rng.uniform(100, 924, size=(400, 2))
    for x, y in pts:
        cv2.circle(m, (int(round(x * 16)), int(round(y * 16))), 3 * 16, (255, 255, 255), -1, cv2.LINE_AA, shift=4)
    m = cv2.GaussianBlur(m, (0, 0), 2.0)
    plan = plan_flight((1024, 1024), "paper", frames=3, size=(640, 360), seed=1)
    frame = next(iter(render_frames(m, plan)))
    gray = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY).astype(np.float64)
    proj = project(plan.map_to_frame[0], pts)
    errors = []
    for x, y in proj:
        if 12 <= x < 640 - 12 and 12 <= y < 360 - 12:
            x0, y0 = int(round(x)), int(round(y))
            win = gray[y0 - 6 : y0 + 7, x0 - 6 : x0 + 7] - 20
            win = np.clip(win, 0, None)
            yy, xx = np.mgrid[-6:7, -6:7]
            cx, cy = (win * xx).sum() / win.sum() + x0, (win * yy).sum() / win.sum() + y0
            errors.append(np.hypot(cx - x, cy - y))
    assert len(errors) > 10
    assert np.median(errors) < 0.3


def test_anti_aliasing_on_zoomed_out_flights():
    # A map of 1-px checkerboard seen from high above must render as flat grey, not moire.
    checker = ((np.indices((2048, 2048)).sum(0) % 2) * 255).astype(np.uint8)
    m = np.repeat(checker[..., None], 3, axis=2)
    plan = plan_flight((2048, 2048), "paper", frames=2, size=(320, 180), seed=0)
    frame = next(iter(render_frames(m, plan)))
    assert abs(frame.mean() - 127.5) < 3 and frame.std() < 6


def test_hard_profile_effects_only_in_pixels(small_map):
    plan = plan_flight((1024, 1024), "hard", frames=6, size=SIZE, seed=2)
    ref = plan_flight((1024, 1024), "paper", frames=6, size=SIZE, seed=2)
    assert set(plan.effects) >= {"gain", "noise_sigma", "blur"}
    clean = FlightPlan(plan.map_to_frame, plan.smooth_map_to_frame, plan.size, "paper", plan.seed, plan.map_size, plan.fps)
    a = list(render_frames(small_map, plan))
    b = list(render_frames(small_map, clean))
    assert all(not np.array_equal(x, y) for x, y in zip(a, b))
    assert ref.map_to_frame.shape == plan.map_to_frame.shape
    again = list(render_frames(small_map, plan))
    assert all(np.array_equal(x, y) for x, y in zip(a, again))  # deterministic noise


def test_extreme_profile_turns_fast_and_degrades_the_pixels_only():
    """Yaw turns (degrees a frame well above the paper profile's 0.25), altitude changes, and
    on a flat gray map the vignetting darkens the corners while the geometry stays exact."""
    plan = plan_flight((4096, 4096), "extreme", frames=300, size=(1280, 720), seed=4)
    angles = np.degrees(np.arctan2(plan.pairwise[:, 1, 0], plan.pairwise[:, 0, 0]))
    assert np.abs(angles).max() > 0.5  # 15 degrees/s at 30 fps
    scale = np.sqrt(np.abs(np.linalg.det(plan.map_to_frame[:, :2, :2])))
    assert scale.max() / scale.min() > 1.2  # altitude changes of tens of percent
    assert {"gain", "noise_sigma", "blur", "vignette", "contrast"} <= set(plan.effects)
    gray = np.full((2048, 2048, 3), 128, np.uint8)
    small = plan_flight((2048, 2048), "extreme", frames=3, size=(320, 180), seed=4)
    frame = next(iter(render_frames(gray, small))).astype(float)
    centre, corner = frame[70:110, 140:180].mean(), frame[:20, :20].mean()
    assert corner < centre * (1 - 0.5 * small.effects["vignette"][0])
    assert PROFILES["extreme"].crf > PROFILES["paper"].crf  # low-bitrate encoding by default


def test_write_flight_and_ground_truth_round_trip(tmp_path, small_map):
    from mosaic_cli.video import open_video

    plan = plan_flight((1024, 1024), "shaky", frames=10, size=SIZE, seed=4)
    out = tmp_path / "flight.mp4"
    write_flight(out, small_map, plan, fps=25, map_name="test-map", show_progress=False)
    gt_path = tmp_path / "flight.gt.json"
    assert out.exists() and gt_path.exists()
    data = json.loads(gt_path.read_text())
    assert data["version"] == 1 and data["kind"] == "mosaic-ground-truth" and data["direction"] == "t_to_t+1"
    assert data["frames"] == 10 and data["size"] == list(SIZE) and data["fps"] == 25 and data["profile"] == "shaky"
    assert data["map"] == "test-map" and data["map_size"] == [1024, 1024] and data["seed"] == 4
    assert np.array(data["pairwise"]).shape == (9, 3, 3)
    loaded = load_ground_truth(gt_path)
    assert isinstance(loaded, GroundTruth)
    assert loaded.frames == 10 and loaded.size == SIZE and loaded.fps == 25 and loaded.map_size == (1024, 1024)
    np.testing.assert_allclose(loaded.map_to_frame, plan.map_to_frame, rtol=0, atol=1e-12)
    np.testing.assert_allclose(loaded.smooth_map_to_frame, plan.smooth_map_to_frame, rtol=0, atol=1e-12)
    np.testing.assert_allclose(loaded.pairwise, plan.pairwise, rtol=0, atol=1e-12)
    assert load_ground_truth(out).frames == 10  # the video's path finds its ground truth
    # the encoded video decodes to the rendered frames
    with open_video(out) as stream:
        decoded = list(stream)
    assert len(decoded) == 10
    rendered = list(render_frames(small_map, plan))
    assert _interior_error(decoded[3], rendered[3], 4) < 4.0
    assert not list(tmp_path.glob(".*part*"))


def test_load_ground_truth_errors(tmp_path):
    with pytest.raises(BadInput, match="no such file"):
        load_ground_truth(tmp_path / "missing.gt.json")
    bad = tmp_path / "bad.gt.json"
    bad.write_text("{not json")
    with pytest.raises(BadInput):
        load_ground_truth(bad)
    bad.write_text(json.dumps({"kind": "something"}))
    with pytest.raises(BadInput, match="not a mosaic ground-truth"):
        load_ground_truth(bad)
    bad.write_text(json.dumps({"kind": "mosaic-ground-truth", "version": 1, "map_to_frame": [[1]]}))
    with pytest.raises(BadInput):
        load_ground_truth(bad)


def test_load_map_variants(tmp_path):
    rgb = np.zeros((120, 200, 3), np.uint8)
    rgb[..., 0] = 200  # red in RGB
    cv2.imwrite(str(tmp_path / "m.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    m = load_map(tmp_path / "m.png")
    assert m.shape == (120, 200, 3) and m[0, 0, 0] == 200 and m[0, 0, 2] == 0
    # RGBA with a transparent outside: cropped to the opaque rectangle
    rgba = np.zeros((300, 400, 4), np.uint8)
    rgba[..., :3] = 90
    rgba[50:250, 80:330, 3] = 255
    rgba[60:70, 300:330, 3] = 0  # a notch
    cv2.imwrite(str(tmp_path / "ortho.png"), rgba)
    m = load_map(tmp_path / "ortho.png")
    assert 150 <= m.shape[0] <= 200 and 200 <= m.shape[1] <= 250
    gray16 = (2000 + np.arange(100 * 100).reshape(100, 100) * 5).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "g16.png"), gray16)
    assert load_map(tmp_path / "g16.png").shape == (100, 100, 3)
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(BadInput):
        load_map(tmp_path / "junk.png")
    with pytest.raises(BadInput):
        load_map(tmp_path / "missing.png")


@pytest.mark.slow
def test_simulate_command(tmp_path, capsys):
    out = tmp_path / "f.mp4"
    assert cli_exit(["simulate", "-o", str(out), "--frames", "8", "--size", "160x96", "--profile", "fast", "--seed", "3", "-q"]) == 0
    gt = load_ground_truth(tmp_path / "f.gt.json")
    assert gt.frames == 8 and gt.size == (160, 96) and gt.profile == "fast" and gt.map_name == "procedural"


def test_simulate_command_over_an_image(tmp_path):
    img = procedural_map((600, 500), seed=2)
    cv2.imwrite(str(tmp_path / "map.jpg"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    assert cli_exit(["simulate", str(tmp_path / "map.jpg"), "-o", str(tmp_path / "f.mp4"), "--frames", "5", "--size", "160x90", "-q"]) == 0
    gt = load_ground_truth(tmp_path / "f.gt.json")
    assert gt.map_name == "map.jpg" and gt.map_size == (600, 500)


@pytest.mark.parametrize(
    "args,message",
    [
        (["--profile", "wobbly"], "--profile must be one of"),
        (["--frames", "1"], "at least 2"),
        (["--size", "big"], "--size"),
        (["--fps", "0"], "--fps"),
        (["--crf", "60"], "--crf must be in 0..51"),
    ],
)
def test_simulate_command_errors(tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "-o", str(tmp_path / "f.mp4"), "-q", *args])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_simulate_command_bad_map(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", str(tmp_path / "nope.png"), "-o", str(tmp_path / "f.mp4"), "-q"])
    assert exc.value.code == 2 and "no such file" in capsys.readouterr().err
    tiny = tmp_path / "tiny.png"
    cv2.imwrite(str(tiny), np.zeros((80, 80, 3), np.uint8))
    with pytest.raises(SystemExit) as exc:
        main(["simulate", str(tiny), "-o", str(tmp_path / "f.mp4"), "-q"])
    assert exc.value.code == 2 and "too small" in capsys.readouterr().err
    assert not (tmp_path / "f.mp4").exists()


def test_load_map_crops_opaque_white_fill(tmp_path):
    # Orthomosaic previews often mark "no data" with opaque white, not transparency.
    img = np.full((300, 400, 4), 255, np.uint8)
    inner = procedural_map((240, 180), seed=3)
    img[60:240, 100:340, :3] = cv2.cvtColor(inner, cv2.COLOR_RGB2BGR)
    img[100:110, 200:210, :3] = 255  # a small white roof inside is real data
    cv2.imwrite(str(tmp_path / "ortho.png"), img)
    m = load_map(tmp_path / "ortho.png")
    assert 170 <= m.shape[0] <= 180 and 225 <= m.shape[1] <= 240
    assert not (m >= 250).all(axis=2).all(axis=0).any()  # no all-white column left


# --- bursts: frames without a motion cue ------------------------------------------------------


@pytest.mark.slow
def test_bursts_spoil_the_listed_frames_and_keep_the_geometry_exact(small_map, tmp_path):
    """The 'bursts' profile: the ground truth lists every spoilt frame; a duplicated frame shows
    exactly the frame before (pairwise identity), a dropped one makes its pair span two flown
    intervals (the product of the two steps of the same flight without bursts), and the pixel
    kinds take the band-passed detail far below the neighbours' (what the estimator calls
    spoilt) while the frames around them are untouched."""
    from mosaic_cli.estimators.correlation import detail_level
    from mosaic_cli.simulate import SimulateOptions, plan_simulated_flight
    from mosaic_cli.simulate.bursts import BurstSpec, burst_pairs, frames_to_plan, plan_bursts

    spec = BurstSpec(PROFILES["bursts"].bursts)
    seed = next(s for s in range(50) if {b.kind for b in plan_bursts(240, spec, s)} == set(spec.kinds))  # every kind
    options = SimulateOptions(profile="bursts", frames=240, size=SIZE, seed=seed)
    plan = plan_simulated_flight((1024, 1024), options)
    kinds = {b.frame: b.kind for b in plan.bursts}
    assert plan.frames == 240 and len(plan.bursts) >= 8 and set(kinds.values()) == set(spec.kinds)
    for t, kind in kinds.items():
        if kind == "duplicate":
            np.testing.assert_allclose(plan.pairwise[t - 1], np.eye(3), atol=1e-12)
    # Drops: the same flight planned without bursts, the dropped frames taken out.
    flown = plan_flight((1024, 1024), "bursts", frames_to_plan(240, spec), SIZE, seed)
    drops = sorted(t for t, k in kinds.items() if k == "drop")
    for t in drops:
        k = t + sum(1 for d in drops if d < t) + 1  # flown index of video frame t (the one before it was dropped)
        spanned = flown.pairwise[k - 1] @ flown.pairwise[k - 2]
        np.testing.assert_allclose(plan.pairwise[t - 1], spanned / spanned[2, 2], rtol=1e-9, atol=1e-9)
    frames = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in render_frames(small_map, plan)]
    levels = np.array([detail_level(cv2.resize(f, (320, 180))) for f in frames])
    clean = np.median(levels)
    for t, kind in kinds.items():
        if kind in ("glare", "dark", "flat"):
            assert levels[t] < 0.2 * clean, (t, kind, levels[t], clean)
        elif kind == "blur":
            assert levels[t] < 0.8 * clean, (t, kind, levels[t], clean)
    # The pairs that touch them: both pairs around a spoilt frame, the one pair of a drop or duplicate.
    touched = burst_pairs(plan.bursts, plan.frames - 1)
    for t, kind in kinds.items():
        assert touched[t - 1] and (kind in ("drop", "duplicate") or touched[t])
    # Written and read back with the video.
    gt = write_flight(tmp_path / "b.mp4", small_map, plan, show_progress=False)
    assert load_ground_truth(tmp_path / "b.mp4").bursts == gt.bursts == [{"frame": b.frame, "kind": b.kind} for b in plan.bursts]


@pytest.mark.slow
def test_bursts_option_and_its_errors(tmp_path, capsys):
    from mosaic_cli.simulate.bursts import KINDS, BurstSpec

    assert BurstSpec.parse("all").kinds == KINDS and not BurstSpec.parse("none").any and not BurstSpec.parse(None).any
    assert BurstSpec.parse("glare, dark").kinds == ("glare", "dark")
    code = cli_exit(["simulate", "-o", str(tmp_path / "x.mp4"), "--bursts", "glare,fog", "-n", "4", "--size", "64x48"])
    assert code == 2 and "unknown kind 'fog'" in capsys.readouterr().err and not (tmp_path / "x.mp4").exists()
    # A paper flight with dark frames only: listed, and a paper flight without the option lists none.
    assert cli_exit(["simulate", "-o", str(tmp_path / "d.mp4"), "--bursts", "dark", "-n", "60", "--size", "128x72", "-q"]) == 0
    listed = load_ground_truth(tmp_path / "d.mp4").bursts
    assert listed and {b["kind"] for b in listed} == {"dark"}
    assert cli_exit(["simulate", "-o", str(tmp_path / "p.mp4"), "-n", "60", "--size", "128x72", "-q"]) == 0
    assert load_ground_truth(tmp_path / "p.mp4").bursts == []
    assert "bursts" not in json.loads((tmp_path / "p.gt.json").read_text())  # the format of flights without them is unchanged
