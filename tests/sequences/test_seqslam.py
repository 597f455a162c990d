"""SeqSLAM's local contrast enhancement against a plain loop, and through the kernel's blocked top-K."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from seqvpr.sequences.adaptive import AdaptiveScorer
from seqvpr.sequences.matching import frame_distances, sequence_topk
from seqvpr.sequences.seqslam import MIN_STD, ContrastScorer, enhance_contrast
from seqvpr.sequences.windows import SequenceSpec
from tests.helpers import examples


def plain_enhance(d: np.ndarray, seg: np.ndarray, window: int) -> np.ndarray:
    out = np.empty_like(d)
    for i in range(d.shape[0]):
        for r in range(d.shape[1]):
            same = [c for c in range(r - window // 2, r - window // 2 + window)
                    if 0 <= c < d.shape[1] and seg[c] == seg[r]]
            values = d[i, same]
            out[i, r] = (d[i, r] - values.mean()) / max(values.std(), MIN_STD)
    return out


@settings(max_examples=examples(30), deadline=None)
@given(seed=st.integers(0, 9999), n_r=st.integers(1, 25), window=st.integers(2, 12), breaks=st.booleans())
def test_contrast_enhancement_equals_a_plain_loop(seed, n_r, window, breaks):
    rng = np.random.default_rng(seed)
    d = rng.random((4, n_r))
    seg = np.sort(rng.integers(0, 3, n_r)) if breaks else np.zeros(n_r, np.int64)
    got = enhance_contrast(torch.from_numpy(d), seg, window).numpy()
    np.testing.assert_allclose(got, plain_enhance(d, seg, window), rtol=1e-7, atol=1e-9)


def test_contrast_scorer_blocked_equals_whole_and_is_the_kernel_on_the_enhanced_matrix():
    rng = np.random.default_rng(2)
    q, r = torch.from_numpy(rng.standard_normal((40, 8))), torch.from_numpy(rng.standard_normal((200, 8)))
    q_seg, r_seg = np.r_[np.zeros(20, int), np.ones(20, int)], np.repeat(np.arange(4), 50)
    spec = SequenceSpec(5, velocities=(0.8, 0.9, 1.0, 1.1, 1.2))
    for inner in (None, AdaptiveScorer(1, 2)):
        scorer = ContrastScorer(10, inner)
        whole = sequence_topk(q, r, spec, 8, q_seg, r_seg, scorer=scorer)
        blocked = sequence_topk(q, r, spec, 8, q_seg, r_seg, scorer=scorer, chunk=23)
        np.testing.assert_array_equal(blocked.indices, whole.indices)
        np.testing.assert_allclose(blocked.distances, whole.distances, rtol=1e-9)
    enhanced = enhance_contrast(frame_distances(q, r), r_seg)
    top = sequence_topk(q, r, SequenceSpec(1), 1, q_seg, r_seg, scorer=ContrastScorer(10))
    np.testing.assert_array_equal(top.indices[:, 0], enhanced.argmin(1).numpy())


def plain_trajectories(spec, seg, n):
    """Per anchor r, the grid's in-segment straight trajectories (lists of reference frames), by enumeration; under
    ``shift`` a trajectory that would leave r's segment is moved inside it, as the kernel moves its windows."""
    h = max(spec.offset, spec.length - 1 - spec.offset)
    if h == 0:
        grid = [1.0]
    else:
        lo, hi = (int(np.floor(h * v + 0.5)) for v in (min(spec.velocities), max(spec.velocities)))
        grid = [k / h for k in range(max(lo, 1), hi + 1)] or [1.0]
    out = []
    for r in range(n):
        paths = []
        for v in grid:
            steps = [int(np.rint(k * v)) for k in range(spec.length)]
            start = r - steps[spec.offset]
            if spec.boundary == "shift":
                first = min(f for f in range(n) if seg[f] == seg[r])
                last = max(f for f in range(n) if seg[f] == seg[r])
                start = min(max(start, first), last - steps[-1])
            frames = [start + t for t in steps]
            if all(0 <= f < n and seg[f] == seg[r] for f in frames):
                paths.append(frames)
        out.append(paths)
    return out


def plain_cone(best, start, spec, seg, n):
    out = np.full(n, np.inf)
    for r, paths in enumerate(plain_trajectories(spec, seg, n)):
        if paths:
            votes = sum(any(p[k] == best[start + k] for p in paths) for k in range(spec.length))
            out[r] = 1 - votes / spec.length
    return out


def plain_hybrid(d, best, start, spec, seg):
    n = d.shape[1]
    out = np.full(n, np.inf)
    window_best = {best[start + k] for k in range(spec.length)}
    for r, paths in enumerate(plain_trajectories(spec, seg, n)):
        for p in paths:
            if window_best & set(p):
                out[r] = min(out[r], np.mean([d[start + k, p[k]] for k in range(spec.length)]))
    return out


SHAPES = dict(seed=st.integers(0, 9999), length=st.integers(1, 7), align=st.sampled_from(["centered", "causal"]),
              low=st.sampled_from([0.5, 0.8, 1.0]), high=st.sampled_from([1.0, 1.2, 1.6]), breaks=st.booleans(),
              boundary=st.sampled_from(["drop", "shift"]))


