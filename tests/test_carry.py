"""The carry head (issue 38): a sequence head that starts as its CNN, whose memory can open under
training, trained from cached features against teacher offsets that are exact for drops,
duplicates, reversed and mirrored windows; and the estimator that runs it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from conftest import Flight
from mosaic_cli.estimators.learned import LearnedConfig, LearnedEstimator
from mosaic_cli.geometry import corner_error
from mosaic_cli.model import HomographyNet, NetConfig, load_weights
from mosaic_cli.model.network import GATE_START, OFFSET_SCALE, SEQUENCE_HEADS
from mosaic_cli.model.patches import patch_corners
from mosaic_cli.train.carry import DROP, DUPLICATE, EVENTS, WARM_UP, WINDOW, CarryObjective, Window, draw_window, teacher_offsets

pytestmark = pytest.mark.usefixtures("one_torch_thread")
CNN = "models/cnn.safetensors"
CARRY = "models/carry.safetensors"  # the carry head on that BASE (models/README.md, "The carry head")


def flight_patches(n: int = 24, size=(320, 180), step: float = 5.0, patch: int = 128) -> torch.Tensor:
    """(1, n-1, 2, P, P) centre patch pairs of a panning flight over a texture, in [-1, 1]."""
    flight = Flight(n_frames=n, frame_size=size, map_size=(1600, 900), seed=3, step=step)
    gray = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in flight.frames]
    x, y = (size[0] - patch) // 2, (size[1] - patch) // 2
    crops = torch.from_numpy(np.stack([g[y:y + patch, x:x + patch] for g in gray])).float() / 127.5 - 1.0
    return torch.stack([crops[:-1], crops[1:]], dim=1)[None]


LSTM = "models/lstm.safetensors"  # LSTM-REG-T, the default: a carry head may read its answer instead


def carry_from(base: HomographyNet) -> HomographyNet:
    torch.manual_seed(0)
    net = HomographyNet(NetConfig(preset=base.config.preset, head="carry", patch=base.config.patch, carry_base=base.head))
    net.start_as_carry(base)
    return net.eval()


# ----------------------------------------------------------------------------- the head


def assert_starts_as(base_net: HomographyNet, net: HomographyNet, pairs: torch.Tensor) -> tuple:
    """``net`` (a fresh carry head on ``base_net``) answers as ``base_net`` over ``pairs``: exactly on
    the first pair, then but for sigmoid(GATE_START) of the carried motion's distance to it.
    Returns the base's offsets, the head's and the head's state."""
    with torch.no_grad():
        base, _ = base_net(pairs)
        carried, state = net(pairs)
    torch.testing.assert_close(carried[:, 0], base[:, 0], rtol=0, atol=1e-6)
    leak = 1.0 / (1.0 + np.exp(-GATE_START))
    jumps = (base[:, 1:] - base[:, :-1]).abs().max()
    assert float((carried - base).abs().max()) <= 1.05 * leak * float(jumps) + 1e-5
    assert float(base.abs().mean()) > 1.0  # a flight that moves: the comparison is not of zeros
    return base, carried, state


def test_the_carry_head_starts_as_the_cnn_it_reads():
    cnn, _ = load_weights(CNN)
    _, _, state = assert_starts_as(cnn, carry_from(cnn), flight_patches())
    assert len(state) == 3 and "carry" in SEQUENCE_HEADS


def test_a_carry_head_on_lstm_reg_t_starts_as_lstm_reg_t_and_carries_both_states_in_one():
    """Over the default's BASE (LSTM-REG-T: the CNN's features, then its LSTM and Linear) the head
    starts as that network, its LSTM's state carried in the same tuple as the head's: the
    sequence read in two parts from the carried state is the sequence read at once, and a
    carry head on the CNN cannot start from LSTM-REG-T."""
    lstm, _ = load_weights(LSTM)
    net = carry_from(lstm)
    pairs = flight_patches()
    _, carried, state = assert_starts_as(lstm, net, pairs)
    with torch.no_grad():
        first, middle = net(pairs[:, :9])
        rest, _ = net(pairs[:, 9:], middle)
    h, c, previous = state
    assert h.shape[-1] == net.config.carry_hidden + net.config.hidden == c.shape[-1] and previous.shape[-1] == 8
    torch.testing.assert_close(torch.cat([first, rest], 1), carried, rtol=0, atol=1e-5)
    frozen = {id(p) for p in net.feature_parameters()}
    assert all(id(p) in frozen for p in net.lstm.parameters()) and not any(id(p) in frozen for p in net.carry.parameters())
    cnn_based = HomographyNet(NetConfig(head="carry"))
    with pytest.raises(ValueError, match="carry head on a cnn head"):
        cnn_based.start_as_carry(lstm)


def test_a_gate_without_memory_weighs_the_pair_alone():
    """With carry_gate_memory off, how far the head trusts its carried motion is a function of the
    current pair (its features, cues, the BASE's answer and the previous output) and not of the
    cell's state: a state that once decided "the BASE is wrong" cannot hold the gate shut on later
    textured pairs.  With it on (the shipped head), the state moves the gate."""
    torch.manual_seed(1)
    for memory in (False, True):
        net = HomographyNet(NetConfig(head="carry", carry_gate_memory=memory)).eval()
        with torch.no_grad():
            net.carry.gate[2].weight.normal_()
            features, cnn = torch.randn(3, 1, net.config.embed).abs(), torch.randn(3, 1, 8)
            previous = torch.randn(1, 3, 8)
            gates = [net.carry(features, cnn, (torch.randn(1, 3, 128), torch.randn(1, 3, 128), previous))[2] for _ in range(2)]
        assert torch.equal(gates[0], gates[1]) != memory


