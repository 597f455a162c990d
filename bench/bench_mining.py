"""Benchmark of SeqMatchNet hard-negative mining: the core kernel against the reference code's per-query cdist.

Run from the repository root (about 2 minutes on 2 cores):

    .venv/bin/python bench/bench_mining.py [--data ../shared/data] [--threads N] [--repeats 3] [--scope auto]
                                           [--skip-training]

Setting (the Nordland training split): summer = reference, winter = query, frames [17, 1200), L = 5 (centred
windows, boundary 'drop'), positives within 1 frame, negatives outside 4 frames, 10 hardest negatives from a pool of
1000 random candidates plus each query's cached negatives, margin rule as in training. Features are the 2048-D
patch-normalised descriptors of ``--data``/nordland_64x32 passed once, without gradients and outside every timed
region, through a freshly initialised ``FrameTransform(TransformConfig(2048), seed=0)``.

Timed, with ``time.perf_counter``, on the same features:

* core: ``SequenceMiner(seqmatch_rows(...), ...)``, i.e. ``sequence_distance_rows`` (one GEMM over the frames the
  query windows cover, then the fused window-mean pass);
* yardstick: the same ``SequenceMiner`` (identical settings) with the reference code's kernel injected: for each
  query its window [L, D] and every reference window [N_valid, L, D] (gathered once per ``mine`` call, which only
  favours the yardstick), ``torch.cdist(ref_windows, query_window[None])`` -> [N_valid, L, L], the mean of the
  diagonal -> one distance per reference window, +inf for reference frames without a window.

One epoch's worth of mining is every training query with a window, in a seeded random order, in chunks of 1000 (the
default ``refresh_every``), each miner fresh and with a fresh ``np.random.default_rng(seed)``, so both do identical
work. The core epoch is warmed up once and timed ``--repeats`` times (median, min); the yardstick is warmed up on 20
queries (which also estimates its cost) and timed once. If the yardstick epoch would take over ~60 s (or with
``--scope subset``), both are timed on the same fixed first 200 queries of the order instead (the output says so;
the core's full epoch is then also timed, for information, with the yardstick's epoch extrapolated from the
subset). On a loaded machine the estimate can land on either side of 60 s; ``--scope epoch`` forces the full epoch.

The triplets of the two miners are compared: same queries, positives and negative sets (order aside), distances
within 1e-4. Where a query's triplet differs (two candidates tied to within float rounding, e.g. at station stops),
both kernels' full distance rows for it are recomputed and must agree within 1e-4 with the same +inf pattern. For
information, the core kernel call alone is also timed on one chunk of the timed queries (the rest of ``mine`` is the
per-query selection in numpy, the same code for both miners).

Last (``--skip-training`` leaves it out), a short real training: ``train_seqmatchnet`` with default
``SeqMatchNetSettings`` except ``epochs=2``, validation on frames [1200, 1600) (radius 1 frame), into a temporary folder;
its per-epoch wall time, mining time and feature time come from the returned history.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from _common import cpu_model
import torch

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numba

from seqvpr.threads import use_threads
from seqvpr.data.ground_truth import ground_truth_within_radius, parse_radius
from seqvpr.data.sources import load_traversal
from seqvpr.data.traversal import Traversal
from seqvpr.models.seqmatchnet import FrameTransform, TransformConfig
from seqvpr.features.describe import describe
from seqvpr.sequences.windows import SequenceSpec, window_starts
from seqvpr.training.mining import DistanceRows, MiningConfig, SequenceMiner, Triplet, seqmatch_rows
from seqvpr.training.seqmatchnet import TrainingData, SeqMatchNetSettings, train_seqmatchnet

REPO = Path(__file__).resolve().parents[1]
TRAIN_FRAMES = (17, 1200)
VAL_FRAMES = (1200, 1600)
LENGTH = 5
CHUNK = 1000  # SeqMatchNetSettings().refresh_every
YARDSTICK_BUDGET_S = 60.0
SUBSET = 200
WARMUP_QUERIES = 20
SEED = 0


def yardstick_rows(spec: SequenceSpec, reference_segments: np.ndarray) -> DistanceRows:
    """The reference code's way: per query, cdist of its window against every reference window, diagonal mean."""
    length = spec.length
    ref_starts = window_starts(np.asarray(reference_segments), length, spec.offset, spec.boundary)
    valid_columns = np.flatnonzero(ref_starts >= 0)
    columns = torch.as_tensor(valid_columns)
    frames = torch.as_tensor(ref_starts[valid_columns][:, None] + np.arange(length)[None, :])  # [N_valid, L]

    def rows(query: torch.Tensor, reference: torch.Tensor, starts: np.ndarray) -> torch.Tensor:
        ref_windows = reference[frames]  # [N_valid, L, D]
        out = torch.full((len(starts), len(reference)), float("inf"), dtype=query.dtype)
        for number, start in enumerate(np.asarray(starts)):
            query_window = query[int(start) : int(start) + length]  # [L, D]
            pairwise = torch.cdist(ref_windows, query_window[None])  # [N_valid, L, L]
            out[number, columns] = torch.diagonal(pairwise, dim1=-2, dim2=-1).mean(-1)
        return out

    return rows


