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

Same name as ``seqvpr.matchers.graph``: graph matching's algorithm; its matcher there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from seqvpr.errors import SeqvprError, SettingError
from seqvpr.sequences.adaptive import same_segment_masks, steps_min
from seqvpr.sequences.topk import rank_order
from seqvpr.results import TopK
from seqvpr.sequences.matching import frame_distances
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
        raise SettingError(f"graph matching holds three {n_q} x {n_r} matrices ({3 * n_q * n_r * 8 / 2**30:.1f} GiB), "
                          f"more than {{memory_budget}}; match fewer frames ({{frames}}) or raise the budget")
    d = frame_distances(query, reference).double().cpu().numpy()
    hidden = float(np.quantile(d, settings.hidden_quantile))
    marginal = path_costs(d, np.asarray(query_segments), np.asarray(reference_segments), settings.fanout, hidden,
                          settings.min_step)
    k = min(k, n_r)
    order = rank_order(np.broadcast_to(np.arange(n_r), marginal.shape), marginal, k)  # the one tie rule
    return TopK(order.astype(np.int64), np.take_along_axis(marginal, order, 1), np.ones(n_q, bool))


def path_costs(d: np.ndarray, query_segments: np.ndarray, reference_segments: np.ndarray, fanout: int,
               hidden: float, min_step: int = 0) -> np.ndarray:
    """Min-marginals [n_q, n_r]: the mean cost per query frame of the best path (within the query frame's segment)
    that passes through reference frame r at query frame i."""
    same = same_segment_masks(np.asarray(reference_segments), fanout, torch.device("cpu"))
    forward = _pass(d, query_segments, same, min_step, fanout, hidden, +1)
    backward = _pass(d, query_segments, same, min_step, fanout, hidden, -1)
    seg_start, seg_end = segment_bounds(query_segments)
    return (forward + backward - d) / (seg_end - seg_start)[:, None]


def _pass(d: np.ndarray, q_seg: np.ndarray, same: list[torch.Tensor], low: int, high: int, hidden: float,
          direction: int) -> np.ndarray:
    """Min-sum costs [n_q, n_r] of the best partial paths ending (forward) or starting (backward) at each reference
    node, steps as the adaptive matcher's (``steps_min``) or through the hidden node; a query segment break starts
    afresh."""
    out = np.empty_like(d)
    rows = range(len(d)) if direction > 0 else range(len(d) - 1, -1, -1)
    previous_row, previous_hidden = -1, 0.0
    for i in rows:
        if previous_row < 0 or q_seg[i] != q_seg[previous_row]:
            carry, carry_hidden = 0.0, 0.0
        else:
            previous = torch.from_numpy(out[previous_row][None])
            carry = steps_min(previous, low, high, same, direction)[0].numpy()
            np.minimum(carry, previous_hidden, out=carry)  # back from the hidden node: a jump
            carry_hidden = min(previous_hidden, float(out[previous_row].min()))
        out[i] = d[i] + carry
        previous_row, previous_hidden = i, hidden + carry_hidden
    return out
