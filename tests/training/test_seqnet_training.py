"""SeqNet training: kernel, miner and loss against plain loops; learning, resume, determinism, model files, errors."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from seqvpr.data.ground_truth import Radius, ground_truth_within_radius
from seqvpr.synthetic.routes import generate_route
from seqvpr.data.traversal import Traversal
from seqvpr.sequences.descriptors import SeqNet, sequence_descriptors
from seqvpr.sequences.windows import SequenceSpec, window_starts
from seqvpr.models import files as ckpt
from seqvpr.models.seqmatchnet import save_seqmatchnet
from seqvpr.models.seqnet import load_seqnet, save_seqnet
from seqvpr.training.state import STATE_JSON
from seqvpr.training.mining import MiningConfig, SequenceMiner
from seqvpr.training.seqnet import (
    SeqNetSettings,
    frame_window_descriptors,
    seqnet_rows,
    seqnet_triplet_loss,
    train_seqnet,
)
from seqvpr.training.trainer import TrainingData
from tests.helpers import raises_one_line


def segmented_problem(seed=0, n_q=40, n_r=50, dim=6, length=4, boundary="drop"):
    """Random frames with segment breaks, a float64 SeqNet, and every frame's window start."""
    rng = np.random.default_rng(seed)
    q_seg = np.repeat([0, 1, 2], [15, 3, n_q - 18])  # the middle segment is shorter than L
    r_seg = np.repeat([0, 1], [20, n_r - 20])
    spec = SequenceSpec(length, boundary=boundary)
    torch.manual_seed(seed)
    model = SeqNet(dim, 5, w=2).double().eval()
    q = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(n_q, dim))), dim=1)
    r = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(n_r, dim))), dim=1)
    q_starts = window_starts(q_seg, length, spec.offset, spec.boundary)
    r_starts = window_starts(r_seg, length, spec.offset, spec.boundary)
    return model, q, r, q_starts, r_starts, length


def brute_rows(model, q, r, r_starts, length):
    """A plain kernel: each window's descriptor by itself, Euclidean distance in a loop, +inf without a window."""

    def rows(_query_feats, _reference_feats, starts):
        out = np.full((len(starts), len(r)), np.inf)
        with torch.no_grad():
            windows = {int(rs): model(r[rs : rs + length][None])[0] for rs in set(r_starts.tolist()) if rs >= 0}
            for i, s in enumerate(starts):
                dq = model(q[s : s + length][None])[0]
                for j, rs in enumerate(r_starts):
                    if rs >= 0:
                        out[i, j] = float(torch.linalg.norm(dq - windows[int(rs)]))
        return torch.tensor(out)

    return rows


@pytest.mark.parametrize("boundary", ["drop", "shift"])
def test_mining_kernel_equals_a_brute_force_loop(boundary):
    model, q, r, q_starts, r_starts, length = segmented_problem(boundary=boundary)
    with torch.no_grad():
        qf = frame_window_descriptors(model, q, q_starts, length)
        rf = frame_window_descriptors(model, r, r_starts, length)
    assert (qf[q_starts < 0] == 0).all()  # the placeholder
    starts = q_starts[q_starts >= 0]
    fast = seqnet_rows(q_starts, r_starts)(qf, rf, starts).numpy()
    slow = brute_rows(model, q, r, r_starts, length)(None, None, starts).numpy()
    assert (np.isinf(fast) == np.isinf(slow)).all()
    assert np.isinf(slow).any() == (boundary == "drop")  # with "shift" every reference frame has a window
    finite = np.isfinite(slow)
    np.testing.assert_allclose(fast[finite], slow[finite], rtol=1e-7, atol=1e-7)