def mine_epoch(
    kernel: DistanceRows, setting: dict, order: np.ndarray, query_feat: torch.Tensor, reference_feat: torch.Tensor
) -> tuple[float, list[Triplet]]:
    """Seconds and triplets of one epoch of mining with a fresh miner and rng (chunks of CHUNK queries)."""
    miner = SequenceMiner(kernel, setting["query_starts"], setting["positives"], setting["near"], MiningConfig())
    rng = np.random.default_rng(SEED)
    triplets: list[Triplet] = []
    start = time.perf_counter()
    for begin in range(0, len(order), CHUNK):
        triplets.extend(miner.mine(query_feat, reference_feat, order[begin : begin + CHUNK], rng))
    return time.perf_counter() - start, triplets


def compare(
    core: list[Triplet],
    other: list[Triplet],
    rows_of: Callable[[np.ndarray], tuple[torch.Tensor, torch.Tensor]],
    tol: float = 1e-4,
) -> tuple[bool, str]:
    """Same queries, positives and negative sets (order aside), distances within ``tol``; else only near-ties.

    Both miners draw the same random pools (the draws depend only on the number of negatives, never on distances)
    and run the same selection code, so a triplet can differ only if the two kernels' distance rows differ. For
    such queries both kernels' rows are recomputed (``rows_of``): the check passes if they agree within ``tol``
    (same +inf pattern), i.e. the difference is two candidates tied to within rounding.
    """
    by_query = {t.query: t for t in core}
    other_by_query = {t.query: t for t in other}
    worst, differing = triplet_differences(by_query, other_by_query)
    negatives = sum(len(t.negatives) for t in core)
    detail = (f"{len(core)} vs {len(other)} triplets, {negatives} core negatives; "
              f"{len(core) - len(differing)} identical, largest distance difference {worst:.2e} (tol {tol:g})")
    ok = worst <= tol
    if differing:
        core_rows, other_rows = rows_of(np.asarray(differing))
        same_inf = bool(torch.equal(torch.isinf(core_rows), torch.isinf(other_rows)))
        finite = torch.isfinite(core_rows) & torch.isfinite(other_rows)
        row_diff = float((core_rows.double() - other_rows.double()).abs()[finite].max())
        ok = ok and same_inf and row_diff <= tol
        shown = [
            describe_difference(by_query.get(query), other_by_query.get(query), query, core_rows[number].double())
            for number, query in enumerate(differing[:3])
        ]
        detail += (f"; {len(differing)} differ, their full distance rows agree to {row_diff:.2e} with the same +inf "
                   f"pattern: {same_inf} -> {'near-ties within rounding' if ok else 'REAL DIFFERENCE'}; "
                   + "; ".join(shown))
    return ok, detail


def triplet_differences(
    by_query: dict[int, Triplet], other_by_query: dict[int, Triplet]
) -> tuple[float, list[int]]:
    """Largest distance difference over the queries whose triplets agree, and the (sorted) queries whose differ."""
    worst = 0.0
    differing: list[int] = []
    for query in sorted(set(by_query) | set(other_by_query)):
        a, b = by_query.get(query), other_by_query.get(query)
        same_set = a is not None and b is not None and np.array_equal(np.sort(a.negatives), np.sort(b.negatives))
        if not same_set or a.positive != b.positive:
            differing.append(query)
            continue
        order_a, order_b = np.argsort(a.negatives), np.argsort(b.negatives)  # same set, possibly tied in another order
        worst = max(worst, abs(a.positive_distance - b.positive_distance),
                    float(np.max(np.abs(a.negative_distances[order_a] - b.negative_distances[order_b]))))
    return worst, differing


