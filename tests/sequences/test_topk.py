"""The one top-K rule (by distance, ties to the lower row, empty entries last) against a plain sort: the dense scan,
the candidate merge, any chunking and any sharding give the same list; uniqueness against a loop."""

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.sequences.topk import TopKMerge, best_k, merge_topks, other_place, rank_order, uniqueness_ratio
from seqvpr.results import TopK
from tests import oracles
from tests.helpers import examples


def sorted_oracle(values: np.ndarray, k: int) -> list[int]:
    """The plain-loop definition: finite entries sorted by (value, row), the first k rows."""
    return [j for _, j in sorted((float(v), j) for j, v in enumerate(values) if np.isfinite(v))[:k]]


def rows_of(picked: np.ndarray) -> list[int]:
    return [int(j) for j in picked if j >= 0]


tied_matrices = st.tuples(st.integers(1, 8), st.integers(1, 40), st.integers(0, 2**32 - 1)).map(
    lambda a: (a[0], _tied(a[1], a[2])))


def _tied(width: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    values = rng.integers(0, 4, size=(5, width)).astype(np.float64)  # many ties
    values[rng.random(values.shape) < 0.2] = np.inf
    return values


@settings(max_examples=examples(60), deadline=None)
@given(tied_matrices, st.data())
def test_scan_and_merge_keep_the_sorted_topk_under_any_chunking(case, data):
    k, values = case
    cuts = sorted(set(data.draw(st.lists(st.integers(1, values.shape[1] - 1), max_size=6)))) if values.shape[1] > 1 else []
    bounds = [0, *cuts, values.shape[1]]
    for scan in (True, False):
        merged = TopKMerge(len(values), k)
        for lo, hi in zip(bounds, bounds[1:]):
            merged.push_columns(torch.tensor(values[:, lo:hi]).contiguous(), lo, scan=scan)
        top = merged.result(np.ones(len(values), bool))
        for i in range(len(values)):
            assert rows_of(top.indices[i]) == sorted_oracle(values[i], k)


@settings(max_examples=examples(60), deadline=None)
@given(tied_matrices, st.integers(1, 5), st.integers(0, 2**32 - 1))
def test_merging_shards_in_any_order_is_the_whole_topk(case, shards, seed):
    k, values = case
    rng = np.random.default_rng(seed)
    owner = rng.integers(0, shards, values.shape[1])  # any split of the rows, not only runs
    parts = []
    for shard in rng.permutation(shards):
        columns = np.flatnonzero(owner == shard)
        rows = np.broadcast_to(columns, (len(values), len(columns)))
        parts.append(TopK(np.array(rows), values[:, columns], np.ones(len(values), bool)))
    top = merge_topks(parts, k)
    assert top.indices.shape == (len(values), k)
    for i in range(len(values)):
        assert rows_of(top.indices[i]) == sorted_oracle(values[i], k)
        assert np.isinf(top.distances[i][top.indices[i] < 0]).all()


@settings(max_examples=examples(60), deadline=None)
@given(st.lists(st.sampled_from([0.5, 1.0, 2.0, np.inf]), min_size=1, max_size=30), st.integers(1, 8))
def test_best_k_of_a_dense_vector_is_the_sorted_list(values, k):
    values = np.array(values)
    rows, best = best_k(values, k)
    assert rows_of(rows) == sorted_oracle(values, k)
    assert len(rows) == min(k, len(values))
    np.testing.assert_array_equal(best, np.sort(values)[: min(k, len(values))])


@settings(max_examples=examples(60), deadline=None)
@given(st.lists(st.floats(0.01, 5.0), min_size=1, max_size=25), st.integers(0, 6))
def test_uniqueness_ratio_is_one_minus_best_over_the_best_elsewhere(values, exclusion):
    values = np.array(values)
    best = int(np.argmin(values))
    elsewhere = [v for j, v in enumerate(values) if abs(j - best) > exclusion]
    expected = 1.0 if not elsewhere else max(0.0, 1.0 - values[best] / min(elsewhere))
    rows, ranked = best_k(values, 2 * exclusion + 2)  # enough to hold the best other place
    assert abs(uniqueness_ratio(rows, ranked, exclusion) - expected) < 1e-12


@settings(max_examples=examples(200), deadline=None)
@given(st.lists(st.tuples(st.integers(-1, 30), st.sampled_from([0.0, 0.25, 0.5, 1.0, 3.0, np.inf, np.nan])),
                max_size=12), st.integers(0, 5))
def test_uniqueness_ratio_is_the_plain_loop_on_any_ranked_list(entries, exclusion):
    """The compiled score equals the plain loop on any list: empty rows, infinite, NaN and zero distances."""
    rows = np.array([r for r, _ in entries], dtype=np.int64)
    values = np.array([v for _, v in entries], dtype=np.float64)
    assert uniqueness_ratio(rows, values, exclusion) == oracles.uniqueness(rows, values, exclusion)
    assert uniqueness_ratio(list(rows), list(values), exclusion) == oracles.uniqueness(rows, values, exclusion)


def test_other_place_skips_the_best_ones_neighbors_and_empty_entries():
    indices = np.array([[10, 11, 9, 30], [5, -1, 6, 7], [3, 4, 2, 1]])
    distances = np.array([[0.1, 0.2, 0.3, 0.4], [0.1, np.inf, 0.2, 0.3], [0.1, 0.2, 0.3, 0.4]])
    np.testing.assert_array_equal(other_place(indices, distances, 2), [3, -1, -1])
    np.testing.assert_array_equal(other_place(indices, distances, 1), [3, 3, 3])
    assert uniqueness_ratio(np.array([-1]), np.array([np.inf]), 1) == 0.0
    assert uniqueness_ratio(indices[2], distances[2], 5) == 1.0


@settings(max_examples=examples(60), deadline=None)
@given(tied_matrices)
def test_the_compiled_tie_rule_ranks_as_rank_order_bit_for_bit(case):
    """``_fused.enter_ranked`` (through which every compiled top-K enters, rows met in row order) against
    ``rank_order`` (the numpy definition): the same rows and the same distances, ties included."""
    from seqvpr.sequences._fused import enter_ranked

    k, values = case
    for row_values in values:
        best, where = np.full(k, np.inf), np.full(k, -1, np.int64)
        for r, v in enumerate(row_values):
            if v < best[-1]:
                enter_ranked(v, r, best, where)
        rows = np.arange(len(row_values))
        ranked = rank_order(rows, row_values, k)
        expected = np.where(np.isfinite(row_values[ranked]), rows[ranked], -1)
        np.testing.assert_array_equal(where[: len(expected)], expected)
        np.testing.assert_array_equal(best[: len(expected)], np.where(expected >= 0, row_values[ranked], np.inf))
