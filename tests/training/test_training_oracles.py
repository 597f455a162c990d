"""SeqMatchNet training components (kernel rows, loss, gradients, miner, frame transform) against plain loops."""

import math

import numpy as np
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from seqvpr.data.ground_truth import Radius, ground_truth_within_radius
from seqvpr.data.traversal import Traversal
from seqvpr.models.seqmatchnet import FrameTransform, TransformConfig
from seqvpr.sequences.matching import aligned_sequence_distances, sequence_distance_rows
from seqvpr.sequences.windows import SequenceSpec, window_starts
from seqvpr.training.losses import sequence_triplet_loss, window_part
from seqvpr.training.mining import (
    MiningConfig,
    SequenceMiner,
    centre_frame_rows,
    mining_kernel,
    seqmatch_rows,
)
from tests import oracles
from tests.helpers import examples

FEW = settings(max_examples=examples(25), deadline=None)


def segment_ids(draw, n):
    return np.cumsum([0] + draw(st.lists(st.booleans(), min_size=n - 1, max_size=n - 1))).astype(np.int64)


def assert_rows_equal(fast, slow, tol=1e-9):
    fast = np.asarray(fast, dtype=np.float64)
    assert fast.shape == slow.shape
    assert (np.isinf(fast) == np.isinf(slow)).all()
    finite = np.isfinite(slow)
    np.testing.assert_allclose(fast[finite], slow[finite], rtol=tol, atol=tol)


# 1. kernel rows for scattered query windows --------------------------------------------------------------------


@st.composite
def scattered_rows(draw):
    n_q, n_r = draw(st.integers(1, 30)), draw(st.integers(1, 25))
    dim = draw(st.integers(1, 5))
    spec = SequenceSpec(
        draw(st.integers(1, 5)),
        draw(st.sampled_from(["centered", "causal"])),
        draw(st.sampled_from(["drop", "shift"])),
        draw(st.sampled_from([(1.0,), (1.0,), (1.0, 1.5)])),
    )
    q_seg, r_seg = segment_ids(draw, n_q), segment_ids(draw, n_r)
    with_window = [i for i in range(n_q) if oracles.window_start(q_seg, i, spec.length, spec.offset, spec.boundary) is not None]
    assume(with_window)
    frames = draw(st.lists(st.sampled_from(with_window), min_size=1, max_size=12))
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    return rng.normal(size=(n_q, dim)), rng.normal(size=(n_r, dim)), spec, q_seg, r_seg, frames


@FEW
@given(scattered_rows())
def test_sequence_distance_rows_match_loop_for_scattered_starts(problem):
    q, r, spec, q_seg, r_seg, frames = problem
    starts = np.array([oracles.window_start(q_seg, i, spec.length, spec.offset, spec.boundary) for i in frames])
    fast = sequence_distance_rows(torch.tensor(q), torch.tensor(r), spec, starts, r_seg)
    slow = np.minimum.reduce([
        oracles.sequence_distances(q, r, spec.length, spec.align, spec.boundary, q_seg, r_seg, v)
        for v in spec.velocities
    ])
    assert_rows_equal(fast.numpy(), slow[frames])


def test_sequence_distance_rows_of_no_windows_is_empty():
    rng = np.random.default_rng(0)
    out = sequence_distance_rows(
        torch.tensor(rng.normal(size=(6, 3))), torch.tensor(rng.normal(size=(5, 3))), SequenceSpec(3), np.zeros(0, np.int64)
    )
    assert tuple(out.shape) == (0, 5)


# 2. pairwise window distances ---------------------------------------------------------------------------------


@FEW
@given(
    st.lists(st.integers(1, 3), min_size=0, max_size=2),
    st.integers(1, 5),
    st.integers(1, 5),
    st.integers(0, 2**31 - 1),
)
def test_aligned_sequence_distances_match_loop(batch, length, dim, seed):
    rng = np.random.default_rng(seed)
    qw = rng.normal(size=(*batch, length, dim))
    rw = rng.normal(size=(*batch, length, dim))
    centre = int(rng.integers(0, length))
    fast = aligned_sequence_distances(torch.tensor(qw), torch.tensor(rw)).numpy()
    single = aligned_sequence_distances(torch.tensor(qw), torch.tensor(rw), slice(centre, centre + 1)).numpy()
    assert fast.shape == tuple(batch) == single.shape
    for index in np.ndindex(*batch):
        expected = oracles.window_distance(qw[index], rw[index])
        assert math.isclose(fast[index], expected, rel_tol=1e-12, abs_tol=1e-12)
        diff = qw[index][centre] - rw[index][centre]
        assert math.isclose(single[index], math.sqrt(float(diff @ diff)), rel_tol=1e-12, abs_tol=1e-12)


