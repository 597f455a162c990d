"""The graph matcher's min-marginals against every path by a plain loop, and its best path on a clean diagonal."""

from __future__ import annotations

import itertools

import numpy as np
import torch
from hypothesis import given, settings, strategies as st

from seqvpr.sequences.graph import GraphSettings, graph_topk, path_costs
from seqvpr.sequences.windows import segment_bounds
from tests.helpers import examples

HIDDEN = -1


def allowed(a: int, b: int, low: int, fanout: int, r_seg: np.ndarray) -> bool:
    """From state a to state b at the next query frame of one segment."""
    if a == HIDDEN or b == HIDDEN:
        return True
    return low <= b - a <= fanout and r_seg[a] == r_seg[b]


def brute_force(d, q_seg, r_seg, low, fanout, hidden):
    n_q, n_r = d.shape
    best = np.full((n_q, n_r), np.inf)
    starts, ends = segment_bounds(q_seg)
    for s in np.unique(starts):
        e = ends[s]
        for states in itertools.product([HIDDEN, *range(n_r)], repeat=e - s):
            if not all(allowed(a, b, low, fanout, r_seg) for a, b in zip(states, states[1:])):
                continue
            cost = sum(hidden if x == HIDDEN else d[s + i, x] for i, x in enumerate(states))
            for i, x in enumerate(states):
                if x != HIDDEN:
                    best[s + i, x] = min(best[s + i, x], cost)
    return best / (ends - starts)[:, None]


@settings(max_examples=examples(30), deadline=None)
@given(seed=st.integers(0, 9999), n_q=st.integers(1, 4), n_r=st.integers(1, 4), low=st.integers(0, 1),
       extra=st.integers(0, 1), breaks=st.booleans(), hidden=st.floats(0.05, 1.0))
def test_min_marginals_equal_every_path_by_a_plain_loop(seed, n_q, n_r, low, extra, breaks, hidden):
    fanout = low + extra
    rng = np.random.default_rng(seed)
    d = rng.random((n_q, n_r))
    q_seg = np.sort(rng.integers(0, 2, n_q)) if breaks else np.zeros(n_q, np.int64)
    r_seg = np.sort(rng.integers(0, 2, n_r)) if breaks else np.zeros(n_r, np.int64)
    np.testing.assert_allclose(path_costs(d, q_seg, r_seg, fanout, hidden, low),
                               brute_force(d, q_seg, r_seg, low, fanout, hidden), rtol=1e-12)


def test_a_route_driven_with_a_stop_and_a_jump_is_followed():
    rng = np.random.default_rng(0)
    reference = torch.nn.functional.normalize(torch.from_numpy(rng.standard_normal((60, 32))), dim=1)
    truth = np.r_[np.arange(10, 20), [20] * 5, np.arange(21, 41, 2), np.arange(45, 55)]  # stop, fast, skip
    query = reference[torch.as_tensor(truth)] + 0.3 * torch.from_numpy(rng.standard_normal((len(truth), 32)))
    top = graph_topk(query, reference, 3, np.zeros(len(truth), int), np.zeros(60, int), GraphSettings(fanout=2, min_step=0))
    assert (top.indices[:, 0] == truth).mean() > 0.95
