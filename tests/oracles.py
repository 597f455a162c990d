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


def window_distance(query_window, reference_window, frames=None):
    """Mean over the (selected) frames of the Euclidean distance between order-aligned frames of two windows."""
    qw = np.asarray(query_window, dtype=np.float64)
    rw = np.asarray(reference_window, dtype=np.float64)
    picked = list(range(len(qw)))[frames] if frames is not None else list(range(len(qw)))
    total = 0.0
    for k in picked:
        diff = qw[k] - rw[k]
        total += math.sqrt(float(diff @ diff))
    return total / len(picked)


def triplet_loss(query_windows, positive_windows, negative_windows, owner, margin, frames=None):
    """sum over triplets t of max(d(q_b, p_b) - d(q_b, n_t) + margin, 0) / T with b = owner[t]."""
    total = 0.0
    for t in range(len(negative_windows)):
        b = int(owner[t])
        d_p = window_distance(query_windows[b], positive_windows[b], frames)
        d_n = window_distance(query_windows[b], negative_windows[t], frames)
        total += max(d_p - d_n + margin, 0.0)
    return total / len(negative_windows)


def diagonal_window_distance(query_window, reference_window):
    """The reference code's way: the full L x L Euclidean distance matrix of two windows, mean of its diagonal."""
    qw = np.asarray(query_window, dtype=np.float64)
    rw = np.asarray(reference_window, dtype=np.float64)
    full = np.sqrt(((qw[:, None, :] - rw[None, :, :]) ** 2).sum(-1))  # full[a, b] = ||q_a - r_b||
    return float(np.trace(full)) / len(qw)


def window_rows(query, reference, query_starts, length, offset, boundary, r_seg, centre_only=False):
    """Plain-loop kernel rows [R, n_r]: query windows at the given starts against every reference frame's window
    (+inf where a reference frame has none); ``centre_only`` compares the windows' current frames only."""
    query = np.asarray(query, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    out = np.full((len(query_starts), len(reference)), np.inf)
    reference_starts = [window_start(r_seg, j, length, offset, boundary) for j in range(len(reference))]
    for i, qs in enumerate(query_starts):
        for j, rs in enumerate(reference_starts):
            if rs is None:
                continue
            if centre_only:
                diff = query[qs + offset] - reference[rs + offset]
                out[i, j] = math.sqrt(float(diff @ diff))
            else:
                out[i, j] = diagonal_window_distance(query[qs : qs + length], reference[rs : rs + length])
    return out


def hardest_negatives(query, reference, q_seg, r_seg, length, offset, boundary, positive_frames, near_frames, count):
    """Brute-force mining per query frame (frame-aligned traversals): None when the query has no window, no
    positive with a window or no negative; else (positive, d_p, hardest negatives, their distances) where the
    positive is the closest reference within ``positive_frames`` frames and the negatives are the ``count``
    closest reference frames farther than ``near_frames`` (ties by index), all among frames with a window."""
    query_starts = [window_start(q_seg, i, length, offset, boundary) for i in range(len(query))]
    with_window = [i for i, qs in enumerate(query_starts) if qs is not None]
    rows = window_rows(query, reference, [query_starts[i] for i in with_window], length, offset, boundary, r_seg)
    result = {i: None for i in range(len(query))}
    for i, row in zip(with_window, rows):
        positives = [j for j in range(len(reference)) if abs(i - j) <= positive_frames and math.isfinite(row[j])]
        negatives = [j for j in range(len(reference)) if abs(i - j) > near_frames and math.isfinite(row[j])]
        if not positives or not negatives:
            continue
        best = min(positives, key=lambda j: (row[j], j))
        hardest = sorted(negatives, key=lambda j: (row[j], j))[:count]
        result[i] = (best, float(row[best]), hardest, [float(row[j]) for j in hardest])
    return result


def uniqueness(rows, values, exclusion):
    """1 - best / (the first finite value of another place: a row more than ``exclusion`` from the best's), in
    [0, 1]; 0 with no match, 1 with no other place: the plain loop over one ranked list."""
    rows, values = list(rows), [float(v) for v in values]
    if not rows or rows[0] < 0 or not math.isfinite(values[0]):
        return 0.0
    for r, v in zip(rows[1:], values[1:]):
        if r >= 0 and math.isfinite(v) and abs(r - rows[0]) > exclusion:
            return 0.0 if v <= 0 else min(max(1.0 - values[0] / v, 0.0), 1.0)
    return 1.0


def eligible_limit(sessions, clock, i, value, unit):
    """Frames j eligible for frame i, by a plain loop: every frame of an earlier session, and of its own session
    those more than ``value`` before it (frames: rows; seconds or metres: ``clock``); the count of the prefix."""
    limit = 0
    for j in range(i):
        if sessions[j] != sessions[i]:
            eligible = True
        elif unit == "f":
            eligible = i - j > value
        else:
            eligible = clock[j] < clock[i] - value and all(clock[m] < clock[i] - value for m in range(j + 1)
                                                             if sessions[m] == sessions[i])
        if eligible:
            limit = j + 1
        else:
            break
    return limit


def loops_by_plain_loop(rows, segments, limits, length):
    """Each frame's best earlier window (row, mean of order-aligned distances) among rows j < limits[i] whose
    causal window lies in one segment, by plain loops in float64; (-1, inf) without a window. Ties: lower row."""
    rows = np.asarray(rows, dtype=np.float64)
    rows = rows / np.linalg.norm(rows, axis=1, keepdims=True)
    best = []
    for i in range(len(rows)):
        found = (-1, math.inf)
        if window_start(segments, i, length, length - 1, "drop") is not None:
            for j in range(limits[i]):
                if window_start(segments, j, length, length - 1, "drop") is None:
                    continue
                value = sum(float(np.linalg.norm(rows[i - k] - rows[j - k])) for k in range(length)) / length
                if value < found[1]:
                    found = (j, value)
        best.append(found)
    return np.array([b[0] for b in best]), np.array([b[1] for b in best])


def loops_from_distance_matrix(distances, segments, limits, length):
    """``loops_by_plain_loop`` over a given frame-distance matrix [N, N] (float64): for each frame, each eligible
    window's mean along its diagonal, summed term by term; the best (lowest row on ties), or (-1, inf)."""
    match, best = np.full(len(distances), -1), np.full(len(distances), math.inf)
    has_window = np.array([window_start(segments, j, length, length - 1, "drop") is not None
                           for j in range(len(distances))])
    for i in range(len(distances)):
        if not has_window[i] or limits[i] < length:
            continue
        ends = np.arange(length - 1, limits[i])
        total = np.zeros(len(ends))
        for k in range(length):
            total += distances[i - k, ends - k]
        means = np.where(has_window[ends], total / length, math.inf)
        if np.isfinite(means).any():
            match[i], best[i] = ends[int(np.argmin(means))], float(means.min())
    return match, best
