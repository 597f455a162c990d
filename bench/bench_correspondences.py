"""Correspondences against the matching they follow: the time of top-K sequence matching, of the top-1 matches'
per-frame pairs (``top1_pairs``; a velocity sweep scores each trajectory through each match) and of writing
``correspondences.csv`` (one ground-truth lookup for all pairs), at N synthetic queries (issue 28: they cost 20x
the matching at 20k queries).

Run from the repository root (CPU; a minute or two):

    .venv/bin/python bench/bench_correspondences.py [--queries 20000] [--velocities 0.8,1,1.2]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from _common import cpu_model

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, default=20000)
    parser.add_argument("--velocities", default="0.8,1,1.2")
    parser.add_argument("--seq-len", type=int, default=5)
    args = parser.parse_args()
    from seqvpr.evaluation.predictions import save_correspondences
    from seqvpr.results import MatchResult
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.matchers.rows import query_rows
    from seqvpr.matchers.sequence import top1_pairs
    from seqvpr.evaluation.ground_truth import resolve_ground_truth
    from seqvpr.evaluation.scoring import match_correspondences
    from seqvpr.sequences.matching import sequence_topk
    from seqvpr.sequences.windows import SequenceSpec, parse_velocities
    from seqvpr.synthetic.routes import generate_route

    reference, query = generate_route(args.queries, 64, 0)
    gt = resolve_ground_truth(reference, query, "25m", None)
    settings = MatchSettings(SequenceSpec(args.seq_len, velocities=parse_velocities(args.velocities)), 20)
    ref, qry = query_rows(reference, settings), query_rows(query, settings)
    started = time.perf_counter()
    topk = sequence_topk(qry, ref, settings.sequence, settings.k, query.segment_ids, reference.segment_ids)
    matched = time.perf_counter()
    pairs = top1_pairs(qry, ref, topk, settings, None, query.segment_ids, reference.segment_ids)
    paired = time.perf_counter()
    result = MatchResult(reference, query, topk, settings, correspondences=pairs)
    with tempfile.TemporaryDirectory() as folder:
        save_correspondences(Path(folder) / "correspondences.csv", result, match_correspondences(result), gt)
    written = time.perf_counter()
    print(f"{cpu_model()}; {args.queries} queries x {len(reference)} reference frames, L={args.seq_len}, "
          f"velocities {args.velocities}")
    print(f"top-K matching {matched - started:.2f} s | top-1 pairs {paired - matched:.2f} s | "
          f"correspondences.csv {written - paired:.2f} s")


if __name__ == "__main__":
    main()