def describe_difference(a: Triplet | None, b: Triplet | None, query: int, row: torch.Tensor) -> str:
    """One differing query's two triplets and the core distances of the disputed references, for the output."""
    describe_a = "none" if a is None else f"pos {a.positive} neg {sorted(a.negatives.tolist())}"
    describe_b = "none" if b is None else f"pos {b.positive} neg {sorted(b.negatives.tolist())}"
    disputed = []
    if a is not None and b is not None:
        disputed = sorted(set(a.negatives.tolist()) ^ set(b.negatives.tolist()))
        if a.positive != b.positive:
            disputed += [a.positive, b.positive]
    values = ", ".join(f"{r}: {row[r].item():.7f}" for r in disputed)
    return (f"query {query}: core {describe_a} / yardstick {describe_b}"
            + (f" (disputed, core distances: {values})" if values else ""))


def load_nordland(root: Path) -> tuple[np.ndarray, np.ndarray]:
    """Patch-normalised descriptors of summer and winter (all frames)."""
    summer = describe(load_traversal(root / "summer", "reference")).descriptors
    winter = describe(load_traversal(root / "winter", "query")).descriptors
    return np.asarray(summer, dtype=np.float32), np.asarray(winter, dtype=np.float32)


def timed_repeats(fn: Callable[[], tuple[float, list[Triplet]]], repeats: int) -> tuple[list[float], list[Triplet]]:
    """Seconds of ``repeats`` runs of ``fn`` after one warm-up run, and the last run's triplets."""
    fn()  # warm-up
    times, triplets = [], []
    for _ in range(repeats):
        seconds, triplets = fn()
        times.append(seconds)
    return times, triplets


@dataclass
class Bench:
    """The training split, its mining setting, the transformed features and the epoch's query order."""

    summer: np.ndarray
    winter: np.ndarray
    reference: Traversal
    query: Traversal
    spec: SequenceSpec
    setting: dict
    query_feat: torch.Tensor
    reference_feat: torch.Tensor
    order: np.ndarray

    @property
    def query_starts(self) -> np.ndarray:
        """Start frame of each query's window (-1 where it has none)."""
        return self.setting["query_starts"]

    def epoch(self, kernel: DistanceRows, order: np.ndarray) -> tuple[float, list[Triplet]]:
        """One epoch of mining with ``kernel`` over the queries of ``order`` (see ``mine_epoch``)."""
        return mine_epoch(kernel, self.setting, order, self.query_feat, self.reference_feat)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line: data folder, threads, repetitions, timing scope and whether to run the short training."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data",
                        help="folder holding nordland_64x32/{summer,winter} (default: ../shared/data from the repo root)")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="torch and numba threads (default: all cores)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repetitions of the core epoch (default 3, at least 1)")
    parser.add_argument("--scope", choices=("auto", "epoch", "subset"), default="auto",
                        help=f"what the two miners are timed on: a full epoch, the first {SUBSET} queries, or auto "
                             f"(the subset when the yardstick epoch would take over {YARDSTICK_BUDGET_S:.0f} s; default)")
    parser.add_argument("--skip-training", action="store_true", help="leave out the short real training")
    return parser.parse_args(argv)


def set_threads(threads: int) -> None:
    """Use ``threads`` torch and numba threads and print the machine and library versions."""
    use_threads(threads)  # the one policy: the library re-asserts it, so a bare torch count would not hold
    print(f"CPU: {cpu_model()} ({os.cpu_count()} logical CPUs); torch {torch.__version__} threads={torch.get_num_threads()}; "
          f"numba {numba.__version__} threads={numba.get_num_threads()}")


