"""SeqSLAM's local contrast enhancement against a plain loop, and through the kernel's blocked top-K."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings, strategies as st

from seqvpr.sequences.adaptive import AdaptiveScorer
from seqvpr.sequences.matching import frame_distances, sequence_topk
from seqvpr.sequences.seqslam import MIN_STD, ContrastScorer, enhance_contrast
from seqvpr.sequences.windows import SequenceSpec


def plain_enhance(d: np.ndarray, seg: np.ndarray, window: int) -> np.ndarray:
    out = np.empty_like(d)
    for i in range(d.shape[0]):
        for r in range(d.shape[1]):
            same = [c for c in range(r - window // 2, r - window // 2 + window)
                    if 0 <= c < d.shape[1] and seg[c] == seg[r]]
            values = d[i, same]
            out[i, r] = (d[i, r] - values.mean()) / max(values.std(), MIN_STD)
    return out


@settings(max_examples=30, deadline=None)
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


def plain_cone(d, start, spec, seg):
    low, high = min(spec.velocities), max(spec.velocities)
    n = d.shape[1]
    out = np.full(n, np.inf)
    for j in range(n):
        total = 0.0
        for k in range(spec.length):
            ends = sorted((int(np.floor(low * (k - spec.offset) + 0.5)), int(np.floor(high * (k - spec.offset) + 0.5))))
            options = [d[start + k, j + t] for t in range(ends[0], ends[1] + 1) if 0 <= j + t < n and seg[j + t] == seg[j]]
            if not options:
                total = np.inf
                break
            total += min(options)
        out[j] = total / spec.length
    return out


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 9999), length=st.integers(1, 6), align=st.sampled_from(["centered", "causal"]),
       low=st.sampled_from([0.5, 0.8, 1.0]), high=st.sampled_from([1.0, 1.2, 1.6]), breaks=st.booleans())
def test_cone_search_equals_a_plain_loop(seed, length, align, low, high, breaks):
    from seqvpr.sequences.matching import sequence_distance_rows
    from seqvpr.sequences.seqslam import ConeScorer
    from seqvpr.sequences.windows import window_starts

    rng = np.random.default_rng(seed)
    q, r = torch.from_numpy(rng.standard_normal((10, 6))), torch.from_numpy(rng.standard_normal((25, 6)))
    r_seg = np.sort(rng.integers(0, 3, 25)) if breaks else np.zeros(25, np.int64)
    spec = SequenceSpec(length, align, velocities=(low, high))
    starts = window_starts(np.zeros(10, np.int64), length, spec.offset, "drop")
    valid = starts[starts >= 0]
    if len(valid) == 0:
        return
    got = sequence_distance_rows(q, r, spec, valid, r_seg, scorer=ConeScorer()).numpy()
    d = frame_distances(q, r).numpy()
    for row, start in enumerate(valid):
        np.testing.assert_allclose(got[row], plain_cone(d, int(start), spec, r_seg), rtol=1e-9)
