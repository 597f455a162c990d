"""Windows against the oracle."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.sequences.windows import window_starts
from tests import oracles
from tests.helpers import examples


@settings(max_examples=examples(200), deadline=None)
@given(st.lists(st.booleans(), max_size=30), st.integers(1, 8), st.integers(0, 7), st.sampled_from(["drop", "shift"]))
def test_window_starts_match_oracle(breaks, span, offset, boundary):
    offset = min(offset, span - 1)
    segments = np.cumsum([0] + breaks)
    fast = window_starts(segments, span, offset, boundary)
    for i in range(len(segments)):
        expected = oracles.window_start(list(segments), i, span, offset, boundary)
        assert fast[i] == (-1 if expected is None else expected)