def test_the_carry_heads_memory_starts_open_for_a_window():
    net = HomographyNet(NetConfig(head="carry"))
    h = net.config.carry_hidden
    forget, inputs = net.carry.cell.bias_ih[h:2 * h].detach(), net.carry.cell.bias_ih[:h].detach()
    timescale = 1 + torch.exp(forget)  # chrono: a forget bias log(T - 1) keeps a state about T steps
    assert float(timescale.min()) >= 2.0 - 1e-4 and float(timescale.max()) <= WINDOW + 1e-3
    torch.testing.assert_close(inputs, -forget)
    assert float(net.carry.gate[2].bias.detach()) == GATE_START


def test_the_carry_head_learns_to_carry_the_motion_across_spoilt_pairs_in_a_few_hundred_steps():
    """Sequences of a smoothly turning motion whose spoilt pairs the CNN gets wildly wrong (and
    whose features say so): trained on the truth, the head places the spoilt pairs from its
    memory; the CNN, and the head restarted at the spoilt pair, cannot."""
    torch.manual_seed(0)
    head = HomographyNet(NetConfig(head="carry")).carry
    F, T = head.code.in_features, 24

    def batch(n: int) -> tuple[torch.Tensor, ...]:
        velocity = torch.randn(n, 1, 8) * 6.0
        turn = torch.randn(n, 1, 8) * 0.2
        truth = velocity + turn * torch.arange(T)[None, :, None]
        spoilt = torch.zeros(n, T, dtype=torch.bool)
        where = torch.randint(WARM_UP, T - 3, (n,))
        for k in range(3):
            spoilt[torch.arange(n), where + k] = torch.rand(n) < 0.8
        cnn = truth + 0.3 * torch.randn(n, T, 8)
        cnn[spoilt] = 20.0 * torch.randn(int(spoilt.sum()), 8)
        features = torch.randn(n, T, F) * 0.5
        features[..., 0] += 4.0 * spoilt  # a spoilt frame shows in its features
        return features, cnn, truth, spoilt

    optimizer = torch.optim.Adam(head.parameters(), lr=3e-3)
    for _ in range(300):
        features, cnn, truth, _ = batch(32)
        out, _, _ = head(features, cnn)
        loss = (out - truth).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    features, cnn, truth, spoilt = batch(256)
    with torch.no_grad():
        out, _, gate = head(features, cnn)
        first = spoilt.float().argmax(1)
        restarted = out.clone()
        for b in range(len(out)):  # the state restarted just before each sequence's first spoilt pair
            if spoilt[b].any():
                t = int(first[b])
                restarted[b, t:] = head(features[b:b + 1, t:], cnn[b:b + 1, t:], None)[0][0]
    error = (out - truth).abs().mean(-1)
    cnn_error = (cnn - truth).abs().mean(-1)
    restart_error = (restarted - truth).abs().mean(-1)
    assert float(error[spoilt].mean()) < 0.2 * float(cnn_error[spoilt].mean())
    assert float(restart_error[spoilt].mean()) > 3 * float(error[spoilt].mean())
    assert float(error[~spoilt].mean()) < 1.5 * float(cnn_error[~spoilt].mean())  # clean pairs: still the CNN's
    assert float(gate[spoilt].mean()) > 0.8 and float(gate[spoilt].mean()) > float(gate[~spoilt].mean()) + 0.4


# ----------------------------------------------------------------------------- training windows


def similarity(angle: float, scale: float, tx: float, ty: float) -> np.ndarray:
    c, s = scale * np.cos(angle), scale * np.sin(angle)
    return np.array([[c, -s, tx], [s, c, ty], [0, 0, 1.0]])


def test_teacher_offsets_are_exact_over_drops_duplicates_reversal_and_mirrors():
    rng = np.random.default_rng(1)
    size, patch = (320, 180), 128
    # Frame t sees the ground at G[t] (frame -> ground); the pair a -> b moves by G[b]^-1 G[a].
    G = [np.eye(3)]
    for _ in range(12):
        G.append(G[-1] @ similarity(rng.normal(0, 0.02), 1 + rng.normal(0, 0.01), *rng.normal(0, 4, 2)))
    H = np.stack([np.linalg.inv(G[t + 1]) @ G[t] for t in range(12)])
    ok = np.ones(12, bool)
    ok[9] = False  # the teacher could not confirm pair 9
    rows = np.array([2, 3, 5, 5, 6, 7, 8, 9, 10])  # a drop (3 -> 5), a duplicate (5, 5)
    events = np.array([0, DROP, DUPLICATE, 0, 0, 0, 0, 0])
    for reverse in (False, True):
        for left_right, upside_down in ((False, False), (True, False), (True, True)):
            r, e = (rows[::-1], events[::-1]) if reverse else (rows, events)
            window = Window(0, r.copy(), np.zeros(9, np.int64), np.zeros(9, np.float32), np.zeros(9, np.float32),
                            e.copy(), left_right, upside_down, (40, 30))
            offsets, known = teacher_offsets(window, H, ok, size, patch)
            corners = patch_corners(torch.tensor([40, 30]), patch).numpy().astype(np.float64)
            w, h = size
            for k, (a, b) in enumerate(zip(r[:-1], r[1:])):
                # Independent truth: the mirrored corners, through the ground (OpenCV), mirrored back.
                mirrored = corners.copy()
                if left_right:
                    mirrored[:, 0] = w - 1 - mirrored[:, 0]
                if upside_down:
                    mirrored[:, 1] = h - 1 - mirrored[:, 1]
                pair = np.linalg.inv(G[b]) @ G[a]
                moved = cv2.perspectiveTransform(mirrored[None], pair)[0]
                if left_right:
                    moved[:, 0] = w - 1 - moved[:, 0]
                if upside_down:
                    moved[:, 1] = h - 1 - moved[:, 1]
                np.testing.assert_allclose(offsets[k], moved - corners, atol=1e-3, err_msg=f"{a}->{b}")
                assert known[k] == (not (min(a, b) <= 9 < max(a, b)))
                if a == b:
                    np.testing.assert_allclose(offsets[k], 0, atol=1e-4)