def prepare(root: Path) -> Bench:
    """Describe Nordland, cut the training split, pass it through a fresh FrameTransform; print the setting."""
    tick = time.perf_counter()
    summer, winter = load_nordland(root)
    print(f"data: {root} (summer reference, winter query), described in {time.perf_counter() - tick:.1f} s")

    reference = Traversal.from_descriptors(summer, "summer").slice_frames(*TRAIN_FRAMES)
    query = Traversal.from_descriptors(winter, "winter").slice_frames(*TRAIN_FRAMES)
    spec = SequenceSpec(LENGTH)
    query_starts = window_starts(query.segment_ids, spec.length, spec.offset, spec.boundary)
    setting = {
        "query_starts": query_starts,
        "positives": ground_truth_within_radius(query, reference, parse_radius("1f")),
        "near": ground_truth_within_radius(query, reference, parse_radius("4f")),
    }
    model = FrameTransform(TransformConfig(summer.shape[1]), seed=0).eval()
    with torch.no_grad():
        query_feat = model(torch.as_tensor(query.descriptors))
        reference_feat = model(torch.as_tensor(reference.descriptors))
    with_window = np.flatnonzero(query_starts >= 0)
    order = np.random.default_rng(SEED).permutation(with_window)
    print(f"setting: frames [{TRAIN_FRAMES[0]}, {TRAIN_FRAMES[1]}): {len(reference)} reference x {len(query)} query frames, "
          f"L={LENGTH} centred/drop, positives <= 1f, negatives > 4f, {MiningConfig()}; features "
          f"{tuple(query_feat.shape)} from a fresh FrameTransform(2048, seed=0)")
    return Bench(summer, winter, reference, query, spec, setting, query_feat, reference_feat, order)


def choose_scope(bench: Bench, yard_kernel: DistanceRows, scope_arg: str) -> np.ndarray:
    """Warm the yardstick up, estimate its epoch, and pick (and print) the queries both miners are timed on."""
    order = bench.order
    warm_s, _ = bench.epoch(yard_kernel, order[:WARMUP_QUERIES])
    estimate = warm_s / WARMUP_QUERIES * len(order)
    if scope_arg == "subset" or (scope_arg == "auto" and estimate > YARDSTICK_BUDGET_S):
        timed_order = order[:SUBSET]
        why = "--scope subset" if scope_arg == "subset" else f"the yardstick epoch would take about {estimate:.0f} s"
        scope = (f"SUBSET: {why}, so both miners are timed on the same first {SUBSET} queries of the epoch order "
                 f"(not a full epoch)")
    else:
        timed_order = order
        scope = (f"full epoch: {len(order)} training queries with a window, chunks of {CHUNK} "
                 f"(yardstick estimate from the warm-up: {estimate:.0f} s)")
    print(f"timed: {scope}\n")
    return timed_order


