"""Benchmark of the sequence-distance kernel against conv2d, a plain copy and shifted sums.

Run from the repository root:

    .venv/bin/python bench/bench_kernel.py [--size 4000] [--repeats 7] [--threads N] [--lengths 5 20]

For each window length L it times, on one seeded random float32 distance matrix of ``size x size``:

* the seqvpr kernel as users call it for a whole matrix,
  ``sequence_distance_matrix(d, SequenceSpec(L), inplace=True)`` (the fused in-place CPU pass), on a fresh copy
  of the matrix each repetition (the copy is made outside the timed region); and, for information,
  ``inplace=False`` (the torch strided reduction);
* the identity-kernel conv2d formulation of the reference code,
  ``conv2d(d[None, None], eye(L)[None, None]) / L``;
* one copy of the matrix: ``d.clone()`` (fresh allocation) and ``buf.copy_(d)`` (preallocated buffer);
* plain shifted sums, ``acc = d[:n1, :n1].clone(); acc += d[k:k+n1, k:k+n1]`` for k = 1..L-1.

Each operation is run once or more as warm-up, then timed with ``time.perf_counter``; the median and the minimum
are printed. Slow operations (conv2d at large L) get fewer repetitions so the whole run stays near a minute.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

from _common import cpu_model
import torch

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numba

from seqvpr.threads import use_threads
from seqvpr.sequences.matching import frame_distances, sequence_distance_matrix
from seqvpr.sequences.windows import SequenceSpec

#: seconds of timed work allowed per measurement; slow operations run fewer repetitions (at least 3)
TIME_BUDGET_S = 4.0
MIN_REPEATS = 3


def timed(fn: Callable[[], object], repeats: int, setup: Callable[[], object] | None = None, warmup: int = 1) -> list[float]:
    """Wall times (seconds) of ``fn`` over ``repeats`` runs after ``warmup`` runs; ``setup`` runs untimed before each."""
    for _ in range(warmup):
        if setup is not None:
            setup()
        fn()
    times: list[float] = []
    spent = 0.0
    for number in range(repeats):
        if number >= MIN_REPEATS and spent > TIME_BUDGET_S:
            break
        if setup is not None:
            setup()
        start = time.perf_counter()
        fn()
        elapsed = time.perf_counter() - start
        times.append(elapsed)
        spent += elapsed
    return times


def make_matrix(size: int, seed: int = 0, dim: int = 64) -> torch.Tensor:
    """Euclidean distances between seeded random unit vectors: a realistic float32 frame-distance matrix."""
    gen = torch.Generator().manual_seed(seed)
    query = torch.nn.functional.normalize(torch.randn(size, dim, generator=gen), dim=1)
    reference = torch.nn.functional.normalize(torch.randn(size, dim, generator=gen), dim=1)
    return frame_distances(query, reference).contiguous()


def conv2d_means(d: torch.Tensor, length: int) -> torch.Tensor:
    """The reference code's formulation: an identity kernel slid over the matrix, divided by L."""
    kernel = torch.eye(length, dtype=d.dtype)[None, None]
    return torch.nn.functional.conv2d(d[None, None], kernel)[0, 0] / length


def shifted_sums(d: torch.Tensor, length: int) -> torch.Tensor:
    """Window sums by L - 1 in-place additions of shifted views (no division)."""
    n1 = min(d.shape) - length + 1
    acc = d[:n1, :n1].clone()
    for k in range(1, length):
        acc += d[k : k + n1, k : k + n1]
    return acc


def fmt(times: list[float]) -> tuple[str, str]:
    """Median and minimum of ``times`` in milliseconds, formatted for the table's columns."""
    return f"{1e3 * statistics.median(times):9.2f}", f"{1e3 * min(times):9.2f}"


LABELS = {
    "kernel": "(a) seqvpr kernel, inplace=True (fused)",
    "strided": "(a') seqvpr, inplace=False (torch strided)",
    "conv2d": "(b) conv2d identity kernel / L",
    "shifted": "(d) shifted sums (L-1 adds)",
    "clone": "(c) copy: d.clone()",
    "copy_": "(c) copy: buf.copy_(d) (preallocated)",
}


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line: matrix size, repetitions, threads, window lengths and seed."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=4000, help="matrix side (default 4000)")
    parser.add_argument("--repeats", type=int, default=7, help="timed repetitions per operation (default 7)")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="torch and numba threads (default: all cores)")
    parser.add_argument("--lengths", type=int, nargs="+", default=[5, 20], help="window lengths (default 5 20)")
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args(argv)