def test_windows_place_their_events_as_they_say():
    segments = [(0, 0, 300)]
    cumulative = np.cumsum([300 - WINDOW - 1])
    seen = set()
    for i in range(300):
        rng = np.random.default_rng([0, i, 38])
        win = draw_window(rng, segments, cumulative, (320, 180), 128, bursts=1.0, flip=True)
        assert len(win.rows) == WINDOW and 0 <= win.rows.min() and win.rows.max() < 300
        steps = np.diff(win.rows)
        forward = steps.sum() > 0
        s = steps if forward else -steps
        for t, event in enumerate(win.events):
            seen.add(EVENTS[event])
            if event == DROP:
                assert s[t] == 2
            elif event == DUPLICATE:
                assert s[t] == 0
            else:
                assert s[t] == 1
        spoilt = np.flatnonzero(win.burst)
        assert not {0, WINDOW - 1} & set(spoilt.tolist())  # never a window's first or last frame
        for f in spoilt:  # both pairs beside a spoilt frame are events
            assert win.events[f - 1] > 0 and win.events[f] > 0
        assert 0 <= win.position[0] <= 320 - 128 and 0 <= win.position[1] <= 180 - 128
        again = draw_window(np.random.default_rng([0, i, 38]), segments, cumulative, (320, 180), 128, 1.0, True)
        assert np.array_equal(again.rows, win.rows) and np.array_equal(again.events, win.events)
    assert seen == set(EVENTS)


def test_the_objective_pulls_event_pairs_to_the_teacher_and_clean_pairs_to_the_base():
    cnn, _ = load_weights(CNN)
    net = carry_from(cnn)
    features = torch.randn(4, 6, net.config.embed).abs()
    with torch.no_grad():
        base = net.regressor(features).unflatten(-1, (4, 2))
    known = torch.ones(4, 6, dtype=torch.bool)
    events = torch.zeros(4, 6, dtype=torch.long)
    events[:, 3:5] = EVENTS.index("glare")
    teacher = base + 3.0  # 3 working px off the BASE in x and y on every pair
    batch = {"features": features, "teacher": teacher, "known": known, "events": events}
    with torch.no_grad():
        offsets, _, _ = net.carry(features, net.regressor(features))
        start = (offsets.unflatten(-1, (4, 2)) - base).norm(dim=-1).mean(-1)  # the head starts at the BASE
    assert float(start.max()) < 0.05
    terms = CarryObjective()(net, batch)
    # Clean pairs (4 of 6) cost almost nothing at the BASE; event pairs (2) cost Huber(3 sqrt 2).
    expected = (2 * (3.0 * np.sqrt(2) - 0.5) + 0.5 * float((start[:, [0, 1, 2, 5]] ** 2).mean()) * 4) / 6
    assert float(terms["total"]) == pytest.approx(expected, rel=1e-2)
    batch["known"][:, 4] = False  # an event pair the teacher does not know adds nothing
    terms = CarryObjective()(net, batch)
    assert float(terms["total"]) == pytest.approx((3.0 * np.sqrt(2) - 0.5) / 5, rel=1e-2)
    # With teacher_beyond, a clean pair whose BASE answer lies further than that from the teacher
    # (here 3 sqrt 2 = 4.24 working px) is pulled to the teacher too; nearer, the BASE's answer stays.
    assert float(CarryObjective(teacher_beyond=5.0)(net, batch)["total"]) == pytest.approx(float(terms["total"]), rel=1e-6)
    assert float(CarryObjective(teacher_beyond=4.0)(net, batch)["total"]) == pytest.approx(3.0 * np.sqrt(2) - 0.5, rel=2e-2)
    with pytest.raises(ValueError):
        CarryObjective(teacher_beyond=0.0)
    # With gate_weight, the gate is also told which answer to take: here the BASE is 4.24 px off
    # the teacher everywhere, so on the event pair the teacher knows (pair 3) the carried motion;
    # clean pairs where the BASE is that wrong are left to the blend's loss.
    with torch.no_grad():
        _, _, gate = net.carry(features, net.regressor(features))
    bce = -torch.log(gate[:, 3]).mean()
    assert float(bce) > 4.0  # the gate starts shut: sigmoid(GATE_START)
    supervised = CarryObjective(gate_weight=0.1)(net, batch)
    assert float(supervised["total"]) == pytest.approx(float(terms["total"]) + 0.1 * float(bce), rel=1e-4)
    # blend="spoilt": the pairs with a spoilt frame take the carried motion whole, as the
    # estimator's carry-blend=spoilt has them; the gate's own answer counts on the others only.
    spoilt = CarryObjective(blend="spoilt")(net, batch)
    assert float(spoilt["gate_event"]) == 1.0 and float(terms["gate_event"]) < 0.05
    assert float(spoilt["gate_clean"]) == pytest.approx(float(terms["gate_clean"]), rel=1e-6)
    with pytest.raises(ValueError):
        CarryObjective(blend="always")
    # correction_weight: an L1 price on the cell's correction where blend="spoilt" takes the carried
    # motion whole (pairs 3 and 4 of each window), and nowhere else.  A cell whose motion layer
    # answers a constant step c on x and y costs weight * c sqrt 2 (working px) more, exactly.
    free = CarryObjective(blend="spoilt")
    with torch.no_grad():
        net.carry.motion.bias.fill_(0.05)
    c = 0.05 * OFFSET_SCALE if net.carry.correction is None else net.carry.correction * float(np.tanh(0.05))
    priced = CarryObjective(blend="spoilt", correction_weight=0.5)
    assert float(priced(net, batch)["total"]) == pytest.approx(float(free(net, batch)["total"]) + 0.5 * c * np.sqrt(2), rel=1e-4)
    forced = CarryObjective(blend="spoilt", correction_weight=0.5, forcing=1.0)  # fed the teacher: the same step
    batch["draw"] = torch.zeros(4)
    assert float(forced(net, batch)["total"]) == pytest.approx(
        float(CarryObjective(blend="spoilt", forcing=1.0)(net, batch)["total"]) + 0.5 * c * np.sqrt(2), rel=1e-4)
    for bad in (dict(correction_weight=-0.1, blend="spoilt"), dict(correction_weight=0.5)):  # priced only where taken whole
        with pytest.raises(ValueError):
            CarryObjective(**bad)


