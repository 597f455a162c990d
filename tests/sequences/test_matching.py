"""The matching kernel against the plain-loop oracle, over random shapes, lengths, segments and policies."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.errors import SeqvprError
from seqvpr.sequences.matching import (
    BLOCK_BYTES, block_shape, frame_distances, reference_rows, sequence_distance_matrix, sequence_topk, unit_rows,
)
from seqvpr.sequences.windows import SequenceSpec
from tests import oracles
from tests.helpers import examples


@st.composite
def problems(draw):
    n_q = draw(st.integers(1, 24))
    n_r = draw(st.integers(1, 24))
    dim = draw(st.integers(1, 6))
    length = draw(st.integers(1, 7))
    align = draw(st.sampled_from(["centered", "causal"]))
    boundary = draw(st.sampled_from(["drop", "shift"]))
    q_seg = np.cumsum([0] + draw(st.lists(st.booleans(), min_size=n_q - 1, max_size=n_q - 1)))
    r_seg = np.cumsum([0] + draw(st.lists(st.booleans(), min_size=n_r - 1, max_size=n_r - 1)))
    velocities = draw(st.sampled_from([(1.0,), (1.0, 1.5), (0.8, 1.0, 1.2)]))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n_q, dim))
    r = rng.normal(size=(n_r, dim))
    return q, r, SequenceSpec(length, align, boundary, velocities), q_seg, r_seg


def oracle_matrix(q, r, spec, q_seg, r_seg):
    mats = [oracles.sequence_distances(q, r, spec.length, spec.align, spec.boundary, q_seg, r_seg, v) for v in spec.velocities]
    return np.minimum.reduce(mats)


def assert_same(fast, slow, tol, atol=None):
    fast = np.asarray(fast, dtype=np.float64)
    assert (np.isinf(fast) == np.isinf(slow)).all()
    finite = np.isfinite(slow)
    np.testing.assert_allclose(fast[finite], slow[finite], rtol=tol, atol=tol if atol is None else atol)


@settings(max_examples=examples(150), deadline=None)
@given(problems(), st.booleans(), st.sampled_from([torch.float32, torch.float64]))
def test_matrix_matches_loop(problem, inplace, dtype):
    q, r, spec, q_seg, r_seg = problem
    d = frame_distances(torch.tensor(q, dtype=dtype), torch.tensor(r, dtype=dtype))
    fast = sequence_distance_matrix(d, spec, q_seg, r_seg, inplace=inplace)
    # float32: sqrt(2 - 2 dot) turns the GEMM's ~1e-7 rounding of a near-1 dot into up to ~sqrt(4e-7) = 6e-4 near 0
    single = dtype == torch.float32
    assert_same(fast.numpy(), oracle_matrix(q, r, spec, q_seg, r_seg), 1e-4 if single else 1e-9, 1e-3 if single else None)


@settings(max_examples=examples(100), deadline=None)
@given(problems(), st.integers(1, 6), st.integers(1, 5000))
def test_blocked_topk_matches_full_matrix(problem, k, budget_rows):
    q, r, spec, q_seg, r_seg = problem
    slow = oracle_matrix(q, r, spec, q_seg, r_seg)
    budget = 8 * len(r) * 2 * (budget_rows % 40 + 2 * spec.length)
    try:
        top = sequence_topk(torch.tensor(q), torch.tensor(r), spec, k, q_seg, r_seg, memory_budget=budget)
    except SeqvprError as error:
        assert "longer than every segment" in str(error)
        return
    for i in range(len(q)):
        row = slow[i]
        expected = np.sort(row)[: top.indices.shape[1]]
        got = top.distances[i]
        assert_same(got, expected, 1e-9)
        ok = top.indices[i] >= 0
        assert_same(got[ok], row[top.indices[i][ok]], 1e-9)  # GEMM distances: absolute error near zero


@settings(max_examples=examples(100), deadline=None)
@given(problems(), st.integers(1, 6), st.integers(1, 40))
def test_reference_chunks_give_the_unchunked_topk(problem, k, chunk):
    q, r, spec, q_seg, r_seg = problem
    try:
        whole = sequence_topk(torch.tensor(q), torch.tensor(r), spec, k, q_seg, r_seg)
    except SeqvprError:
        return
    chunked = sequence_topk(torch.tensor(q), torch.tensor(r), spec, k, q_seg, r_seg, chunk=chunk)
    assert_same(chunked.distances, whole.distances, 1e-12)
    finite = np.isfinite(whole.distances)
    slow = oracle_matrix(q, r, spec, q_seg, r_seg)
    rows = np.nonzero(finite)[0]
    assert_same(slow[rows, chunked.indices[finite]], whole.distances[finite], 1e-9)


def test_a_memmapped_reference_is_read_in_chunks_with_the_same_result(tmp_path):
    rng = np.random.default_rng(3)
    reference = rng.standard_normal((3000, 16)).astype(np.float32)
    query = torch.tensor(rng.standard_normal((40, 16)).astype(np.float32))
    np.save(tmp_path / "r.npy", reference)
    mapped = np.load(tmp_path / "r.npy", mmap_mode="r")
    segments = np.repeat(np.arange(6), 500)
    spec = SequenceSpec(5, boundary="shift", velocities=(0.8, 1.0, 1.25))
    whole = sequence_topk(query, torch.tensor(reference), spec, 7, None, segments)
    budget = 2 * 4 * 60 * 1200  # 40 query rows (+ halo) by about 1,000 reference columns
    chunked = sequence_topk(query, mapped, spec, 7, None, segments, memory_budget=budget)
    np.testing.assert_array_equal(chunked.indices, whole.indices)
    np.testing.assert_allclose(chunked.distances, whole.distances, rtol=1e-6)


def test_block_shape_keeps_blocks_efficient_and_within_the_budget():
    spec = SequenceSpec(5)
    assert block_shape(1000, 5000, spec, 4, 2 * 1024**3) == (1000, 5000)  # small: one block
    for in_memory in (True, False):
        rows, columns = block_shape(1000, 10**6, spec, 4, 2 * 1024**3, in_memory=in_memory)
        assert rows == 1000 and columns >= 8192  # a large reference is chunked, all queries in one GEMM
        assert 2 * 4 * (rows + 8) * (columns + 10) <= BLOCK_BYTES
    rows, columns = block_shape(1000, 10**6, spec, 4, 100_000)  # a tiny budget still fits
    assert 2 * 4 * (rows + 8) * (columns + 10) <= 100_000
    with pytest.raises(SeqvprError, match="too small"):
        block_shape(10, 10, spec, 4, 100)


def test_fused_and_strided_agree_on_a_large_matrix():
    rng = np.random.default_rng(0)
    d = torch.tensor(rng.random((300, 257)), dtype=torch.float32)
    for length in (1, 2, 5, 20):
        spec = SequenceSpec(length)
        strided = sequence_distance_matrix(d.clone(), spec, inplace=False)
        fused = sequence_distance_matrix(d.clone(), spec, inplace=True)
        assert_same(fused.numpy(), strided.numpy().astype(np.float64), 1e-5)


def test_frame_distances_never_nan_for_identical_unit_vectors():
    generator = torch.Generator().manual_seed(0)
    x = torch.nn.functional.normalize(torch.randn(500, 128, generator=generator), dim=1)
    d = frame_distances(x, x)
    assert torch.isfinite(d).all()
    # 2 - 2<x, x> cancels to float32 rounding (~1e-6), whose square root is ~1e-3
    assert d.diagonal().max() < 3e-3
    assert (frame_distances(x.double(), x.double()).diagonal() < 1e-5).all()


def test_frame_distance_gradient_finite_at_zero_distance():
    x = torch.randn(4, 8, generator=torch.Generator().manual_seed(0)).requires_grad_()
    frame_distances(x, x.detach()).sum().backward()
    assert torch.isfinite(x.grad).all()


def test_dimension_mismatch_is_one_line_error():
    with pytest.raises(SeqvprError, match="dimensions differ"):
        frame_distances(torch.zeros(3, 4), torch.zeros(3, 5))


def test_sequence_longer_than_every_segment():
    with pytest.raises(SeqvprError, match="longer than every segment"):
        sequence_topk(torch.zeros(4, 2), torch.zeros(10, 2), SequenceSpec(5), 1)


@pytest.mark.parametrize("kind", ["array", "memmap", "tensor"])
@pytest.mark.parametrize("index", [slice(2, 7), np.array([0, 5, 3, 9])])
def test_reference_rows_are_the_indexed_rows_in_the_likes_dtype(tmp_path, kind, index):
    rows = np.random.default_rng(0).standard_normal((10, 4)).astype(np.float32)
    if kind == "memmap":
        reference = np.lib.format.open_memmap(tmp_path / "r.npy", mode="w+", dtype=np.float16, shape=rows.shape)
        reference[:] = rows
        rows = np.asarray(reference, np.float32)
    else:
        reference = torch.from_numpy(rows) if kind == "tensor" else rows
    got = reference_rows(reference, index, torch.zeros(0, dtype=torch.float64))
    assert got.dtype == torch.float64
    np.testing.assert_array_equal(got.numpy(), rows[index].astype(np.float64))


def test_reference_rows_index_a_device_tensor_where_it_lies():
    """A reference already on a device (meta here: NumPy cannot read it, as it cannot read a CUDA tensor) is indexed
    on that device, slice or row numbers, never through NumPy (what broke adaptive matching on CUDA)."""
    reference, like = torch.empty((10, 4), device="meta"), torch.empty(0, device="meta")
    assert reference_rows(reference, np.array([1, 3, 8]), like).shape == (3, 4)
    assert reference_rows(reference, slice(2, 5), like).device.type == "meta"