# 3. the triplet loss --------------------------------------------------------------------------------------------


@st.composite
def triplet_batches(draw):
    b, t = draw(st.integers(1, 4)), draw(st.integers(1, 8))
    length, dim = draw(st.integers(1, 5)), draw(st.integers(1, 6))
    align = draw(st.sampled_from(["centered", "causal"]))
    margin = draw(st.sampled_from([0.0, math.sqrt(0.1), 0.5, 2.0]))
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    windows = [rng.normal(size=(n, length, dim)) for n in (b, b, t)]
    owner = rng.integers(0, b, size=t)
    return (*windows, owner, margin, SequenceSpec(length, align))


@FEW
@given(triplet_batches(), st.sampled_from(["seqmatch", "single"]))
def test_sequence_triplet_loss_matches_loop(batch, method):
    q, p, n, owner, margin, spec = batch
    frames = window_part(method, spec.length, spec.offset)
    if method == "single":
        assert frames == slice(spec.offset, spec.offset + 1)
    loss = sequence_triplet_loss(
        torch.tensor(q), torch.tensor(p), torch.tensor(n), torch.as_tensor(owner), margin, frames
    )
    expected = oracles.triplet_loss(q, p, n, owner, margin, frames)
    assert loss.ndim == 0
    assert math.isclose(float(loss), expected, rel_tol=1e-9, abs_tol=1e-12)


# 4. gradients ---------------------------------------------------------------------------------------------------


def test_loss_gradient_is_finite_for_identical_query_and_positive():
    rng = np.random.default_rng(1)
    q = torch.tensor(rng.normal(size=(3, 4, 5)), requires_grad=True)
    positive = q.detach().clone()
    negatives = torch.tensor(rng.normal(size=(6, 4, 5)))
    owner = torch.tensor([0, 0, 1, 1, 2, 2])
    for frames in (None, slice(2, 3)):
        q.grad = None
        loss = sequence_triplet_loss(q, positive, negatives, owner, margin=10.0, frames=frames)
        loss.backward()
        assert torch.isfinite(q.grad).all()
        assert q.grad.abs().sum() > 0  # the negative term still pulls


def test_loss_gradient_through_transform_is_finite_with_zero_distance():
    model = FrameTransform(TransformConfig(6), seed=3)
    frames = torch.tensor(np.random.default_rng(2).normal(size=(2, 3, 6)), dtype=torch.float32)
    windows = model(frames)
    negatives = model(torch.flip(frames, dims=[0]))
    loss = sequence_triplet_loss(windows, model(frames), negatives, torch.tensor([0, 1]), margin=5.0)
    loss.backward()
    for parameter in model.parameters():
        assert parameter.grad is not None and torch.isfinite(parameter.grad).all()


@FEW
@given(st.integers(2, 8), st.integers(1, 4), st.integers(0, 2**31 - 1), st.sampled_from(["reference", "identity"]))
def test_transform_weight_and_bias_receive_gradients(dim, length, seed, init):
    rng = np.random.default_rng(seed)
    model = FrameTransform(TransformConfig(dim, init=init), seed=seed % 1000)
    q, p, n = (model(torch.tensor(rng.normal(size=(s, length, dim)), dtype=torch.float32)) for s in (2, 2, 4))
    loss = sequence_triplet_loss(q, p, n, torch.tensor([0, 1, 1, 0]), margin=10.0)  # every triplet active
    loss.backward()
    weight, bias = model.layers[0].weight.grad, model.layers[0].bias.grad
    assert torch.isfinite(weight).all() and torch.isfinite(bias).all()
    assert weight.abs().max() > 0
    assert bias.abs().max() > 0


# 5-7. mining ----------------------------------------------------------------------------------------------------

N_REF, N_QUERY, DIM = 60, 50, 8


@st.composite
def mining_problems(draw):
    spec = SequenceSpec(
        draw(st.integers(1, 5)), draw(st.sampled_from(["centered", "causal"])), draw(st.sampled_from(["drop", "shift"]))
    )
    split = draw(st.integers(10, N_REF - 10))
    r_seg = np.array([0] * split + [1] * (N_REF - split), dtype=np.int64)
    q_split = draw(st.sampled_from([None, 20, 35]))
    q_seg = np.zeros(N_QUERY, np.int64) if q_split is None else (np.arange(N_QUERY) >= q_split).astype(np.int64)
    mix = draw(st.sampled_from([0.0, 0.8, 1.0]))
    return (*descriptors(draw(st.integers(0, 2**31 - 1)), mix), spec, q_seg, r_seg)