# ----------------------------------------------------------------------------- the estimator


def test_the_estimator_runs_a_carry_head_as_lstm_and_restarted_every_pair_it_is_the_cnn(tmp_path):
    from mosaic_cli.model.checkpoint import save_weights

    cnn, meta = load_weights(CNN)
    net = carry_from(cnn)
    with torch.no_grad():  # a head that leans on its memory, so that a restart shows
        net.carry.gate[2].bias.fill_(0.0)
    path = tmp_path / "carry.safetensors"
    save_weights(path, net, variant="carry", int8=meta["int8"])
    flight = Flight(n_frames=20, frame_size=(640, 360), map_size=(2400, 1400), seed=4, step=12.0)

    def run(model, variant: str, **options) -> np.ndarray:
        config = LearnedConfig(refine=None, fallback="none", min_zncc=None, carry="none", **options)
        est = LearnedEstimator(model, {**meta, "variant": variant}, device="cpu", config=config)
        est.reset((640, 360))
        out = [e.H for f in flight.frames for e in est.feed(f)] + [e.H for e in est.finish()]
        return np.stack(out)

    carried, _ = load_weights(path)
    base = run(cnn, "base")
    restarted = run(carried, "carry", reset_every=1)
    np.testing.assert_allclose(restarted, base, rtol=1e-5, atol=1e-4)  # float32 sums of other batch sizes
    assert np.abs(run(load_weights(path)[0], "carry") - base).max() > 1e-3  # carried, it is not


def test_the_lstm_estimator_takes_carry_weights(tmp_path):
    from mosaic_cli.estimators.learned import make_learned_estimator
    from mosaic_cli.model.checkpoint import save_weights

    cnn, meta = load_weights(CNN)
    path = tmp_path / "carry.safetensors"
    save_weights(path, carry_from(cnn), variant="carry", int8=meta["int8"])
    est = make_learned_estimator("lstm", weights=path, device="cpu")
    assert est.model.head == "carry" and est.name == "carry"


# ----------------------------------------------------------------------------- the memory probe


@pytest.mark.slow
def test_the_shipped_sequence_model_carries_the_motion_in_its_state(tmp_path):
    """The memory probe of the shipped carry head (models/carry.safetensors) on a fresh flight with
    bursts (a procedural map the network never saw): restarting the state just before each burst
    makes the network-alone burst pairs clearly worse, while a restart at an ordinary place changes
    little.  The LSTM-REG-T of models/lstm.safetensors (its forget gate shut) fails it: the same
    failures both ways (24 and 24 of 29 burst pairs on this flight)."""
    import subprocess
    import sys

    from mosaic_cli.evaluate import memory_probe

    flight = tmp_path / "bursts.mp4"
    subprocess.run([sys.executable, "-m", "mosaic_cli", "simulate", "-p", "bursts", "-n", "240", "--size", "640x360",
                    "--seed", "11", "--preset", "veryfast", "-q", "-o", str(flight)], check=True, timeout=300)
    counts = memory_probe(flight, weights=CARRY).failures()
    assert counts["burst_pairs"] >= 20 and counts["ordinary_pairs"] >= 20
    carried, restarted = counts["burst_failed_carried"], counts["burst_failed_restarted"]
    assert restarted >= 1.5 * carried + 3, counts
    assert counts["ordinary_failed_restarted"] <= counts["ordinary_failed_carried"] + 0.1 * counts["ordinary_pairs"], counts


def test_the_image_cues_tell_a_washed_out_dark_or_flat_frame_and_reach_the_head():
    from mosaic_cli.model.network import CUES, patch_cues
    from mosaic_cli.train.bursts import DARK, FLAT, GLARE, spoil

    pairs = flight_patches(n=6)[0]  # (5, 2, P, P)
    clean = patch_cues(pairs)
    assert clean.shape == (5, CUES)
    frames = pairs[:, :1][None]  # the first patch of each pair as a 5-frame window (1, 5, 1, P, P)
    for code in (GLARE, DARK, FLAT):
        spoilt = spoil(frames, torch.full((1, 5), code), torch.full((1, 5), 0.05), torch.zeros(1, 5),
                       generator=torch.Generator().manual_seed(0))[0]
        cues = patch_cues(torch.cat([spoilt, pairs[:, 1:]], dim=1))
        assert bool((cues[:, 2] < clean[:, 2] / 3).all()), code  # the spoilt patch's contrast collapses
        torch.testing.assert_close(cues[:, [1, 3, 5]], clean[:, [1, 3, 5]])  # the other patch's cues stay
    cnn, _ = load_weights(CNN)
    net = HomographyNet(NetConfig(head="carry", carry_cues=CUES))
    net.start_as_carry(cnn)
    features = torch.zeros(5, net.config.embed)
    assert net.head_inputs(pairs, features).shape == (5, net.config.embed + CUES)
    assert cnn.head_inputs(pairs, features) is features


