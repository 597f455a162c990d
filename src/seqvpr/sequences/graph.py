"""Graph-based sequence matching in the spirit of GISM (Naseer et al., network flows): the best path through the
whole distance matrix, one reference frame per query frame, with bounded jumps.

The graph has a node per (query frame, reference frame) costing their distance, and one "hidden" node per query
frame costing ``hidden`` (a frame that matches nothing: occlusion, a detour). From reference frame r' a path goes
on to r' + t with t in [0, fanout] inside one reference segment; it may leave for the hidden node and come back
anywhere, which is how it jumps. A unit flow through this acyclic graph is its shortest path, so min-sum dynamic
programming (Viterbi) finds it exactly. Each query frame's candidates are ranked by their min-marginal: the cost
of the best whole path through them (forward + backward - own), so the top-1 is the best path's frame and the
rest of the top-K are the best alternatives. Query segment breaks start new paths. Unlike the window matchers it
uses the whole query (offline): the online counterpart is the ``hmm`` filter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from seqvpr.errors import SeqvprError
from seqvpr.sequences.matching import TopK, frame_distances
from seqvpr.sequences.windows import segment_bounds

HIDDEN_QUANTILE = 0.8  # the hidden node costs this quantile of the frame distances (measured: 0.8 on Nordland and GP)


@dataclass(frozen=True)
class GraphSettings:
    """A path moves ``min_step`` to ``fanout`` reference frames per query frame; ``hidden_quantile``: the hidden
    node's cost as a quantile of the distance matrix (lower: fewer frames left unmatched)."""

    fanout: int = 2
    hidden_quantile: float = HIDDEN_QUANTILE
    min_step: int = 1

    def __post_init__(self) -> None:
        if not 0 <= self.min_step <= self.fanout or not 0 < self.hidden_quantile < 1:
            raise SeqvprError(f"graph matching needs fanout >= 0 and 0 < hidden quantile < 1, got {self}")


def graph_topk(query: torch.Tensor, reference: torch.Tensor, k: int, query_segments: np.ndarray,
               reference_segments: np.ndarray, settings: GraphSettings = GraphSettings(),
               memory_budget: int | None = None) -> TopK:
    """The K reference frames per query frame with the cheapest whole path through them (mean cost per frame)."""
    n_q, n_r = len(query), len(reference)
    if memory_budget is not None and 3 * n_q * n_r * 8 > memory_budget:
        raise SeqvprError(f"graph matching holds three {n_q} x {n_r} matrices ({3 * n_q * n_r * 8 / 2**30:.1f} GiB), "
                          f"more than --memory-budget; match fewer frames (--frames) or raise the budget")
    d = frame_distances(query, reference).double().cpu().numpy()
    hidden = float(np.quantile(d, settings.hidden_quantile))
    marginal = path_costs(d, np.asarray(query_segments), np.asarray(reference_segments), settings.fanout, hidden,
                          settings.min_step)
    k = min(k, n_r)
    order = np.argsort(marginal, axis=1, kind="stable")[:, :k]
    return TopK(order.astype(np.int64), np.take_along_axis(marginal, order, 1), np.ones(n_q, bool))


def path_costs(d: np.ndarray, query_segments: np.ndarray, reference_segments: np.ndarray, fanout: int,
               hidden: float, min_step: int = 0) -> np.ndarray:
    """Min-marginals [n_q, n_r]: the mean cost per query frame of the best path (within the query frame's segment)
    that passes through reference frame r at query frame i."""
    moves = _moves(reference_segments, fanout)[min_step:]
    forward, _ = _pass(d, query_segments, moves, hidden, +1)
    backward, _ = _pass(d, query_segments, moves, hidden, -1)
    seg_start, seg_end = segment_bounds(query_segments)
    return (forward + backward - d) / (seg_end - seg_start)[:, None]


def _moves(segments: np.ndarray, fanout: int) -> list[tuple[int, np.ndarray]]:
    """For each step t in [0, fanout]: whether reference frame r may be reached from r - t (one segment)."""
    n = len(segments)
    out = []
    for t in range(fanout + 1):
        ok = np.zeros(n, bool)
        ok[t:] = segments[t:] == segments[: n - t]
        out.append((t, ok))
    return out


def _pass(d: np.ndarray, q_seg: np.ndarray, moves, hidden: float, direction: int) -> tuple[np.ndarray, np.ndarray]:
    """Min-sum costs of the best partial paths ending (forward) or starting (backward) at each node: [n_q, n_r]
    for the reference nodes and [n_q] for the hidden node; a query segment break starts afresh."""
    n_q, n_r = d.shape
    out = np.empty_like(d)
    out_hidden = np.empty(n_q)
    rows = range(n_q) if direction > 0 else range(n_q - 1, -1, -1)
    previous, previous_hidden, previous_row = None, 0.0, -1
    for i in rows:
        if previous is None or q_seg[i] != q_seg[previous_row]:
            carry, carry_hidden = np.zeros(n_r), 0.0
        else:
            carry = np.full(n_r, np.inf)
            for t, ok in moves:
                if direction > 0:
                    shifted = np.full(n_r, np.inf)
                    shifted[t:] = previous[: n_r - t]
                    shifted[~ok] = np.inf
                else:
                    shifted = np.full(n_r, np.inf)
                    shifted[: n_r - t] = previous[t:]
                    shifted[: n_r - t][~ok[t:]] = np.inf
                np.minimum(carry, shifted, out=carry)
            np.minimum(carry, previous_hidden, out=carry)  # back from the hidden node: a jump
            carry_hidden = min(previous_hidden, float(previous.min()))
        out[i] = d[i] + carry
        out_hidden[i] = hidden + carry_hidden
        previous, previous_hidden, previous_row = out[i], out_hidden[i], i
    return out, out_hidden
