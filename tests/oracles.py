"""Plain-loop reference implementations that the fast paths are tested against."""

from __future__ import annotations

import math

import numpy as np


def segment_of(segment_ids, i):
    """[start, end) of the run of equal ids containing frame i, by walking outwards."""
    start = i
    while start > 0 and segment_ids[start - 1] == segment_ids[i]:
        start -= 1
    end = i + 1
    while end < len(segment_ids) and segment_ids[end] == segment_ids[i]:
        end += 1
    return start, end


def window_start(segment_ids, i, span, offset, boundary):
    """Window start of frame i, or None: drop needs the natural window to fit, shift clamps it inward."""
    start, end = segment_of(segment_ids, i)
    if end - start < span:
        return None
    natural = i - offset
    if boundary == "drop":
        return natural if start <= natural and natural + span <= end else None
    return min(max(natural, start), end - span)


def sequence_distances(query, reference, length, align="centered", boundary="drop", q_seg=None, r_seg=None, velocity=1.0):
    """S[i, j] = mean over k of ||q[qs_i + k] - r[rs_j + round(k * v)]||, +inf without a window."""
    n_q, n_r = len(query), len(reference)
    q_seg = [0] * n_q if q_seg is None else list(q_seg)
    r_seg = [0] * n_r if r_seg is None else list(r_seg)
    offset = length // 2 if align == "centered" else length - 1
    steps = [int(np.rint(k * velocity)) for k in range(length)]
    out = np.full((n_q, n_r), np.inf)
    for i in range(n_q):
        qs = window_start(q_seg, i, length, offset, boundary)
        if qs is None:
            continue
        for j in range(n_r):
            rs = window_start(r_seg, j, steps[-1] + 1, steps[offset], boundary)
            if rs is None:
                continue
            total = 0.0
            for k in range(length):
                diff = np.asarray(query[qs + k], dtype=np.float64) - np.asarray(reference[rs + steps[k]], dtype=np.float64)
                total += math.sqrt(float(diff @ diff))
            out[i, j] = total / length
    return out


def recall_at_k(predictions, positives, ks):
    """Fraction of queries with a positive among their first k predictions, over queries that have positives."""
    evaluated = [i for i in range(len(predictions)) if len(positives[i]) > 0]
    result = {}
    for k in ks:
        hits = 0
        for i in evaluated:
            if any(p in positives[i] for p in predictions[i][:k] if p >= 0):
                hits += 1
        result[k] = hits / len(evaluated) if evaluated else float("nan")
    return result
