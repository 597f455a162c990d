"""The recent past a loop may not come from: parsed with its unit, and the eligible prefix of every frame equal to a
plain loop over earlier frames, for frames, seconds and metres, over several sessions."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from seqvpr.data.exclusion import Exclusion, eligible_limits, parse_exclusion, travelled
from tests.helpers import raises_one_line
from tests.oracles import eligible_limit


@pytest.mark.parametrize("text, value, unit", [("30s", 30, "s"), ("200f", 200, "f"), ("50m", 50, "m"),
                                               ("2.5 frames", 2.5, "f"), ("0s", 0, "s")])
def test_an_exclusion_reads_its_number_and_unit(text, value, unit):
    assert parse_exclusion(text) == Exclusion(value, unit)


@pytest.mark.parametrize("text", ["30", "30x", "-5f", "f", "", "nanm"])
def test_an_exclusion_without_a_known_unit_or_negative_is_one_line(text):
    raises_one_line("exclude", parse_exclusion, text)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 40), st.integers(1, 3), st.sampled_from(["f", "s", "m"]), st.floats(0, 6),
       st.integers(0, 2**31 - 1))
def test_eligible_limits_are_the_plain_loops(n, n_sessions, unit, value, seed):
    rng = np.random.default_rng(seed)
    sessions = np.sort(rng.integers(0, n_sessions, n))
    stamps = np.cumsum(rng.uniform(0, 2, n))
    positions = np.cumsum(rng.normal(size=(n, 2)), axis=0)
    limits = eligible_limits(Exclusion(value, unit), sessions, stamps, positions)
    clock = stamps if unit == "s" else travelled(positions, sessions)
    expected = [eligible_limit(sessions, clock, i, value, unit) for i in range(n)]
    np.testing.assert_array_equal(limits, expected)
    assert (np.diff(limits) >= 0).all()


def test_seconds_need_timestamps_and_metres_positions():
    sessions = np.zeros(5, int)
    raises_one_line("needs timestamps", eligible_limits, Exclusion(3, "s"), sessions, None, None, "run.npz")
    raises_one_line("needs positions", eligible_limits, Exclusion(3, "m"), sessions, None, None, "run.npz")
