"""The kernel's trajectory correspondences, vectorised over the queries, equal the per-query loop they replace
(``trajectory_correspondences`` with a scorer that is the kernel itself takes the loop)."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings, strategies as st

from seqvpr.sequences.correspondences import kernel_trajectories, trajectory_correspondences
from seqvpr.sequences.matching import max_span, sequence_rows, sequence_topk
from seqvpr.sequences.windows import SequenceSpec
from tests.helpers import examples


class _KernelInTheLoop:
    """The kernel's own window distance as a scorer, so ``trajectory_correspondences`` runs its per-query loop."""

    def span(self, spec: SequenceSpec) -> int:
        return max_span(spec)

    def __call__(self, *args, **kwargs):
        return sequence_rows(*args, **kwargs)

    def trajectory_velocities(self, spec: SequenceSpec) -> tuple[float, ...]:
        return tuple(spec.velocities)


@settings(max_examples=examples(30), deadline=None)
@given(seed=st.integers(0, 9999), length=st.integers(1, 7), boundary=st.sampled_from(["drop", "shift"]),
       dtype=st.sampled_from([torch.float32, torch.float64]), stored=st.booleans())
def test_kernel_trajectories_equal_the_per_query_loop(seed, length, boundary, dtype, stored):
    rng = np.random.default_rng(seed)
    r = torch.from_numpy(rng.standard_normal((90, 8))).to(dtype)
    q = r[20:60] + 0.7 * torch.from_numpy(rng.standard_normal((40, 8))).to(dtype)
    q_seg, r_seg = np.r_[np.zeros(25, int), np.ones(15, int)], np.sort(rng.integers(0, 3, 90))
    spec = SequenceSpec(length, boundary=boundary, velocities=(0.7, 1.0, 1.4))
    best = sequence_topk(q, r, spec, 1, q_seg, r_seg).indices[:, 0]
    reference = r.numpy() if stored else r  # a saved map's rows are an array read a block at a time
    fast = kernel_trajectories(q, reference, best, spec, q_seg, r_seg)
    loop = trajectory_correspondences(q, r, best, spec, _KernelInTheLoop(), q_seg, r_seg)
    assert loop is not None and (loop[0] >= 0).any()
    np.testing.assert_array_equal(fast[0], loop[0])
    np.testing.assert_array_equal(fast[1], loop[1])