def check_triplets(
    bench: Bench, core_kernel: DistanceRows, yard_kernel: DistanceRows, core: list[Triplet], yard: list[Triplet]
) -> bool:
    """Compare the two miners' triplets (recomputing distance rows where they differ) and print the verdict."""

    def rows_of(rows: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            starts = bench.query_starts[rows]
            return (core_kernel(bench.query_feat, bench.reference_feat, starts),
                    yard_kernel(bench.query_feat, bench.reference_feat, starts))

    ok, detail = compare(core, yard, rows_of)
    print(f"same triplets (core vs yardstick): {ok} ({detail})")
    return ok


def time_kernel_alone(bench: Bench, core_kernel: DistanceRows, timed_order: np.ndarray, repeats: int) -> None:
    """Time the core kernel call on one chunk of the timed queries (first call is warm-up) and print its median."""
    kernel_times = []
    chunk_starts = bench.query_starts[timed_order[:CHUNK]]
    with torch.no_grad():
        for number in range(repeats + 1):
            tick = time.perf_counter()
            core_kernel(bench.query_feat, bench.reference_feat, chunk_starts)
            if number:  # the first call is the warm-up
                kernel_times.append(time.perf_counter() - tick)
    kernel_median = statistics.median(kernel_times)
    print(f"  of which the core kernel call alone ({len(chunk_starts)} query windows at once): median "
          f"{kernel_median:.3f} s; the rest is the miner's per-query selection, shared by both miners")


def print_full_epoch(bench: Bench, core_kernel: DistanceRows, timed_order: np.ndarray, yard_s: float, repeats: int) -> None:
    """After a subset timing: time the core's full epoch and print it beside the yardstick's extrapolated epoch."""
    order = bench.order
    full_times, _ = timed_repeats(lambda: bench.epoch(core_kernel, order), repeats)
    full_median = statistics.median(full_times)
    print(f"for information, core mining per full epoch ({len(order)} queries): median {full_median:.3f} s "
          f"(min {min(full_times):.3f} s, n={len(full_times)}, {1e3 * full_median / len(order):.3f} ms/query); "
          f"yardstick extrapolated from the subset: {yard_s / len(timed_order) * len(order):.0f} s "
          f"(~{yard_s / len(timed_order) * len(order) / full_median:.0f}x)")


def bench_miners(bench: Bench, scope_arg: str, repeats: int) -> bool:
    """Time the core and yardstick miners, check they agree and print the timings and ratio; True if they agree."""
    core_kernel = seqmatch_rows(bench.spec, bench.reference.segment_ids)
    yard_kernel = yardstick_rows(bench.spec, bench.reference.segment_ids)
    timed_order = choose_scope(bench, yard_kernel, scope_arg)
    core_times, core_triplets = timed_repeats(lambda: bench.epoch(core_kernel, timed_order), repeats)
    yard_s, yard_triplets = bench.epoch(yard_kernel, timed_order)
    ok = check_triplets(bench, core_kernel, yard_kernel, core_triplets, yard_triplets)

    core_median = statistics.median(core_times)
    label = "per epoch" if timed_order is bench.order else f"per {len(timed_order)} queries"
    print(f"core mining {label}:      median {core_median:8.3f} s  (min {min(core_times):.3f} s, n={len(core_times)}, "
          f"{1e3 * core_median / len(timed_order):.3f} ms/query)")
    time_kernel_alone(bench, core_kernel, timed_order, repeats)
    print(f"yardstick mining {label}: {yard_s:8.3f} s  (n=1, {1e3 * yard_s / len(timed_order):.3f} ms/query)")
    ratio = yard_s / core_median
    print(f"ratio yardstick / core = {ratio:.1f}x (target >= 20x: {'met' if ratio >= 20 else 'NOT met'})")
    if timed_order is not bench.order:
        print_full_epoch(bench, core_kernel, timed_order, yard_s, repeats)
    if not ok:
        print("ERROR: the core and yardstick miners disagree", file=sys.stderr)
    return ok


def short_training(bench: Bench) -> None:
    """Two epochs of real SeqMatchNet training into a temporary folder; print each epoch's times from its history."""
    print("\nshort real training: train_seqmatchnet, default SeqMatchNetSettings except epochs=2, "
          f"validation frames [{VAL_FRAMES[0]}, {VAL_FRAMES[1]})")
    data = TrainingData(
        reference=bench.reference,
        query=bench.query,
        val_reference=Traversal.from_descriptors(bench.summer, "summer").slice_frames(*VAL_FRAMES),
        val_query=Traversal.from_descriptors(bench.winter, "winter").slice_frames(*VAL_FRAMES),
        positive_radius=parse_radius("1f"),
        negative_radius=parse_radius("4f"),
        val_radius=parse_radius("1f"),
    )
    with tempfile.TemporaryDirectory(prefix="bench-mining-") as folder:
        tick = time.perf_counter()
        result = train_seqmatchnet(data, TransformConfig(data.dim), SeqMatchNetSettings(epochs=2), Path(folder) / "run")
        total = time.perf_counter() - tick
    print(f"  epoch 0 (untrained, fresh transform): val R@1 {result.history[0].recall[1]:.3f}")
    for record in result.history[1:]:
        share = record.mining_seconds / record.epoch_seconds if record.epoch_seconds else float("nan")
        print(f"  epoch {record.epoch}: {record.epoch_seconds:7.2f} s/epoch, mining {record.mining_seconds:6.3f} s "
              f"({100 * share:.2f}% of the epoch), features {record.features_seconds:6.3f} s; "
              f"{record.queries_used} queries used, {record.queries_skipped} skipped, loss {record.loss:.4f}, "
              f"val R@1 {record.recall[1]:.3f}")
    print(f"  whole run (epoch-0 validation, 2 epochs, checkpoints): {total:.1f} s")


def main(argv: list[str] | None = None) -> int:
    """Benchmark the two miners on Nordland, then (unless skipped) a short training; 1 if the miners disagree."""
    args = parse_args(argv)
    root = args.data / "nordland_64x32"
    if not ((root / "summer").is_dir() and (root / "winter").is_dir()):
        print(f"error: {root}/summer and {root}/winter not found; pass --data pointing at the shared data folder",
              file=sys.stderr)
        return 2
    repeats = max(1, args.repeats)
    set_threads(args.threads)
    bench = prepare(root)
    ok = bench_miners(bench, args.scope, repeats)
    if not args.skip_training:
        short_training(bench)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