def test_a_head_saved_on_its_base_loads_whole_and_never_on_another_base(tmp_path):
    import shutil

    from mosaic_cli.errors import BadInput
    from mosaic_cli.model.checkpoint import read_metadata, save_on_base, save_weights

    cnn, meta = load_weights(CNN)
    net = carry_from(cnn)
    with torch.no_grad():
        net.carry.motion.weight.normal_()  # a head that is not its starting point
    shutil.copy(CNN, tmp_path / "cnn.safetensors")
    save_on_base(tmp_path / "carry.safetensors", net, tmp_path / "cnn.safetensors", "carry", int8=meta["int8"])
    assert (tmp_path / "carry.safetensors").stat().st_size < 0.1 * (tmp_path / "cnn.safetensors").stat().st_size
    loaded, loaded_meta = load_weights(tmp_path / "carry.safetensors")
    for key, value in net.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key
    assert loaded_meta["base"] == "cnn.safetensors" and loaded_meta["int8"] == meta["int8"]
    assert read_metadata(CARRY)["base"] == "cnn.safetensors"  # the shipped head is saved on the shipped BASE

    other = carry_from(cnn)
    with torch.no_grad():
        other.embed.bias.add_(1.0)
    with pytest.raises(ValueError):  # a model not made on that BASE cannot be saved on it
        save_on_base(tmp_path / "other.safetensors", other, tmp_path / "cnn.safetensors", "carry")
    save_weights(tmp_path / "cnn.safetensors", other, variant="base")  # the BASE beside it changes
    with pytest.raises(BadInput, match="another cnn.safetensors"):
        load_weights(tmp_path / "carry.safetensors")
    (tmp_path / "cnn.safetensors").unlink()
    with pytest.raises(BadInput, match="not beside it"):
        load_weights(tmp_path / "carry.safetensors")


# ----------------------------------------------------------------------------- the confirmed motion fed back (carry-state)


def test_the_head_continues_from_the_motion_it_is_told_was_confirmed():
    """``confirm`` at pair t: the next pairs are what the head makes of a state whose previous
    output is ``confirmed[t]`` (run from that state by hand), and pair t's own output is untouched."""
    torch.manual_seed(1)
    head = HomographyNet(NetConfig(head="carry")).carry.eval()
    with torch.no_grad():
        head.gate[2].bias.fill_(0.0)  # a head that leans on what it carries, so that it shows
        head.motion.weight.normal_(0.0, 0.05)
    T = 6
    features, cnn = torch.randn(2, T, head.code.in_features).abs(), torch.randn(2, T, 8) * 4.0
    confirmed = torch.randn(2, T, 8) * 4.0
    confirm = torch.zeros(2, T, dtype=torch.bool)
    confirm[0, 2] = True  # the first sequence's third pair was confirmed; the second, none
    with torch.no_grad():
        fed, state, _ = head(features, cnn, confirmed=confirmed, confirm=confirm)
        own, _, _ = head(features, cnn)
        _, (h, c, _), _ = head(features[:, :3], cnn[:, :3])
        by_hand, _, _ = head(features[:1, 3:], cnn[:1, 3:], (h[:, :1], c[:, :1], confirmed[None, :1, 2]))
    torch.testing.assert_close(fed[:, :3], own[:, :3], rtol=0, atol=0)
    torch.testing.assert_close(fed[0, 3:], by_hand[0], rtol=1e-6, atol=1e-5)
    torch.testing.assert_close(fed[1], own[1], rtol=0, atol=0)
    assert float((fed[0, 3] - own[0, 3]).abs().max()) > 0.5  # the fed motion mattered
    assert torch.equal(state[2][0, 0], fed[0, -1])  # a last pair not confirmed: its own output carried on


def test_teacher_forcing_feeds_the_teacher_after_the_pairs_the_frames_would_confirm():
    T = 8
    events = torch.zeros(3, T, dtype=torch.long)
    events[:, 2] = EVENTS.index("blur")
    events[:, 4] = DROP
    events[:, 6] = DUPLICATE
    known = torch.ones(3, T, dtype=torch.bool)
    known[:, 1] = False
    batch = {"teacher": torch.randn(3, T, 4, 2), "known": known, "events": events, "draw": torch.tensor([0.1, 0.6, 0.9])}
    forced = CarryObjective(forcing=0.5).forced(batch)
    expected = torch.tensor([True, False, False, True, True, True, True, True])  # not unknown, not spoilt
    assert torch.equal(forced["confirm"][0], expected)
    assert not forced["confirm"][1:].any()  # the windows not drawn (draw >= 0.5): their own output
    assert torch.equal(forced["confirmed"], batch["teacher"].flatten(-2))
    assert CarryObjective().forced(batch) == {}
    with pytest.raises(ValueError):
        CarryObjective(forcing=1.5)


