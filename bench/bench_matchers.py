"""Speed of the matchers beside the kernel, as ratios against the core kernel in the same run.

Run from the repository root (about a minute on 2 cores):

    .venv/bin/python bench/bench_matchers.py [--queries 2000] [--references 8000] [--dim 256] [--lengths 5,10,20]

Each matcher goes through ``sequence_topk`` on the same seeded random unit descriptors (K = 20, the default 2 GB
budget): the constant-velocity kernel (the yardstick), ``AdaptiveScorer(1, 2)`` (``--method adaptive``) and
``ContrastScorer()`` (``--method seqslam``), the kernel with SeqSLAM's five-velocity sweep, OpenSeqSLAM2's cone
(``ConeScorer``, ``--method seqslam-cone``) and hybrid search (``ContrastScorer(10, HybridScorer())``,
``--method seqslam-hybrid``) over velocities 0.8..1.2 (each includes its single-image pass), CaseVPR's hierarchy
(``seqvpr.match(..., "casevpr")``: a SeqGeM top-20 shortlist from faiss, re-ranked by adaptive matching), and once the graph
matcher (``--method graph``, whole query) against the kernel at L = 1. The median of
``--repeats`` runs is reported per length, with the ratio to the kernel at the same length.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from _common import cpu_model
from seqvpr.errors import SeqvprError
from seqvpr.sequences.adaptive import AdaptiveScorer
from seqvpr.sequences.graph import GraphSettings, graph_topk
from seqvpr.sequences.matching import sequence_topk
from seqvpr.sequences.seqslam import ConeScorer, ContrastScorer, HybridScorer
from seqvpr.sequences.windows import SequenceSpec


def timed_casevpr(query: torch.Tensor, reference: torch.Tensor, length: int, repeats: int) -> float:
    """Median seconds of ``seqvpr.match(..., "casevpr")`` (shortlist and adaptive re-rank) over ``repeats`` runs."""
    from seqvpr.data.traversal import Traversal
    from seqvpr.api import match
    from seqvpr.sequences.match_settings import MatchSettings

    def traversal(name: str, rows: torch.Tensor) -> Traversal:
        return Traversal(name, np.arange(len(rows)), np.zeros(len(rows), np.int64), rows.numpy())

    ref, qry = traversal("reference", reference), traversal("query", query)
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        match(ref, qry, "casevpr", settings=MatchSettings(SequenceSpec(length), k=20))
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def timed(query, reference, spec, scorer, repeats: int) -> float:
    """Median seconds of ``sequence_topk`` over ``repeats`` runs."""
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        sequence_topk(query, reference, spec, 20, memory_budget=2 * 1024**3, scorer=scorer)
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, default=2000)
    parser.add_argument("--references", type=int, default=8000)
    parser.add_argument("--dim", type=int, default=256)
    parser.add_argument("--lengths", default="5,10,20")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    unit = lambda n: torch.nn.functional.normalize(torch.from_numpy(rng.standard_normal((n, args.dim), np.float32)), dim=1)  # noqa: E731
    query, reference = unit(args.queries), unit(args.references)
    print(f"CPU: {cpu_model()}; torch {torch.__version__} threads={torch.get_num_threads()}")
    print(f"{args.queries} queries x {args.references} references, {args.dim}-D, K=20, median of {args.repeats}")
    print(f"{'L':>3} {'matcher':<28} {'seconds':>8} {'x kernel':>9}")
    for length in (int(x) for x in args.lengths.split(",")):
        spec, sweep = SequenceSpec(length), SequenceSpec(length, velocities=(0.8, 0.9, 1.0, 1.1, 1.2))
        base = timed(query, reference, spec, None, args.repeats)
        rows = [("kernel (constant velocity)", base),
                ("kernel, 5 velocities 0.8-1.2", timed(query, reference, sweep, None, args.repeats)),
                ("seqslam-cone, 0.8-1.2", timed(query, reference, sweep, ConeScorer(), args.repeats)),
                ("seqslam-hybrid, 0.8-1.2", timed(query, reference, sweep, ContrastScorer(10, HybridScorer()),
                                                  args.repeats)),
                ("adaptive, steps 1..2", timed(query, reference, spec, AdaptiveScorer(1, 2), args.repeats)),
                ("casevpr (top 20, adaptive)", timed_casevpr(query, reference, length, args.repeats)),
                ("seqslam contrast (window 10)", timed(query, reference, spec, ContrastScorer(), args.repeats))]
        for name, seconds in rows:
            print(f"{length:>3} {name:<28} {seconds:8.3f} {seconds / base:8.2f}x")
    base = timed(query, reference, SequenceSpec(1), None, args.repeats)
    segments = (np.zeros(args.queries, np.int64), np.zeros(args.references, np.int64))
    started = time.perf_counter()
    try:
        graph_topk(query, reference, 20, *segments, GraphSettings(), 2 * 1024**3)
    except SeqvprError as error:  # it holds whole n_query x n_reference matrices: large sizes are refused
        print(f"{'-':>3} {'graph (whole path, steps 1..2)':<28} refused: {error}")
        return
    seconds = time.perf_counter() - started
    print(f"{'-':>3} {'graph (whole path, steps 1..2)':<28} {seconds:8.3f} {seconds / base:8.2f}x  (against the kernel at L=1)")


if __name__ == "__main__":
    main()
