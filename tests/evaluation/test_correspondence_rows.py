"""The correspondences CSV's rows, found with one ground-truth lookup, equal a plain per-pair loop."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import scipy.sparse as sp
from hypothesis import given, settings, strategies as st

from seqvpr.data.ground_truth import GroundTruth
from seqvpr.evaluation.predictions import correspondence_rows
from tests.helpers import examples


def _loop_rows(result, q_rows, r_rows, gt) -> list[list]:
    """The oracle: pair by pair, one ground-truth lookup each."""
    rows = []
    for i in range(len(q_rows)):
        for position in range(q_rows.shape[1]):
            q, r = int(q_rows[i, position]), int(r_rows[i, position])
            if q < 0 or r < 0:
                continue
            correct = str(int(gt.contains(np.array([q]), np.array([r]))[0])) if gt.has_positive()[q] else ""
            rows.append([int(result.query.frame_index[i]), position, int(result.query.frame_index[q]),
                         int(result.reference.frame_index[r]), correct])
    return rows


@settings(max_examples=examples(30), deadline=None)
@given(seed=st.integers(0, 9999), n_query=st.integers(1, 30), n_ref=st.integers(1, 30), length=st.integers(1, 6))
def test_correspondence_rows_equal_a_plain_loop(seed, n_query, n_ref, length):
    rng = np.random.default_rng(seed)
    positives = rng.random((n_query, n_ref)) < 0.2
    positives[rng.random(n_query) < 0.3] = False  # queries without a positive get an empty "correct"
    gt = GroundTruth(sp.csr_array(positives))
    q_rows = rng.integers(-1, n_query, (n_query, length))
    r_rows = rng.integers(-1, n_ref, (n_query, length))
    result = SimpleNamespace(query=SimpleNamespace(frame_index=rng.permutation(n_query) + 100),
                             reference=SimpleNamespace(frame_index=rng.permutation(n_ref) + 7))
    got = correspondence_rows(result, (q_rows, r_rows), gt)
    assert got == _loop_rows(result, q_rows, r_rows, gt)