def test_blown_glare_blows_out_a_share_of_the_glare_frames_and_leaves_every_other_draw_as_it_was():
    from mosaic_cli.train.bursts import GLARE, LEVELS

    segments, cumulative = [(0, 0, 300)], np.cumsum([300 - WINDOW - 1])
    glare = []
    for i in range(400):
        plain = draw_window(np.random.default_rng([0, i, 38]), segments, cumulative, (320, 180), 128, 1.0, True)
        blown = draw_window(np.random.default_rng([0, i, 38]), segments, cumulative, (320, 180), 128, 1.0, True,
                            blown_glare=0.5)
        for name in ("rows", "burst", "angle", "events"):  # the same windows, events and frames
            assert np.array_equal(getattr(plain, name), getattr(blown, name)), name
        other = plain.burst != GLARE
        assert np.array_equal(plain.level[other], blown.level[other])
        glare.extend(blown.level[plain.burst == GLARE].tolist())
        assert all(LEVELS[GLARE][0] <= v <= LEVELS[GLARE][1] for v in plain.level[plain.burst == GLARE])
    glare_levels = np.array(glare)
    assert len(glare_levels) > 100
    assert 0.35 < float((glare_levels == 0).mean()) < 0.65  # about half blown out
    assert glare_levels.max() <= LEVELS[GLARE][1] and glare_levels[glare_levels > 0].min() >= LEVELS[GLARE][0]


def test_turning_windows_retrace_their_steps_and_the_teacher_reverses_with_them():
    """A share of the windows turn back at a frame in their second half: the rows after it retrace
    the ones before, the pair after the turn is the inverse of the one before it (the motion flips
    from one pair to the next), and nothing else of the window changes."""
    segments, cumulative = [(0, 0, 300)], np.cumsum([300 - WINDOW - 1])
    rng = np.random.default_rng(5)
    H = np.repeat(np.eye(3)[None], 299, axis=0)
    H[:, 0, 2], H[:, 1, 2] = rng.uniform(-4, 4, 299), rng.uniform(-4, 4, 299)
    ok = np.ones(299, bool)
    turned = inverted = 0
    for i in range(200):
        plain = draw_window(np.random.default_rng([0, i, 38]), segments, cumulative, (320, 180), 128, 1.0, True)
        turn = draw_window(np.random.default_rng([0, i, 38]), segments, cumulative, (320, 180), 128, 1.0, True, turns=0.5)
        for name in ("burst", "level", "angle", "events"):
            assert np.array_equal(getattr(plain, name), getattr(turn, name)), name
        assert (turn.position, turn.left_right, turn.upside_down) == (plain.position, plain.left_right, plain.upside_down)
        changed = np.flatnonzero(plain.rows != turn.rows)
        if not len(changed):
            continue
        turned += 1
        k = int(changed[0]) - 1  # the frame it turns at
        assert k >= (WINDOW - 1) // 2 and plain.rows.min() <= turn.rows.min() and turn.rows.max() <= plain.rows.max()
        np.testing.assert_array_equal(turn.rows[k + 1:], 2 * plain.rows[k] - plain.rows[k + 1:])
        if turn.rows[k - 1] != turn.rows[k] and turn.rows[k + 1] == turn.rows[k - 1]:  # no drop or duplicate there
            offsets, known = teacher_offsets(turn, H, ok, (320, 180), 128)
            H_before = offsets_to_H(offsets[k - 1], turn.position)
            H_after = offsets_to_H(offsets[k], turn.position)
            np.testing.assert_allclose(H_after @ H_before, np.eye(3), atol=1e-6)
            inverted += 1
    assert 70 < turned < 130 and inverted > 30  # about half turn; most at a plain pair


def offsets_to_H(offsets: np.ndarray, position: tuple[int, int]) -> np.ndarray:
    from mosaic_cli.model.patches import offsets_to_homography

    H = offsets_to_homography(torch.from_numpy(offsets).double()[None], torch.tensor(position, dtype=torch.float64)[None], 128)[0]
    return H.numpy()


def test_blown_glare_by_burst_blows_out_whole_bursts():
    """Per burst, a burst of glare is white throughout or not at all (never a white frame beside a
    faint one, which no encoded flight shows), about half the bursts, with every other draw as it was."""
    from mosaic_cli.train.bursts import GLARE, LEVELS

    segments, cumulative = [(0, 0, 300)], np.cumsum([300 - WINDOW - 1])
    whole, mixed, multi = 0, 0, 0
    for i in range(600):
        plain = draw_window(np.random.default_rng([0, i, 38]), segments, cumulative, (320, 180), 128, 1.0, True)
        blown = draw_window(np.random.default_rng([0, i, 38]), segments, cumulative, (320, 180), 128, 1.0, True,
                            blown_glare=0.5, blown_by_burst=True)
        for name in ("rows", "burst", "angle", "events"):
            assert np.array_equal(getattr(plain, name), getattr(blown, name)), name
        other = plain.burst != GLARE
        assert np.array_equal(plain.level[other], blown.level[other])
        # runs of consecutive glare frames (two bursts of glare never touch in these windows' draws
        # often enough to matter; where they do, the run is counted as mixed only if it is)
        glare = np.flatnonzero(plain.burst == GLARE)
        for run in np.split(glare, np.flatnonzero(np.diff(glare) > 1) + 1) if len(glare) else []:
            levels = blown.level[run]
            if len(run) > 1:
                multi += 1
                mixed += int((levels == 0).any() and (levels > 0).any())
            whole += int((levels == 0).all())
            assert all(v == 0 or LEVELS[GLARE][0] <= v <= LEVELS[GLARE][1] for v in levels)
    assert multi > 50 and mixed <= 0.05 * multi  # (two adjoining bursts may differ)
    assert whole > 50


def _carry_estimator(net: HomographyNet, meta: dict, **options) -> LearnedEstimator:
    config = LearnedConfig(fallback="none", carry="network", **options)
    return LearnedEstimator(net, {**meta, "variant": "carry"}, device="cpu", config=config)


def _track(est: LearnedEstimator, flight: Flight) -> list:
    est.reset(flight.frame_size)
    return [e for f in flight.frames for e in est.feed(f)] + list(est.finish())