def scored_against_a_plain_loop(scorer, plain, seed, length, align, low, high, breaks, boundary):
    """The scorer's distances for every query window (prepared and located as sequence_topk does) against
    ``plain(d, best, start, spec, seg)``; the same for the block holding reference rows 7.. only."""
    from seqvpr.sequences.matching import sequence_distance_rows
    from seqvpr.sequences.windows import window_starts

    rng = np.random.default_rng(seed)
    q, r = torch.from_numpy(rng.standard_normal((12, 6))), torch.from_numpy(rng.standard_normal((30, 6)))
    q[5] = r[20] + 0.01  # a query frame whose best match is certain, so votes and kept paths occur
    r_seg = np.sort(rng.integers(0, 3, 30)) if breaks else np.zeros(30, np.int64)
    q_seg = np.zeros(12, np.int64)
    spec = SequenceSpec(length, align, boundary, velocities=(low, high))
    starts = window_starts(q_seg, length, spec.offset, "drop")
    valid = starts[starts >= 0]
    if len(valid) == 0:
        return
    d = frame_distances(q, r).numpy()
    best = d.argmin(1)
    bound = scorer.prepare(q, r, q_seg, r_seg, None)
    np.testing.assert_array_equal(bound.best, best)
    got = sequence_distance_rows(q, r, spec, valid, r_seg, scorer=bound).numpy()
    part = sequence_distance_rows(q, r[7:], spec, valid, r_seg[7:], scorer=bound, reference_first=7).numpy()
    for row, start in enumerate(valid):
        np.testing.assert_allclose(got[row], plain(d, best, int(start), spec, r_seg), rtol=1e-9)
        np.testing.assert_allclose(part[row], plain(d[:, 7:], best - 7, int(start), spec, r_seg[7:]), rtol=1e-9)


@settings(max_examples=examples(40), deadline=None)
@given(**SHAPES)
def test_cone_search_counts_best_matches_inside_the_cone_as_a_plain_loop(seed, length, align, low, high, breaks,
                                                                         boundary):
    from seqvpr.sequences.seqslam import ConeScorer

    scored_against_a_plain_loop(ConeScorer(), lambda d, best, start, spec, seg: plain_cone(best, start, spec, seg,
                                                                                           d.shape[1]),
                                seed, length, align, low, high, breaks, boundary)


@settings(max_examples=examples(40), deadline=None)
@given(**SHAPES)
def test_hybrid_search_keeps_trajectories_through_a_best_match_as_a_plain_loop(seed, length, align, low, high,
                                                                               breaks, boundary):
    from seqvpr.sequences.seqslam import HybridScorer

    scored_against_a_plain_loop(HybridScorer(), plain_hybrid, seed, length, align, low, high, breaks, boundary)


def test_velocity_grid_is_openseqslam2s():
    from seqvpr.sequences.seqslam import velocity_grid

    assert velocity_grid(SequenceSpec(10, velocities=(0.8, 1.2))) == (0.8, 1.0, 1.2)  # d_s = 10: h = 5
    assert velocity_grid(SequenceSpec(20, velocities=(0.8, 0.9, 1.0, 1.1, 1.2))) == (0.8, 0.9, 1.0, 1.1, 1.2)
    assert velocity_grid(SequenceSpec(5, velocities=(0.8, 1.2))) == (1.0,)  # h = 2: 1.6 and 2.4 round to 2
    assert velocity_grid(SequenceSpec(1, velocities=(0.8, 1.2))) == (1.0,)


def test_cone_and_hybrid_blocked_equal_whole_and_need_preparing():
    from seqvpr.errors import SeqvprError
    from seqvpr.sequences.matching import sequence_distance_rows
    from seqvpr.sequences.seqslam import ConeScorer, HybridScorer

    rng = np.random.default_rng(4)
    r = torch.from_numpy(rng.standard_normal((200, 8)))
    q = r[60:100] + 0.6 * torch.from_numpy(rng.standard_normal((40, 8)))
    q_seg, r_seg = np.r_[np.zeros(20, int), np.ones(20, int)], np.repeat(np.arange(4), 50)
    spec = SequenceSpec(7, velocities=(0.6, 1.4))
    for scorer in (ConeScorer(), ContrastScorer(10, HybridScorer())):
        for boundary in ("drop", "shift"):
            spec = SequenceSpec(7, boundary=boundary, velocities=(0.6, 1.4))
            whole = sequence_topk(q, r, spec, 8, q_seg, r_seg, scorer=scorer)
            blocked = sequence_topk(q, r, spec, 8, q_seg, r_seg, scorer=scorer, chunk=23, memory_budget=10**6)
            np.testing.assert_allclose(blocked.distances, whole.distances, rtol=1e-9)
            # the contrast's float64 running sums start at each block's edge, so windows that `shift` makes equal
            # are equal only to ~1e-15 and may swap ranks; everywhere else the order is the same
            with np.errstate(invalid="ignore"):  # inf - inf past the last window
                gaps = np.nan_to_num(np.diff(whole.distances, axis=1), nan=np.inf)
            near = np.zeros_like(whole.indices, dtype=bool)
            near[:, 1:] |= gaps < 1e-9
            near[:, :-1] |= gaps < 1e-9
            np.testing.assert_array_equal(blocked.indices[~near], whole.indices[~near])
            assert (whole.indices[:, 0] >= 0).mean() > 0.5
    with pytest.raises(SeqvprError, match="best match"):
        sequence_distance_rows(q, r, spec, np.array([0]), r_seg, scorer=HybridScorer())