def print_setup(d: torch.Tensor, repeats: int) -> None:
    """The machine, library versions and thread counts, and the matrix measured, so a run can be compared."""
    n = d.shape[0]
    print(f"CPU: {cpu_model()} ({os.cpu_count()} logical CPUs); torch {torch.__version__} threads={torch.get_num_threads()}; "
          f"numba {numba.__version__} threads={numba.get_num_threads()}")
    print(f"matrix: {n} x {n} float32 ({d.numel() * 4 / 2**20:.0f} MiB), repeats={repeats} (warm-up first)\n")


def kernel_matches_conv2d(d: torch.Tensor, length: int) -> bool:
    """Check once that the in-place kernel equals conv2d on the interior (and +inf outside); print the verdict."""
    n = d.shape[0]
    spec = SequenceSpec(length)
    a = spec.offset
    n1 = n - length + 1
    fused = sequence_distance_matrix(d.clone(), spec, inplace=True)
    reference = conv2d_means(d, length)
    interior = fused[a : a + n1, a : a + n1]
    ok = torch.allclose(interior, reference, rtol=1e-5, atol=1e-5)
    err = (interior.double() - reference.double()).abs().max().item()
    outside_inf = bool(torch.isinf(fused[:a]).all()) and bool(torch.isinf(fused[a + n1 :]).all())
    print(f"L={length:2d}: kernel == conv2d on interior: {ok} (max abs diff {err:.2e}); border rows +inf: {outside_inf}")
    return ok


def time_length(d: torch.Tensor, buf: torch.Tensor, length: int, repeats: int) -> dict[str, list[float]]:
    """Times of the kernel (in place on a fresh copy, and strided), conv2d and shifted sums for one window length."""
    spec = SequenceSpec(length)
    return {
        "kernel": timed(
            lambda: sequence_distance_matrix(buf, spec, inplace=True), repeats, setup=lambda: buf.copy_(d), warmup=2
        ),
        "strided": timed(lambda: sequence_distance_matrix(d, spec, inplace=False), repeats),
        "conv2d": timed(lambda: conv2d_means(d, length), repeats),
        "shifted": timed(lambda: shifted_sums(d, length), repeats),
    }


def print_table(per_length: dict[str, dict[int, list[float]]], lengths: list[int]) -> None:
    """The table of median and minimum milliseconds per operation and window length, with repetition counts."""
    header = f"{'operation':44s}" + "".join(f" | L={L:<2d} median ms |    min ms" for L in lengths)
    print("\n" + header)
    print("-" * len(header))
    for key, label in LABELS.items():
        cells = "".join(" | {:>15s} | {:>9s}".format(*fmt(per_length[key][L])) for L in lengths)
        reps = "/".join(str(len(per_length[key][L])) for L in lengths)
        print(f"{label:44s}{cells}   (n={reps})")


def print_ratios(per_length: dict[str, dict[int, list[float]]], lengths: list[int]) -> None:
    """Median ratios per window length against the targets (conv2d >= 50x slower, <= 3x a preallocated copy)."""
    print("\nratios (medians):")
    for length in lengths:
        med = {key: statistics.median(per_length[key][length]) for key in per_length}
        conv_ratio = med["conv2d"] / med["kernel"]
        into_ratio = med["kernel"] / med["copy_"]
        clone_ratio = med["kernel"] / med["clone"]
        print(
            f"  L={length:2d}: conv2d / kernel = {conv_ratio:6.1f}x (target >= 50x: {'met' if conv_ratio >= 50 else 'NOT met'});"
            f"  kernel / copy_ (preallocated) = {into_ratio:4.2f}x (target <= 3x: {'met' if into_ratio <= 3 else 'NOT met'});"
            f"  kernel / clone = {clone_ratio:4.2f}x;  strided / kernel = {med['strided'] / med['kernel']:5.1f}x;"
            f"  shifted / kernel = {med['shifted'] / med['kernel']:4.1f}x"
        )


def main(argv: list[str] | None = None) -> int:
    """Time every operation for each window length and print the table and ratios; 1 if kernel and conv2d disagree."""
    args = parse_args(argv)
    use_threads(args.threads)  # the one policy: the library re-asserts it, so a bare torch count would not hold
    d = make_matrix(args.size, args.seed)
    buf = torch.empty_like(d)
    print_setup(d, args.repeats)

    copy_clone = timed(lambda: d.clone(), args.repeats)
    copy_into = timed(lambda: buf.copy_(d), args.repeats)
    per_length: dict[str, dict[int, list[float]]] = {key: {} for key in LABELS}
    for length in args.lengths:
        if not kernel_matches_conv2d(d, length):
            print("ERROR: kernel and conv2d disagree", file=sys.stderr)
            return 1
        for key, times in time_length(d, buf, length, args.repeats).items():
            per_length[key][length] = times
        per_length["clone"][length] = copy_clone
        per_length["copy_"][length] = copy_into

    print_table(per_length, args.lengths)
    print_ratios(per_length, args.lengths)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