def test_carry_state_confirmed_puts_the_polished_motion_into_the_heads_state():
    """A head whose own answer is 2 working px off in x and y (its regressor's bias moved): the
    polish confirms the true motion, and with carry-state=confirmed the state's previous output
    is that motion's offsets at the patch (its corners moved by OpenCV), where with the default
    it stays the head's own answer."""
    cnn, meta = load_weights(CNN)
    net = carry_from(cnn)
    with torch.no_grad():
        net.regressor.bias.add_(2.0)
    flight = Flight(n_frames=18, frame_size=(640, 360), map_size=(2400, 1400), seed=4, step=6.0)
    scale = np.diag([0.5, 0.5, 1.0])  # 640 -> the 320 px working frame
    truth = scale @ flight.pairwise[-1] @ np.linalg.inv(scale)
    for polish_with in ("opencv", "torch"):  # one pair at a time, and the chunk's polish batched
        fed = _carry_estimator(net, meta, carry_state="confirmed", chunk=8, polish_with=polish_with)
        estimates = _track(fed, flight)
        assert estimates[-1].path == "learned" and fed.path_counts["learned"] == len(flight.frames) - 1
        x, y = (float(v) - 0.5 for v in fed.positions[0])  # the patch's outer corners, pixel centres on integers
        P = fed.patch
        corners = np.array([[x, y], [x + P, y], [x + P, y + P], [x, y + P]], np.float64)
        moved = cv2.perspectiveTransform(corners[None], fed._motion)[0]
        state = fed._state[2][0, 0].reshape(4, 2).double().numpy()
        np.testing.assert_allclose(state, moved - corners, atol=1e-3)  # exactly the confirmed motion
        true_offsets = cv2.perspectiveTransform(corners[None], truth)[0] - corners
        assert np.abs(state - true_offsets).max() < 0.5  # ...which the polish placed on the truth

    own = _carry_estimator(net, meta, chunk=8)
    _track(own, flight)
    own_state = own._state[2][0, 0].reshape(4, 2).double().numpy()
    assert np.abs(own_state - true_offsets).max() > 1.5  # the head's own answer, 2 px off


def test_carry_blend_spoilt_takes_the_carried_motion_whole_on_pairs_with_a_spoilt_frame():
    """carry-blend=spoilt: on a pair the estimator finds a spoilt frame in, the head's gate is 1.
    A fresh head (its correction still zero) then carries the confirmed motion exactly, as the
    velocity rule does, where its own gate (still shut) hands over the BASE's answer on the black
    frames.  Asked without carry-state=confirmed, it is one clear error."""
    from mosaic_cli.errors import BadInput

    cnn, meta = load_weights(CNN)
    net = carry_from(cnn)
    flight = Flight(n_frames=18, frame_size=(640, 360), map_size=(2400, 1400), seed=4, step=6.0)
    flight.frames[10] = np.zeros_like(flight.frames[10])  # pairs 9 and 10 touch a black frame
    rule = _track(LearnedEstimator(cnn, meta, device="cpu", config=LearnedConfig(fallback="none", carry="velocity")), flight)
    for threads in (1, 2):  # one thread decides each pair in turn; more check the pairs on a pool
        whole_est = _carry_estimator(net, meta, carry_state="confirmed", carry_blend="spoilt", chunk=8)
        gated_est = _carry_estimator(net, meta, carry_state="confirmed", chunk=8)
        whole_est.threads = gated_est.threads = threads
        whole, gated = _track(whole_est, flight), _track(gated_est, flight)
        assert [e.path for e in whole[9:11]] == ["carried"] * 2 == [e.path for e in rule[9:11]]
        for k in (9, 10):
            np.testing.assert_allclose(whole[k].H, rule[k].H, atol=1e-3)
            assert float(np.abs(gated[k].H - rule[k].H).max()) > 0.5
    with pytest.raises(BadInput, match="carry-state=confirmed"):
        LearnedConfig(carry="network", carry_blend="spoilt")
    with torch.no_grad():
        features, cnn_offsets = torch.randn(2, 3, net.config.embed).abs(), torch.randn(2, 3, 8)
        trust = torch.tensor([[False, True, True], [False, False, False]])
        out, _, gate = net.carry(features, cnn_offsets, trust=trust)
    assert torch.equal(gate[trust], torch.ones(2))
    torch.testing.assert_close(out[0, 2], out[0, 0])  # the carried motion (no correction yet) is the first answer