def test_miner_with_an_injected_brute_force_kernel_gives_identical_triplets():
    model, q, r, q_starts, r_starts, length = segmented_problem(seed=3)
    q_pos = np.stack([np.arange(len(q)) * 1.0, np.zeros(len(q))], axis=1)
    r_pos = np.stack([np.arange(len(r)) * 0.8, np.zeros(len(r))], axis=1)
    qry = Traversal.from_descriptors(q.numpy(), "q", positions=q_pos)
    ref = Traversal.from_descriptors(r.numpy(), "r", positions=r_pos)
    positives = ground_truth_within_radius(qry, ref, Radius(2, "m"))
    near = ground_truth_within_radius(qry, ref, Radius(5, "m"))
    config = MiningConfig(negatives=4, pool=12, margin=0.5)
    with torch.no_grad():
        qf = frame_window_descriptors(model, q, q_starts, length)
        rf = frame_window_descriptors(model, r, r_starts, length)
    queries = np.arange(len(q))
    mined = []
    for kernel in (seqnet_rows(q_starts, r_starts), brute_rows(model, q, r, r_starts, length)):
        miner = SequenceMiner(kernel, q_starts, positives, near, config)
        rng = np.random.default_rng(11)
        mined.append([miner.mine(qf, rf, queries, rng) for _ in range(2)])  # the second round uses the cache
    for fast_round, slow_round in zip(*mined):
        assert len(fast_round) == len(slow_round) > 0
        for a, b in zip(fast_round, slow_round):
            assert (a.query, a.positive) == (b.query, b.positive)
            assert np.array_equal(a.negatives, b.negatives)
            np.testing.assert_allclose(a.negative_distances, b.negative_distances, rtol=1e-7, atol=1e-7)


def test_loss_equals_a_plain_computation():
    rng = np.random.default_rng(5)
    q, p, n = (torch.tensor(rng.normal(size=shape)) for shape in ((3, 4), (3, 4), (7, 4)))
    owner = torch.tensor([0, 0, 1, 1, 1, 2, 2])
    margin = 0.8
    terms = [max(float(torch.linalg.norm(q[b] - p[b])) - float(torch.linalg.norm(q[b] - n[t])) + margin, 0.0)
             for t, b in enumerate(owner.tolist())]
    assert float(seqnet_triplet_loss(q, p, n, owner, margin)) == pytest.approx(np.mean(terms), rel=1e-12)
    # the reference: TripletMarginLoss(reduction="sum") over every (q, p, n) divided by the number of negatives
    reference = torch.nn.TripletMarginLoss(margin=margin, p=2, eps=0.0, reduction="sum")(q[owner], p[owner], n) / 7
    assert float(seqnet_triplet_loss(q, p, n, owner, margin)) == pytest.approx(float(reference), rel=1e-9)


def route_data(seed=0):
    ref, qry = generate_route(n_frames=300, dim=32, seed=seed)
    return TrainingData(ref.slice_frames(0, 200), qry.slice_frames(0, 200), ref.slice_frames(200, 300),
                        qry.slice_frames(200, 300), Radius(5, "m"), Radius(20, "m"), Radius(5, "m"))


FAST = SeqNetSettings(SequenceSpec(5), epochs=3, batch_size=8, optimizer="adam", lr=3e-3, weight_decay=0.0,
                      negative_pool=None, seed=1)
SMALL = SeqNetSettings(SequenceSpec(4), w=2, out_dim=16, epochs=3, batch_size=8, negative_pool=30, lr=0.05,
                       lr_step=2, refresh_every=60, seed=7)


def test_short_training_lowers_the_loss_and_improves_validation_recall(tmp_path):
    result = train_seqnet(route_data(), FAST, tmp_path / "run")
    losses = [r.loss for r in result.history[1:]]
    assert losses[-1] < 0.7 * losses[0]
    assert result.best_recall[5] > result.history[0].recall[5]
    assert result.history[result.best_epoch].recall == result.best_recall
    assert len((tmp_path / "run" / "history.csv").read_text().splitlines()) == 5
    model, config = load_seqnet(tmp_path / "run")
    assert config["format"] == "seqvpr-seqnet" and config["epoch"] == result.best_epoch
    assert (config["in_dim"], config["out_dim"], config["w"], config["L"]) == (32, 32, 3, 5)


