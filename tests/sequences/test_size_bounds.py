"""The library's size bounds (issue 28): velocities counted before they are made, -L against the segments, the
filter's steps; each one line naming the option and its limit."""

from __future__ import annotations

import numpy as np
import pytest

from seqvpr.errors import SeqvprError
from seqvpr.sequences.filter import MAX_STEP, FilterSettings
from seqvpr.sequences.seqslam import velocity_grid
from seqvpr.sequences.windows import MAX_VELOCITIES, SequenceSpec, check_length, parse_velocities


def test_a_velocity_range_is_made_up_to_the_bound_and_refused_past_it():
    assert len(parse_velocities("0.01:10:0.01")) == MAX_VELOCITIES
    assert parse_velocities("0.8:1.2:0.1") == (0.8, 0.9, 1.0, 1.1, 1.2)
    with pytest.raises(SeqvprError, match=f"velocities '0.5:2:1e-7': 15000001 velocities, at most {MAX_VELOCITIES}"):
        parse_velocities("0.5:2:1e-7")


@pytest.mark.parametrize("text", ["1e300", "0.8,nan", "0.5:inf:1", "0,1", "-1", "99:101:1"])
def test_a_velocity_out_of_range_is_one_line(text):
    with pytest.raises(SeqvprError, match="^velocities"):  # a Python caller's argument; the CLI's --velocities
        parse_velocities(text)


def test_the_spec_itself_refuses_too_many_velocities():
    with pytest.raises(SeqvprError, match="at most 1000"):
        SequenceSpec(5, velocities=tuple(np.linspace(0.5, 2, MAX_VELOCITIES + 1)))


def test_the_cone_and_hybrid_grid_is_bounded():
    assert len(velocity_grid(SequenceSpec(41, velocities=(0.5, 2.0)))) == 31  # k = 10..40 over h = 20
    with pytest.raises(SeqvprError, match="trajectories, at most 1000"):
        velocity_grid(SequenceSpec(41, velocities=(0.5, 100.0)))


def test_a_length_longer_than_every_segment_names_l_and_the_longest():
    segments = np.r_[np.zeros(7, int), np.ones(12, int)]
    check_length(12, segments, "query q.npz")
    with pytest.raises(SeqvprError, match=r"seq_len 13: longer than every segment of query q.npz \(longest segment: 12"):
        check_length(13, segments, "query q.npz")


def test_the_filter_steps_are_bounded():
    FilterSettings(max_step=MAX_STEP)
    with pytest.raises(SeqvprError, match=f"max_step {MAX_STEP + 1} is above {MAX_STEP}"):
        FilterSettings(max_step=MAX_STEP + 1)
