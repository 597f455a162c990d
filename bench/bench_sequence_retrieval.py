"""Benchmark: retrieval with one compact sequence descriptor per window (SeqGeM + faiss) against sequence matching.

JIST's claim is that a compact sequence descriptor is much faster to match than sequence matching over frame
descriptors. Run from the repository root (about two minutes on 2 cores):

    .venv/bin/python bench/bench_sequence_retrieval.py [--references 10000 100000] [--queries 1000] [--dim 512]

On seeded smooth random frame descriptors (a random walk, L2-normalised; ``--dim`` as JIST's 512-D), with L = 5
centred windows and the top 20 kept, both sides answer the same question for ``--queries`` query frames:

* yardstick: seqvpr's sequence matching, ``sequence_topk`` (one GEMM per block of queries, then the fused window
  mean, then top-K) over the frame descriptors;
* sequence descriptors: ``sequence_descriptors(..., "seqgem")`` for the query frames (the reference side is built
  once with the map, so it is timed separately), then a faiss exact flat index search (``retrieve``);
* for information, the same with an approximate HNSW index (``kind="hnsw"``, M=32, efSearch=64; its build is
  timed separately): compact descriptors admit sub-linear indexes, sequence matching does not.

Each measurement is the median of ``--repeats`` runs after one warm-up; the printed ratio is matching time over
descriptor-retrieval time (with and without building the reference side).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _common import cpu_model, median_time

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from seqvpr.sequences.descriptors import sequence_descriptors
from seqvpr.sequences.matching import sequence_topk
from seqvpr.sequences.retrieval import build_index, retrieve
from seqvpr.sequences.windows import SequenceSpec


def random_walk(n: int, dim: int, seed: int) -> np.ndarray:
    """Smooth L2-normalised frame descriptors: consecutive frames alike, distant ones not."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(n, dim)).astype(np.float32)
    walk = np.empty_like(steps)
    walk[0] = steps[0]
    for i in range(1, n):  # AR(1): x_i = 0.9 x_{i-1} + noise
        walk[i] = 0.9 * walk[i - 1] + steps[i]
    return walk / np.linalg.norm(walk, axis=1, keepdims=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--references", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--queries", type=int, default=1000)
    parser.add_argument("--dim", type=int, default=512)
    parser.add_argument("--length", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    spec = SequenceSpec(args.length)
    print(f"CPU: {cpu_model()} ({os.cpu_count()} logical CPUs); torch {torch.__version__} threads={torch.get_num_threads()}")
    print(f"{args.queries} query frames, {args.dim}-D frames, L={args.length}, top 20; median of {args.repeats}\n")
    print("| reference frames | sequence matching (s) | SeqGeM query side + faiss flat search (s) | "
          "reference SeqGeM + flat index (s) | ratio | ratio incl. reference side | HNSW search (s) | "
          "HNSW build (s) | ratio, HNSW search |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    query = random_walk(args.queries, args.dim, seed=1)
    for n_ref in args.references:
        reference = random_walk(n_ref, args.dim, seed=2)
        q_t, r_t = torch.from_numpy(query), torch.from_numpy(reference)
        matching_s = median_time(lambda: sequence_topk(q_t, r_t, spec, 20, memory_budget=2 * 1024**3), args.repeats)
        state = {}

        def build_reference() -> None:
            state["ref"] = sequence_descriptors(reference, None, spec, "seqgem")
            state["index"] = build_index(state["ref"].vectors)

        def search() -> None:
            query_descriptors = sequence_descriptors(query, None, spec, "seqgem")
            retrieve(query_descriptors, state["ref"], 20, index=state["index"])

        build_s = median_time(build_reference, args.repeats)
        search_s = median_time(search, args.repeats)
        start = time.perf_counter()
        state["index"] = build_index(state["ref"].vectors, "hnsw")
        hnsw_build_s = time.perf_counter() - start
        hnsw_s = median_time(search, args.repeats)
        print(f"| {n_ref:,} | {matching_s:.3f} | {search_s:.3f} | {build_s:.3f} | {matching_s / search_s:.1f}x | "
              f"{matching_s / (search_s + build_s):.1f}x | {hnsw_s:.3f} | {hnsw_build_s:.1f} | "
              f"{matching_s / hnsw_s:.0f}x |", flush=True)


if __name__ == "__main__":
    main()