def last_state_weights(folder):
    state = ckpt.read_json(folder / STATE_JSON)
    return ckpt.read_tensors(folder / state["state_dir"] / ckpt.MODEL_FILE)


def test_resume_after_kill_gives_the_same_weights(tmp_path):
    data = route_data(1)
    whole = train_seqnet(data, SMALL, tmp_path / "whole")
    train_seqnet(data, replace(SMALL, epochs=1), tmp_path / "killed")
    resumed = train_seqnet(data, SMALL, tmp_path / "killed", resume=True)
    a, b = last_state_weights(tmp_path / "whole"), last_state_weights(tmp_path / "killed")
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert [r.loss for r in whole.history] == [r.loss for r in resumed.history]
    assert whole.best_epoch == resumed.best_epoch
    state = ckpt.read_json(tmp_path / "killed" / STATE_JSON)
    assert state["seqnet"] == {"in_dim": 32, "out_dim": 16, "w": 2}
    raises_one_line("cannot resume with w=3", train_seqnet, data, replace(SMALL, w=3), tmp_path / "killed",
                    resume=True)
    raises_one_line("use resume to continue it", train_seqnet, data, SMALL, tmp_path / "killed")


def test_training_is_deterministic_for_a_seed_and_varies_with_it(tmp_path):
    data = route_data(2)
    one = replace(SMALL, epochs=1)
    a = train_seqnet(data, one, tmp_path / "a")
    b = train_seqnet(data, one, tmp_path / "b")
    c = train_seqnet(data, replace(one, seed=8), tmp_path / "c")
    assert a.history[1].loss == b.history[1].loss
    assert a.history[1].loss != c.history[1].loss
    wa, wb = last_state_weights(tmp_path / "a"), last_state_weights(tmp_path / "b")
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


def test_saved_model_reloads_and_gives_identical_descriptors(tmp_path):
    torch.manual_seed(0)
    model = SeqNet(12, 7, w=3)
    x = np.random.default_rng(0).normal(size=(30, 12)).astype(np.float32)
    segments = np.repeat([0, 1], [18, 12])
    save_seqnet(tmp_path / "m", model, {"sequence": {"length": 5}})
    loaded, config = load_seqnet(tmp_path / "m")
    before = sequence_descriptors(x, segments, SequenceSpec(5), "seqnet", model)
    after = sequence_descriptors(x, segments, SequenceSpec(5), "seqnet", loaded)
    assert np.array_equal(before.vectors, after.vectors) and np.array_equal(before.rows, after.rows)
    assert config["L"] == 5 and config["out_dim"] == 7


def test_bad_input_is_one_line(tmp_path):
    raises_one_line("shorter than the temporal kernel width w=3", SeqNetSettings, SequenceSpec(2), w=3)
    raises_one_line("w must be an integer in [1, inf]", SeqNetSettings, w=0)
    raises_one_line("velocity 1 only", SeqNetSettings, SequenceSpec(5, velocities=(1.0, 1.5)))
    ref, qry = generate_route(n_frames=60, dim=8, seed=0)
    narrow = qry.with_descriptors(qry.descriptors[:, :6])
    raises_one_line("descriptor dimensions differ", TrainingData, ref, narrow, ref, qry, Radius(5, "m"),
                    Radius(20, "m"), Radius(5, "m"))
    raises_one_line("no such model folder", load_seqnet, tmp_path / "absent")
    save_seqnet(tmp_path / "m", SeqNet(4, 4, 2), {})
    (tmp_path / "m" / ckpt.MODEL_FILE).write_bytes(b"garbage")
    raises_one_line("its content is not what", load_seqnet, tmp_path / "m")
    from seqvpr.models.seqmatchnet import FrameTransform, TransformConfig

    save_seqmatchnet(tmp_path / "smn", FrameTransform(TransformConfig(4)), {})
    raises_one_line("not a seqvpr SeqNet config", load_seqnet, tmp_path / "smn")
    data = route_data()
    raises_one_line("longer than every segment", train_seqnet, data, replace(SMALL, sequence=SequenceSpec(150)),
                    tmp_path / "long")
