"""A query's frames one at a time: the prepared row against ``unit_rows``, and the one-frame distance pass against
the matching kernel's, bit for bit, over random shapes."""

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.matchers.rows import frame_row
from seqvpr.sequences.frame_pass import FrameRow, ReferenceBlocks
from seqvpr.sequences.matching import distances_to_reference, unit_rows
from tests.helpers import examples, raises_one_line


@settings(max_examples=examples(300), deadline=None)
@given(st.integers(1, 600), st.floats(-30, 30), st.integers(0, 2**32 - 1),
       st.sampled_from(["normal", "zero", "one", "nan", "inf"]))
def test_a_prepared_row_is_unit_rows_bit_for_bit(dim, exponent, seed, kind):
    """The localiser's normalisation of one frame (compiled passes and torch's norm, into a reused row) equals
    ``unit_rows`` exactly, at any scale, NaN and infinity where unit_rows has them."""
    rng = np.random.default_rng(seed)
    values = {"normal": rng.standard_normal(dim) * 10.0**exponent, "zero": np.zeros(dim),
              "one": np.eye(1, dim, int(rng.integers(dim)))[0] * 10.0**exponent}.get(kind, rng.standard_normal(dim))
    if kind in ("nan", "inf"):
        values[int(rng.integers(dim))] = np.nan if kind == "nan" else -np.inf
    vector = torch.from_numpy(values.astype(np.float32))
    expected = unit_rows(vector, dim=0)
    reused = FrameRow.of(rng.standard_normal(dim))  # a row that held another frame before
    for got in (FrameRow.empty(dim).set_unit(vector.numpy()).vector, reused.set_unit(vector.numpy()).vector):
        assert torch.equal(got.isnan(), expected.isnan())
        assert torch.equal(got.nan_to_num(7.0), expected.nan_to_num(7.0))
    assert reused.finite() == bool(torch.isfinite(vector).all())


@settings(max_examples=examples(60), deadline=None)
@given(st.integers(1, 3000), st.integers(1, 40), st.integers(1, 5), st.booleans(), st.integers(0, 2**31 - 1))
def test_one_frames_distances_are_the_kernels_block_for_block(n, dim, blocks, coded, seed):
    """``distances_into`` over the rows in blocks (views made once for float32 rows; rows read and converted a
    block at a time for stored ones, float16 here) equals ``distances_to_reference`` over the same blocks, bit for
    bit (a matrix product over other blocks may round the last bit otherwise)."""
    rng = np.random.default_rng(seed)
    rows = rng.standard_normal((n, dim)).astype(np.float16 if coded else np.float32)
    reference = ReferenceBlocks(rows, columns=max(1, -(-n // blocks)))
    frame = FrameRow.of(rng.standard_normal(dim))
    got = reference.distances_into(frame, np.full(n, np.nan, np.float32))
    expected = distances_to_reference(frame.row, rows, reference.norms, reference.columns)[0]
    np.testing.assert_array_equal(got, expected)


def test_a_frame_of_another_size_is_one_line_and_leaves_the_row_as_it_was():
    row = frame_row(np.arange(4, dtype=np.float32))
    before = row.numbers.copy()
    raises_one_line("a frame of 3 values for a row of 4", frame_row, np.ones(3), None, True, row)
    raises_one_line("one descriptor [D]", frame_row, np.ones((2, 2)), None, True, row)
    np.testing.assert_array_equal(row.numbers, before)
    np.testing.assert_array_equal(row.numbers, unit_rows(torch.arange(4.0), dim=0).numpy())
