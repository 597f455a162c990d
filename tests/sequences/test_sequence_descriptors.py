"""Sequence descriptors against plain-loop formulas, window and segment rules, and faiss retrieval vs brute force."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.data.ground_truth import parse_radius
from seqvpr.data.traversal import Traversal
from seqvpr.evaluation.metrics import evaluate
from seqvpr.matchers.sequence import SequenceMatcher
from seqvpr.evaluation.ground_truth import ground_truth
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.descriptors import (
    FIXED_POOLINGS,
    SeqGeM,
    SeqNet,
    SequenceDescriptors,
    concatenation,
    delta,
    sequence_descriptors,
    smoothing,
    window_stack,
)
from seqvpr.sequences.retrieval import build_index, retrieve
from seqvpr.sequences.windows import SequenceSpec, segment_bounds, window_starts
from tests.helpers import examples, raises_one_line


def unit(v):
    return v / np.linalg.norm(v)


def random_windows(seed, n=4, length=5, dim=6):
    return np.random.default_rng(seed).normal(size=(n, length, dim))


# ---------------------------------------------------------------- descriptors vs plain formulas


@pytest.mark.parametrize("length", [1, 2, 3, 4, 5])
def test_smoothing_is_the_normalized_mean(length):
    x = random_windows(0, length=length)
    got = smoothing(torch.tensor(x)).numpy()
    for b in range(len(x)):
        total = np.zeros(x.shape[2])
        for t in range(length):
            total += x[b, t]
        np.testing.assert_allclose(got[b], unit(total / length), atol=1e-12)


@pytest.mark.parametrize("length", [1, 2, 3, 4, 5, 6, 7])
def test_delta_uses_the_reference_weights(length):
    x = random_windows(1, length=length)
    got = delta(torch.tensor(x)).numpy()
    for b in range(len(x)):
        total = np.zeros(x.shape[2])
        for t in range(length):
            weight = 1.0 / (length / 2)
            total += (-weight if t < length // 2 else weight) * x[b, t]
        np.testing.assert_allclose(got[b], unit(total), atol=1e-12)


def test_delta_odd_length_keeps_a_static_scene_even_length_cancels_it():
    frame = np.random.default_rng(2).normal(size=8)
    static5 = torch.tensor(np.tile(frame, (1, 5, 1)))
    static4 = torch.tensor(np.tile(frame, (1, 4, 1)))
    np.testing.assert_allclose(delta(static5).numpy()[0], unit(frame), atol=1e-12)  # weights sum to 2/L, not 0
    np.testing.assert_allclose(delta(static4).numpy()[0], 0.0, atol=1e-12)


@pytest.mark.parametrize("length", [1, 3, 4])
def test_concatenation_normalizes_frames_then_the_whole(length):
    x = random_windows(3, length=length)
    got = concatenation(torch.tensor(x)).numpy()
    for b in range(len(x)):
        parts = [unit(x[b, t]) for t in range(length)]
        np.testing.assert_allclose(got[b], unit(np.concatenate(parts)), atol=1e-12)
    assert got.shape == (len(x), length * x.shape[2])


@pytest.mark.parametrize(("length", "w"), [(5, 3), (5, 5), (10, 5), (4, 1), (3, 2)])
def test_seqnet_is_mean_of_explicit_conv_sums(length, w):
    torch.manual_seed(0)
    model = SeqNet(6, 4, w).double()
    weight = model.conv.weight.detach().numpy()  # [out, in, w]
    bias = model.conv.bias.detach().numpy()
    x = random_windows(4, length=length)
    got = model(torch.tensor(x)).detach().numpy()
    for b in range(len(x)):
        outputs = []
        for t in range(length - w + 1):
            y = bias.copy()
            for k in range(w):
                y = y + weight[:, :, k] @ x[b, t + k]
            outputs.append(y)
        np.testing.assert_allclose(got[b], unit(np.mean(outputs, axis=0)), atol=1e-12)


def test_s1_is_a_linear_map_then_l2():
    torch.manual_seed(1)
    model = SeqNet(6, 3, w=1).double()
    x = random_windows(5, length=1)
    got = model(torch.tensor(x)).detach().numpy()
    weight, bias = model.conv.weight.detach().numpy()[:, :, 0], model.conv.bias.detach().numpy()
    for b in range(len(x)):
        np.testing.assert_allclose(got[b], unit(weight @ x[b, 0] + bias), atol=1e-12)


def gem_loop(x, p, eps):
    """Per-dimension power mean over time of max(x, eps), by loops."""
    length, dim = x.shape
    out = np.zeros(dim)
    for d in range(dim):
        out[d] = (sum(max(x[t, d], eps) ** p for t in range(length)) / length) ** (1.0 / p)
    return out


@pytest.mark.parametrize("p", [1.0, 3.0, 4.5])
def test_seqgem_clamp_is_the_per_dimension_power_mean(p):
    model = SeqGeM(p=p).double()
    x = random_windows(6)
    got = model(torch.tensor(x)).detach().numpy()
    for b in range(len(x)):
        np.testing.assert_allclose(got[b], unit(gem_loop(x[b], p, 1e-6)), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("p", [1.0, 3.0])
def test_seqgem_signed_pools_positive_and_negative_parts(p):
    model = SeqGeM(p=p, mode="signed").double()
    x = random_windows(7)
    got = model(torch.tensor(x)).detach().numpy()
    assert got.shape == (len(x), 2 * x.shape[2])
    for b in range(len(x)):
        expected = np.concatenate([gem_loop(x[b], p, 1e-6), gem_loop(-x[b], p, 1e-6)])
        np.testing.assert_allclose(got[b], unit(expected), rtol=1e-9, atol=1e-12)


def test_seqgem_signed_keeps_the_sign_that_clamp_loses():
    x = random_windows(8, n=1)
    flipped = np.where(x < 0, 2 * x, x)  # only the negative entries change
    clamp, signed = SeqGeM().double(), SeqGeM(mode="signed").double()
    with torch.no_grad():
        assert float((clamp(torch.tensor(x)) - clamp(torch.tensor(flipped))).abs().max()) == 0.0
        assert float((signed(torch.tensor(x)) - signed(torch.tensor(flipped))).abs().max()) > 1e-3
    # at p = 1 the difference of the halves is the temporal mean (up to eps): the sign survives pooling
    halves = SeqGeM(p=1.0, mode="signed").double()(torch.tensor(x)).detach().numpy()[0]
    dim = x.shape[2]
    np.testing.assert_allclose(unit(halves[:dim] - halves[dim:]), unit(x[0].mean(0)), atol=1e-5)


@pytest.mark.parametrize("mode", ["clamp", "signed"])
def test_seqgem_p_is_learnt(mode):
    torch.manual_seed(0)
    model = SeqGeM(mode=mode)
    x = torch.randn(8, 5, 16)
    target = torch.randn(8, 16 if mode == "clamp" else 32)
    loss = (model(x) * target).sum()
    loss.backward()
    grad = model.p.grad
    assert grad is not None and bool(torch.isfinite(grad).all()) and float(grad.abs().max()) > 0
    before = model.p.detach().clone()
    torch.optim.SGD(model.parameters(), lr=0.1).step()
    assert not torch.equal(model.p.detach(), before)


# ---------------------------------------------------------------- windows, segments, boundary rule


@st.composite
def layouts(draw):
    n = draw(st.integers(1, 40))
    breaks = draw(st.lists(st.booleans(), min_size=n - 1, max_size=n - 1))
    segments = np.cumsum([0] + [int(b) for b in breaks])
    length = draw(st.integers(1, 8))
    align = draw(st.sampled_from(["centered", "causal"]))
    return segments, length, align


@settings(max_examples=examples(150), deadline=None)
@given(layouts())
def test_windows_respect_segments_and_boundary_rule(layout):
    segments, length, align = layout
    n = len(segments)
    frames = torch.tensor(np.stack([np.arange(n), segments], axis=1), dtype=torch.float64)
    seg_start, seg_end = segment_bounds(segments)
    per_boundary = {}
    for boundary in ("drop", "shift"):
        spec = SequenceSpec(length, align, boundary)
        starts = window_starts(segments, length, spec.offset, boundary)
        if not (starts >= 0).any():
            raises_one_line("longer than every segment", window_stack, frames, segments, spec)
            per_boundary[boundary] = None
            continue
        windows, rows = window_stack(frames, segments, spec)
        np.testing.assert_array_equal(rows, np.flatnonzero(starts >= 0))
        assert windows.shape == (len(rows), length, 2)
        for window, row in zip(windows.numpy(), rows):
            covered = window[:, 0].astype(int)
            np.testing.assert_array_equal(covered, np.arange(starts[row], starts[row] + length))
            assert (window[:, 1] == segments[row]).all()  # never crosses a segment break
            assert row in covered
            if boundary == "drop":
                assert covered[0] == row - spec.offset  # the natural window, unmoved
        per_boundary[boundary] = rows
    fits = (seg_end - seg_start) >= length
    if per_boundary["shift"] is not None:
        np.testing.assert_array_equal(per_boundary["shift"], np.flatnonzero(fits))  # shift keeps every frame
    if per_boundary["drop"] is not None:
        assert set(per_boundary["drop"]) <= set(per_boundary["shift"])


def test_sequence_descriptors_batches_and_input_types_agree_with_window_stack():
    rng = np.random.default_rng(9)
    x = rng.normal(size=(60, 12))
    segments = np.repeat([0, 1, 2], [25, 3, 32])
    spec = SequenceSpec(4, "centered", "shift")
    frames = torch.nn.functional.normalize(torch.tensor(x, dtype=torch.float32), dim=1)
    windows, rows = window_stack(frames, segments, spec)
    torch.manual_seed(0)
    models = {"seqnet": SeqNet(12, 5, 3), "seqgem": SeqGeM(mode="signed")}
    for method in (*FIXED_POOLINGS, "seqnet", "seqgem"):
        model = models.get(method)
        expected = {"smoothing": smoothing, "delta": delta, "concat": concatenation}.get(method, model)(windows)
        whole = sequence_descriptors(x, segments, spec, method, model)
        small = sequence_descriptors(torch.tensor(x), segments, spec, method, model, batch_size=7)
        np.testing.assert_array_equal(whole.rows, rows)
        assert whole.vectors.dtype == np.float32 and whole.n_frames == 60
        np.testing.assert_allclose(whole.vectors, expected.detach().numpy(), atol=1e-6)
        np.testing.assert_allclose(small.vectors, whole.vectors, atol=1e-6)
        assert whole.has_window.sum() == 57  # the 3-frame segment has no 4-frame window
    assert models["seqgem"].training  # the caller's training mode is restored


def test_seqgem_default_model_and_clamp_output_dimension():
    x = np.random.default_rng(10).normal(size=(20, 8))
    out = sequence_descriptors(x, None, SequenceSpec(5), "seqgem")
    assert out.vectors.shape == (16, 8)
    assert (out.vectors >= 0).all()


# ---------------------------------------------------------------- retrieval


def brute_force(query: SequenceDescriptors, reference: SequenceDescriptors, k: int):
    d = np.linalg.norm(query.vectors[:, None, :].astype(np.float64) - reference.vectors[None, :, :], axis=2)
    order = np.argsort(d, axis=1, kind="stable")[:, :k]
    return reference.rows[order], np.take_along_axis(d, order, axis=1)


@pytest.mark.parametrize(("seed", "k"), [(0, 1), (1, 5), (2, 40), (3, 500)])
def test_retrieval_equals_brute_force(seed, k):
    rng = np.random.default_rng(seed)
    spec = SequenceSpec(3, "centered", "drop")
    q_seg = np.repeat([0, 1, 2], [30, 2, 28])
    r_seg = np.repeat([0, 1], [50, 40])
    query = sequence_descriptors(rng.normal(size=(60, 16)), q_seg, spec, "smoothing")
    reference = sequence_descriptors(rng.normal(size=(90, 16)), r_seg, spec, "smoothing")
    top = retrieve(query, reference, k)
    kept = min(k, len(reference.vectors))
    assert top.indices.shape == (60, kept) and top.indices.dtype == np.int64 and top.distances.dtype == np.float64
    expected_rows, expected_dist = brute_force(query, reference, kept)
    np.testing.assert_array_equal(top.indices[query.rows], expected_rows)
    np.testing.assert_allclose(top.distances[query.rows], expected_dist, atol=1e-4)
    missing = ~query.has_window
    assert missing.sum() == 2 + 2 + 2  # segment ends and the 2-frame segment
    assert (top.indices[missing] == -1).all() and np.isinf(top.distances[missing]).all()
    np.testing.assert_array_equal(top.has_window, query.has_window)
    again = retrieve(query, reference, k, index=build_index(reference.vectors))
    np.testing.assert_array_equal(again.indices, top.indices)
    np.testing.assert_array_equal(again.distances, top.distances)


def test_hnsw_is_reproducible_and_close_to_exact():
    rng = np.random.default_rng(4)
    query = sequence_descriptors(rng.normal(size=(80, 16)), None, SequenceSpec(3), "smoothing")
    reference = sequence_descriptors(rng.normal(size=(300, 16)), None, SequenceSpec(3), "smoothing")
    exact = retrieve(query, reference, 5)
    first, second = retrieve(query, reference, 5, kind="hnsw"), retrieve(query, reference, 5, kind="hnsw")
    np.testing.assert_array_equal(first.indices, second.indices)
    rows = query.rows
    assert np.mean(first.indices[rows, 0] == exact.indices[rows, 0]) >= 0.95


def test_smoothing_l1_retrieval_equals_single_image_matching():
    rng = np.random.default_rng(11)
    reference_frames, query_frames = rng.normal(size=(120, 24)), rng.normal(size=(70, 24))
    r_seg, q_seg = np.repeat([0, 1], [60, 60]), np.repeat([0, 1, 2], [20, 1, 49])
    spec = SequenceSpec(1)
    top = retrieve(
        sequence_descriptors(query_frames, q_seg, spec, "smoothing"),
        sequence_descriptors(reference_frames, r_seg, spec, "smoothing"),
        5,
    )
    reference = Traversal.from_descriptors(reference_frames, "ref", segment_ids=r_seg)
    query = Traversal.from_descriptors(query_frames, "qry", segment_ids=q_seg)
    kernel = SequenceMatcher(MatchSettings(spec, k=5)).topk(reference, query).topk
    np.testing.assert_array_equal(top.indices[:, 0], kernel.indices[:, 0])
    np.testing.assert_allclose(top.distances, kernel.distances, atol=1e-4)
    np.testing.assert_array_equal(top.has_window, kernel.has_window)
    gt = ground_truth(reference, query, parse_radius("2f"))
    scores = evaluate(top.indices, top.distances, top.has_window, gt, (1, 5))
    assert scores.queries_evaluated + scores.queries_excluded == len(query)


def test_evaluate_counts_frames_without_a_window():
    rng = np.random.default_rng(12)
    frames = rng.normal(size=(50, 8))
    traversal = Traversal.from_descriptors(frames, "t")
    descriptors = sequence_descriptors(frames, None, SequenceSpec(5), "delta")
    top = retrieve(descriptors, descriptors, 3)
    gt = ground_truth(traversal, traversal, parse_radius("0f"))
    scores = evaluate(top.indices, top.distances, top.has_window, gt, (1,))
    assert scores.excluded_no_window == 4
    assert scores.recall[1] == 1.0  # every window finds itself


# ---------------------------------------------------------------- errors


def test_bad_input_gives_one_line_errors():
    x = np.random.default_rng(13).normal(size=(30, 8))
    spec = SequenceSpec(5)
    raises_one_line("not known", sequence_descriptors, x, None, spec, "seqvlad")
    raises_one_line("needs a model", sequence_descriptors, x, None, spec, "seqnet")
    raises_one_line("takes no model", sequence_descriptors, x, None, spec, "smoothing", SeqNet(8, 4))
    raises_one_line(
        "shorter than the temporal kernel", sequence_descriptors, x, None, SequenceSpec(3), "seqnet", SeqNet(8, 4, w=5)
    )
    raises_one_line("expects 16-D", sequence_descriptors, x, None, spec, "seqnet", SeqNet(16, 4))
    raises_one_line("shorter than the temporal kernel", SeqNet(8, 4, w=5), torch.zeros(2, 3, 8))
    raises_one_line("expects 8-D", SeqNet(8, 4), torch.zeros(2, 5, 6))
    bad = x.copy()
    bad[17, 3] = np.nan
    raises_one_line("frame row 17", sequence_descriptors, bad, None, spec, "smoothing")
    raises_one_line("velocity 1", sequence_descriptors, x, None, SequenceSpec(5, velocities=(1.0, 1.5)), "delta")
    raises_one_line("longer than every segment", sequence_descriptors, x, np.arange(30) // 3, spec, "delta")
    raises_one_line("segment_ids", sequence_descriptors, x, np.zeros(29), spec, "delta")
    raises_one_line("[N, D]", sequence_descriptors, x[0], None, spec, "delta")
    raises_one_line("mode", SeqGeM, mode="abs")
    a = sequence_descriptors(x, None, spec, "smoothing")
    b = sequence_descriptors(x, None, spec, "concat")
    raises_one_line("dimensions differ", retrieve, a, b, 3)
    raises_one_line("at least 1", retrieve, a, a, 0)
    raises_one_line("not known", retrieve, a, a, 3, kind="ivf")
    raises_one_line("index holds", retrieve, a, a, 3, index=build_index(a.vectors[:5]))
