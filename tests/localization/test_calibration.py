"""The calibrated threshold against a brute-force search over every candidate threshold."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.localization.calibration import find_threshold, precision_at
from tests.helpers import raises_one_line


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([0.1, 0.2, 0.3, 0.5, 0.9]), st.booleans()), min_size=1, max_size=30),
       st.sampled_from([0.5, 0.8, 0.99, 1.0]))
def test_the_threshold_is_the_lowest_that_reaches_the_target(pairs, target):
    scores, correct = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
    found = find_threshold(scores, correct, target)
    meeting = [t for t in sorted(set(scores)) if precision_at(scores, correct, t)[0] >= target]
    if not meeting:
        assert not found.reached and (scores < found.threshold).all()
        return
    assert found.reached and found.threshold == meeting[0]
    precision, recall = precision_at(scores, correct, found.threshold)
    assert abs(found.precision - precision) < 1e-12 and abs(found.recall - recall) < 1e-12


def test_bad_targets_and_empty_calibrations_are_one_line():
    raises_one_line("--target-precision must be in (0, 1]", find_threshold, np.ones(3), np.ones(3, bool), 1.5)
    raises_one_line("no frame of the calibration traversal", find_threshold, np.zeros(0), np.zeros(0, bool), 0.9)
