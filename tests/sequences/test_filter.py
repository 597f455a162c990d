"""The topological filter against a plain-loop forward pass, its behaviour on routes (tracking, stops, kidnapping),
and the offline pass against stepping by hand."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.sequences.filter import FilterSettings, TopologicalFilter, distance_scale, filter_topk
from seqvpr.sequences.matching import reference_squared_norms
from tests.helpers import examples, raises_one_line


def oracle_step(belief, distances, segments, settings, scale):
    """One forward step by loops: move within the segment (clamped at its ends), floor, likelihood, normalise."""
    n = len(belief)
    steps = range(settings.min_step, settings.max_step + 1)
    moved = np.zeros(n)
    for r in range(n):
        start = min(j for j in range(n) if segments[j] == segments[r] and all(segments[m] == segments[r] for m in range(j, r + 1)))
        end = max(j for j in range(n) if segments[j] == segments[r] and all(segments[m] == segments[r] for m in range(r, j + 1)))
        for step in steps:
            moved[min(max(r + step, start), end)] += belief[r] / len(steps)
    moved = moved * (1 - settings.floor) + settings.floor / n
    post = moved * np.exp(-(distances - distances.min()) / scale)
    return post / post.sum()


@settings(max_examples=examples(60), deadline=None)
@given(st.integers(2, 15), st.integers(-2, 1), st.integers(0, 3), st.floats(0.0, 0.2), st.integers(0, 2**31 - 1))
def test_a_step_equals_the_loop_forward_pass(n, low, span, floor, seed):
    rng = np.random.default_rng(seed)
    segments = np.sort(rng.integers(0, 3, n))
    settings = FilterSettings(low, low + span, floor, 1.0, 1)
    filt = TopologicalFilter(segments, 0.3, settings)
    belief = np.full(n, 1.0 / n)
    for _ in range(3):
        d = rng.random(n)
        belief = oracle_step(belief, d, segments, settings, 0.3)
        np.testing.assert_allclose(filt.step(d), belief, rtol=1e-10, atol=1e-15)


def route_distances(true_frames, n, rng, noise=0.3):
    """Frame distances of a query at ``true_frames`` (-1: off the map) to an n-frame map: 0 at the true frame."""
    rows = []
    for t in true_frames:
        d = 1.0 + noise * rng.random(n)
        if t >= 0:
            d[t] = 0.2
        rows.append(d)
    return rows


def test_the_filter_follows_stops_and_speed_changes_and_recovers_after_a_kidnapping():
    rng = np.random.default_rng(1)
    path = [*range(0, 30), *[30] * 10, *range(30, 90, 2), *range(200, 240)]  # go, stop, go fast, kidnapped
    filt = TopologicalFilter(np.zeros(300), 0.1)
    found = []
    for d in route_distances(path, 300, rng):
        filt.step(d)
        found.append(int(np.argmax(filt.mass())))
    found, path = np.array(found), np.array(path)
    assert (np.abs(found - path)[5:80] <= 2).mean() > 0.95  # tracks through the stop and the faster stretch
    assert (np.abs(found - path)[-20:] <= 2).all()  # found again after the jump to 200


def test_mass_is_the_belief_near_each_frame_and_sums_to_one():
    filt = TopologicalFilter(np.zeros(50), 0.1, FilterSettings(radius=2))
    belief = filt.step(np.linspace(1, 2, 50))
    assert abs(belief.sum() - 1) < 1e-12
    mass = filt.mass()
    assert abs(mass[10] - belief[8:13].sum()) < 1e-12


def test_filter_topk_is_the_filter_stepped_by_hand_with_restarts_at_query_breaks():
    rng = np.random.default_rng(2)
    reference, query = torch.randn(40, 8), torch.randn(12, 8)
    segments = np.array([0] * 6 + [1] * 6)
    norms = reference_squared_norms(reference)
    top = filter_topk(query, reference, norms, TopologicalFilter(np.zeros(40), 0.5), 5, segments, block=5)
    by_hand = TopologicalFilter(np.zeros(40), 0.5)
    for i in range(12):
        if i == 6:
            by_hand.reset()
        by_hand.step(torch.cdist(query[i : i + 1], reference)[0].double().numpy())
        mass = by_hand.mass()
        assert top.indices[i, 0] == int(np.argmax(mass))
        assert abs(top.distances[i, 0] - (1 - mass.max())) < 1e-5
    del rng


def test_bad_filter_settings_and_scales_are_one_line():
    raises_one_line("min_step 3 is above max_step 1", FilterSettings, 3, 1)
    raises_one_line("floor must be in", FilterSettings, floor=1.0)
    raises_one_line("scale must be a positive", TopologicalFilter, np.zeros(3), 0.0)
    raises_one_line("all equally far apart", distance_scale, np.ones((2, 30)), 1.0, 1, np.array([0, 5]))
    with pytest.raises(Exception):
        TopologicalFilter(np.zeros(3), 1.0).step(np.zeros(4))