def test_carry_blend_spoilt_checks_a_spoilt_pair_from_what_the_base_reads_of_it():
    """carry-blend=spoilt: the frames of a pair with a spoilt frame are checked (polished,
    correlated) from the BASE's reading of them, as the rule's pipeline checks them, and not from
    the carried motion the head takes whole there (polished from it, a spoilt frame's residue
    pulled the polish onto false matches: models/README.md, run 18).  Here the BASE reads every
    pair 2 working px off; the polish confirms the true motion on the clean pairs, so the carried
    motion and the BASE's reading differ, and the head's spoilt pairs are checked from the very
    seeds the rule's pipeline over the same BASE checks them from."""
    cnn, meta = load_weights(CNN)
    with torch.no_grad():
        cnn.regressor.bias.add_(2.0)
    net = carry_from(cnn)
    flight = Flight(n_frames=18, frame_size=(640, 360), map_size=(2400, 1400), seed=4, step=6.0)
    flight.frames[10] = np.zeros_like(flight.frames[10])  # pairs 9 and 10 touch a black frame

    def spoilt_seeds(est: LearnedEstimator) -> tuple[list, list]:
        seen = []
        check = est._check

        def spy(prev, cur, seed, offsets_ok):
            if prev.spoilt or cur.spoilt:  # on whichever thread: each spoilt pair is checked once
                seen.append(np.array(seed))
            return check(prev, cur, seed, offsets_ok)

        est._check = spy  # type: ignore[method-assign]
        return seen, _track(est, flight)

    rule_seeds, rule = spoilt_seeds(LearnedEstimator(cnn, meta, device="cpu", config=LearnedConfig(fallback="none", carry="velocity"),
                                                     threads=1))
    assert len(rule_seeds) == 2
    for threads in (1, 2):
        est = _carry_estimator(net, meta, carry_state="confirmed", carry_blend="spoilt", chunk=8)
        est.threads = threads
        checked, whole = spoilt_seeds(est)
        assert len(checked) == 2
        in_order = sorted(checked, key=lambda H: min(float(np.abs(H - R).max()) for R in rule_seeds[:1]))  # (a pool's order varies)
        for seed, expected in zip(in_order, rule_seeds):
            np.testing.assert_allclose(seed, expected, atol=1e-4)
        scale = np.diag([0.5, 0.5, 1.0])  # 640 -> the 320 px working frame
        for k, seed in zip((9, 10), rule_seeds):
            assert whole[k].path == "carried" == rule[k].path
            np.testing.assert_allclose(whole[k].H, rule[k].H, atol=1e-3)  # the confirmed motion, carried...
            carried = scale @ whole[k].H @ np.linalg.inv(scale)
            assert float(corner_error(carried, seed, (320, 180))) > 1.0  # ...not the reading it was checked from


def test_carry_state_confirmed_is_the_same_on_any_number_of_threads_and_changes_no_other_head():
    cnn, meta = load_weights(CNN)
    net = carry_from(cnn)
    with torch.no_grad():
        net.carry.gate[2].bias.fill_(0.0)  # leaning on its memory: the fed state changes the seeds
    flight = Flight(n_frames=18, frame_size=(640, 360), map_size=(2400, 1400), seed=5, step=8.0)
    runs = []
    for threads in (1, 2):
        est = _carry_estimator(net, meta, carry_state="confirmed", chunk=8)
        est.threads = threads
        runs.append(np.stack([e.H for e in _track(est, flight)]))
    np.testing.assert_array_equal(runs[0], runs[1])
    for weights in (CNN, "models/lstm.safetensors"):  # no carry head: the option changes nothing
        model, model_meta = load_weights(weights)
        outputs = []
        for state in ("own", "confirmed"):
            est = LearnedEstimator(model, model_meta, device="cpu", config=LearnedConfig(carry_state=state))
            est.threads = 1
            outputs.append(np.stack([e.H for e in _track(est, flight)]))
        np.testing.assert_array_equal(outputs[0], outputs[1])


# ----------------------------------------------------------------------------- scripts/carry_ceiling.py


def test_carry_ceiling_scores_the_rules_from_the_true_past_motions(tmp_path):
    """scripts/carry_ceiling.py on a flight whose truth is known: a steady 4 px/frame translation
    that speeds up by 6 px a frame from pair 9, with frame 10 spoilt (pairs 9 and 10 touch it) and
    a dropped frame at 15 (placed by the frames: not scored).  From the true motions before pair
    9 (4 px each) the last one misses pair 9 (10 px) by 6 px and pair 10 (16 px) by 12; constant
    acceleration, from two steady motions, misses by as much; the mean of any k of them too."""
    import importlib.util
    import json
    import subprocess
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "carry_ceiling.py"
    spec = importlib.util.spec_from_file_location("carry_ceiling", path)
    assert spec is not None and spec.loader is not None
    ceiling = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ceiling)
    steps = [4.0] * 9 + [10.0, 16.0] + [4.0] * 9
    pairwise = [[[1, 0, dx], [0, 1, 0], [0, 0, 1]] for dx in steps]
    truth = {"size": [1280, 720], "pairwise": pairwise, "bursts": [{"frame": 10, "kind": "glare"}, {"frame": 15, "kind": "drop"}]}
    (tmp_path / "f.gt.json").write_text(json.dumps(truth))
    rows = ceiling.flight_rows(tmp_path / "f.gt.json")
    assert [r["pair"] for r in rows] == [9, 10]
    for row, miss in zip(rows, (6.0, 12.0)):
        for name in ("last", "mean 2", "mean 3", "mean 5", "accel"):
            assert row["errors"][name] == pytest.approx(miss)
    out = subprocess.run([sys.executable, str(path), str(tmp_path)], capture_output=True, text=True, check=True).stdout
    assert "2 spoilt pairs" in out and "last    (true past motions):    1 of 2 failed" in out
    # With a track: the rules from the motions it confirmed (its pair 8, placed 1 px off, and pair
    # 7 unconfirmed: skipped), and its own estimates (pair 9 exact, pair 10 carried at 5 px a frame).
    estimated = [row[:] for row in pairwise]
    estimated[8] = [[1, 0, 5.0], [0, 1, 0], [0, 0, 1]]
    estimated[10] = [[1, 0, 5.0], [0, 1, 0], [0, 0, 1]]
    paths = ["learned"] * 20
    paths[7], paths[10] = "failed", "carried"
    tracks = tmp_path / "tracks"
    tracks.mkdir()
    (tracks / "f.json").write_text(json.dumps({"pairwise": estimated, "path": paths}))
    rows = ceiling.flight_rows(tmp_path / "f.gt.json", tracks / "f.json")
    assert [r["tracked"]["last"] for r in rows] == [pytest.approx(5.0), pytest.approx(11.0)]
    assert [r["tracked"]["accel"] for r in rows] == [pytest.approx(4.0), pytest.approx(10.0)]  # 2 x 5 - 4 (pair 6)
    assert [r["track"] for r in rows] == [pytest.approx(0.0), pytest.approx(11.0)]