def descriptors(seed, mix):
    """Random query/reference frames; with ``mix`` > 0 reference frame i resembles query frame i (so some
    queries have a clearly best positive and no margin-violating negative)."""
    rng = np.random.default_rng(seed)
    q, r = rng.normal(size=(N_QUERY, DIM)), rng.normal(size=(N_REF, DIM))
    r[:N_QUERY] = mix * q + (1.0 - 0.7 * mix) * r[:N_QUERY]
    return q, r


def make_miner(kernel, q, r, spec, q_seg, r_seg, config):
    query = Traversal.from_descriptors(q, "query", segment_ids=q_seg)
    reference = Traversal.from_descriptors(r, "reference", segment_ids=r_seg)
    positives = ground_truth_within_radius(query, reference, Radius(1, "frames"))
    near = ground_truth_within_radius(query, reference, Radius(3, "frames"))
    starts = window_starts(q_seg, spec.length, spec.offset, spec.boundary)
    return SequenceMiner(kernel, starts, positives, near, config)


def brute(q, r, spec, q_seg, r_seg, count=4):
    return oracles.hardest_negatives(q, r, q_seg, r_seg, spec.length, spec.offset, spec.boundary, 1, 3, count)


@FEW
@given(mining_problems())
def test_miner_returns_brute_force_hardest_negatives(problem):
    q, r, spec, q_seg, r_seg = problem
    miner = make_miner(seqmatch_rows(spec, r_seg), q, r, spec, q_seg, r_seg,
                       MiningConfig(negatives=4, pool=None, only_violating=False))
    triplets = miner.mine(torch.tensor(q), torch.tensor(r), np.arange(N_QUERY), np.random.default_rng(0))
    expected = brute(q, r, spec, q_seg, r_seg)
    got = {t.query: t for t in triplets}
    assert sorted(got) == [i for i, e in expected.items() if e is not None]
    for i, t in got.items():
        positive, d_p, hardest, d_n = expected[i]
        assert t.positive == positive
        assert t.negatives.tolist() == hardest
        assert math.isclose(t.positive_distance, d_p, rel_tol=1e-9, abs_tol=1e-12)
        np.testing.assert_allclose(t.negative_distances, d_n, rtol=1e-9, atol=1e-12)


@FEW
@given(mining_problems())
def test_miner_keeps_only_margin_violating_negatives(problem):
    q, r, spec, q_seg, r_seg = problem
    config = MiningConfig(negatives=4, pool=None, only_violating=True)
    miner = make_miner(seqmatch_rows(spec, r_seg), q, r, spec, q_seg, r_seg, config)
    triplets = miner.mine(torch.tensor(q), torch.tensor(r), np.arange(N_QUERY), np.random.default_rng(0))
    expected = brute(q, r, spec, q_seg, r_seg)
    got = {t.query: t for t in triplets}
    for i, e in expected.items():
        if e is None:
            assert i not in got
            continue
        positive, d_p, hardest, d_n = e
        violating = [j for j, d in zip(hardest, d_n) if d < d_p + config.margin]
        if i not in got:
            assert violating == [], f"query {i} skipped but {violating} violate the margin"
            continue
        t = got[i]
        assert t.positive == positive
        assert t.negatives.tolist() == violating
        assert (t.negative_distances < t.positive_distance + config.margin).all()


def test_margin_filter_both_keeps_and_skips():
    q, r = descriptors(7, 0.8)
    spec, q_seg, r_seg = SequenceSpec(3), np.zeros(N_QUERY, np.int64), (np.arange(N_REF) >= 30).astype(np.int64)
    config = MiningConfig(negatives=4, pool=None, only_violating=True)
    miner = make_miner(seqmatch_rows(spec, r_seg), q, r, spec, q_seg, r_seg, config)
    kept = {t.query for t in miner.mine(torch.tensor(q), torch.tensor(r), np.arange(N_QUERY), np.random.default_rng(0))}
    expected = brute(q, r, spec, q_seg, r_seg)
    violating = {i for i, e in expected.items() if e is not None and e[3][0] < e[1] + config.margin}
    minable = {i for i, e in expected.items() if e is not None}
    assert kept == violating
    assert 0 < len(kept) < len(minable)  # the example exercises both branches


def brute_force_kernel(spec, r_seg):
    def rows(query, reference, starts):
        out = oracles.window_rows(query.numpy(), reference.numpy(), list(starts), spec.length, spec.offset,
                                  spec.boundary, r_seg)
        return torch.tensor(out, dtype=query.dtype)

    return rows


@settings(max_examples=examples(10), deadline=None)
@given(mining_problems(), st.integers(0, 2**31 - 1))
def test_pooled_miner_with_injected_brute_force_kernel_is_identical(problem, seed):
    q, r, spec, q_seg, r_seg = problem
    config = MiningConfig(negatives=4, pool=10, only_violating=False)
    core = make_miner(seqmatch_rows(spec, r_seg), q, r, spec, q_seg, r_seg, config)
    slow = make_miner(brute_force_kernel(spec, r_seg), q, r, spec, q_seg, r_seg, config)
    core_rng, slow_rng = np.random.default_rng(seed), np.random.default_rng(seed)
    order = np.random.default_rng(seed + 1).permutation(N_QUERY)
    for epoch in range(2):  # the second epoch's pools include each query's cached negatives
        queries = order[: 20 + 15 * epoch]
        a = core.mine(torch.tensor(q), torch.tensor(r), queries, core_rng)
        b = slow.mine(torch.tensor(q), torch.tensor(r), queries, slow_rng)
        assert [t.query for t in a] == [t.query for t in b]
        assert a, "no triplets mined"
        for x, y in zip(a, b):
            assert x.positive == y.positive
            assert x.negatives.tolist() == y.negatives.tolist()
            assert math.isclose(x.positive_distance, y.positive_distance, rel_tol=1e-9, abs_tol=1e-12)
            np.testing.assert_allclose(x.negative_distances, y.negative_distances, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(core.cache_array(N_QUERY), slow.cache_array(N_QUERY))


@FEW
@given(mining_problems(), st.lists(st.integers(0, N_QUERY - 1), min_size=1, max_size=10))
def test_single_mining_uses_centre_frame_distances(problem, picks):
    q, r, spec, q_seg, r_seg = problem
    q_starts = window_starts(q_seg, spec.length, spec.offset, spec.boundary)
    starts = q_starts[[i for i in picks if q_starts[i] >= 0]]
    assume(len(starts))
    kernel = mining_kernel("single", spec, r_seg)
    fast = kernel(torch.tensor(q), torch.tensor(r), starts).numpy()
    slow = oracles.window_rows(q, r, list(starts), spec.length, spec.offset, spec.boundary, r_seg, centre_only=True)
    assert_rows_equal(fast, slow)
    fast_direct = centre_frame_rows(spec, r_seg)(torch.tensor(q), torch.tensor(r), starts).numpy()
    assert_rows_equal(fast_direct, slow)


# 8. the frame transform -----------------------------------------------------------------------------------------


@FEW
@given(st.integers(1, 12), st.integers(1, 10), st.integers(0, 2**31 - 1))
def test_identity_transform_is_normalization(dim, rows, seed):
    x = torch.tensor(np.random.default_rng(seed).normal(size=(rows, dim)) * 3.0, dtype=torch.float32)
    model = FrameTransform(TransformConfig(dim, init="identity"), seed=seed % 100)
    with torch.no_grad():
        out = model(x)
    expected = x / x.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(out, expected, rtol=0, atol=1e-6)


@FEW
@given(
    st.integers(1, 10),
    st.none() | st.integers(1, 10),
    st.lists(st.integers(1, 8), max_size=2),
    st.sampled_from(["reference", "identity"]),
    st.integers(0, 2**31 - 1),
)
def test_transform_outputs_have_unit_norm(in_dim, out_dim, hidden, init, seed):
    config = TransformConfig(in_dim, out_dim, tuple(hidden), init)
    model = FrameTransform(config, seed=seed % 1000)
    x = torch.tensor(np.random.default_rng(seed).normal(size=(2, 7, in_dim)), dtype=torch.float32)
    with torch.no_grad():
        out = model(x)
    assert out.shape == (2, 7, config.output_dim)
    norms = out.norm(dim=-1)
    nonzero = norms > 0  # a ReLU layer may zero a row entirely; everything else must be unit length
    if not hidden:
        assert nonzero.all()
    torch.testing.assert_close(norms[nonzero], torch.ones_like(norms[nonzero]), rtol=0, atol=1e-5)


def test_transform_initialization_is_seeded():
    config = TransformConfig(16, 8, (12,), "reference")
    a, b, c = FrameTransform(config, seed=5), FrameTransform(config, seed=5), FrameTransform(config, seed=6)
    for x, y, z in zip(a.parameters(), b.parameters(), c.parameters()):
        assert torch.equal(x, y)
        assert not torch.equal(x, z)
    # seeded independently of the global generator
    torch.manual_seed(123)
    d = FrameTransform(config, seed=5)
    torch.manual_seed(456)
    e = FrameTransform(config, seed=5)
    for x, y in zip(d.parameters(), e.parameters()):
        assert torch.equal(x, y)
