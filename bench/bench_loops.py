"""Loop closures and growing maps at scale, each against a yardstick measured in the same run:

- ``loops``: ``find_loops`` over a drive of N random unit frames (D dimensions, L = 5, 100 frames excluded)
  against one triangular GEMM of the same shapes (each block of rows against every row before it: the distance
  products the search cannot avoid), and the streaming ``LoopDetector`` over its last frames (ms a frame).
- ``add``: ``seqvpr map add`` of A frames to a map of N frames against building the N + A map whole, from
  descriptor files (nothing to describe: the cost is the map's own writing, checking and digesting).

Run from the repository root (CPU; about 5 minutes at the default sizes):

    .venv/bin/python bench/bench_loops.py --work runs/loops-bench [--sizes 10000,100000] [--dim 256]
    .venv/bin/python bench/bench_loops.py --work runs/loops-bench --parts add --map-frames 1000000 --added 10000
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from _common import cpu_model

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))


def unit_rows(n: int, dim: int, seed: int) -> np.ndarray:
    rows = np.random.default_rng(seed).standard_normal((n, dim), dtype=np.float32)
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def triangular_gemm_seconds(rows: np.ndarray, block: int = 2048) -> float:
    """Every block of rows times every row before its end: the lower triangle of the Gram matrix, in blocks."""
    import torch

    tensor = torch.from_numpy(rows)
    started = time.perf_counter()
    for begin in range(0, len(rows), block):
        end = min(begin + block, len(rows))
        torch.mm(tensor[begin:end], tensor[:end].T)
    return time.perf_counter() - started


def run_loops(args) -> list[str]:
    from seqvpr.data.traversal import Traversal
    from seqvpr.localization.loop_detector import LoopDetector
    from seqvpr.localization.loops import LoopSettings, find_loops, make_drive

    lines = [f"| frames | D | loops s | triangular GEMM s | loops / GEMM | LoopDetector ms a frame (at the end) |",
             "|---:|---:|---:|---:|---:|---:|"]
    settings = LoopSettings(seq_len=5, exclude="100f")
    for n in args.sizes:
        rows = unit_rows(n, args.dim, 0)
        drive = make_drive([Traversal("drive", np.arange(n), np.zeros(n, np.int64), rows, source="drive")])
        gemm = triangular_gemm_seconds(rows)
        started = time.perf_counter()
        find_loops(drive, settings)
        loops = time.perf_counter() - started
        detector = LoopDetector(settings, folder=args.work)
        for i in range(n - 20):  # the past, entered without matching (what a restored detector holds)
            detector._enter(rows[i], None, None)
            detector.since_break = 0
        detector.ring = []
        timed = []
        for i in range(n - 20, n):
            started = time.perf_counter()
            detector.update(rows[i])
            timed.append(time.perf_counter() - started)
        per_frame = float(np.median(timed[5:])) * 1e3
        lines.append(f"| {n:,} | {args.dim} | {loops:.1f} | {gemm:.1f} | {loops / gemm:.2f} | {per_frame:.1f} |")
        print(lines[-1], flush=True)
    return lines


def run_add(args) -> list[str]:
    from seqvpr.data.sources import save_traversal_npz
    from seqvpr.data.traversal import Traversal
    from seqvpr.maps import build_map
    from seqvpr.maps.grow import add_to_map

    work = args.work / "add"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    base, extra = unit_rows(args.map_frames, args.dim, 1), unit_rows(args.added, args.dim, 2)
    for name, rows in (("base", base), ("extra", extra)):
        save_traversal_npz(work / f"{name}.npz", Traversal(name, np.arange(len(rows)), np.zeros(len(rows), np.int64),
                                                            rows, source=name))
    del base, extra
    lines = ["| map frames | added | D | dtype | map add s | build whole s | add / build |", "|---:|---:|---:|---|---:|---:|---:|"]
    for dtype in ("float32", "float16"):
        build_map([str(work / "base.npz")], work / f"grown-{dtype}", dtype=dtype)
        started = time.perf_counter()
        try:
            add_to_map(work / f"grown-{dtype}", [str(work / "extra.npz")])
        except Exception as error:  # sq8: random frames outside the map's range are refused
            print(f"{dtype}: {error}", flush=True)
            continue
        added = time.perf_counter() - started
        started = time.perf_counter()
        build_map([str(work / "base.npz"), str(work / "extra.npz")], work / f"whole-{dtype}", dtype=dtype)
        whole = time.perf_counter() - started
        lines.append(f"| {args.map_frames:,} | {args.added:,} | {args.dim} | {dtype} | {added:.2f} | {whole:.2f} | "
                     f"{added / whole:.3f} |")
        print(lines[-1], flush=True)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("runs/loops-bench"))
    parser.add_argument("--parts", default="loops,add")
    parser.add_argument("--sizes", default="10000,100000", type=lambda t: [int(v) for v in t.split(",")])
    parser.add_argument("--dim", type=int, default=256)
    parser.add_argument("--map-frames", type=int, default=200_000)
    parser.add_argument("--added", type=int, default=10_000)
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    print(cpu_model(), flush=True)
    for part in args.parts.split(","):
        print("\n".join({"loops": run_loops, "add": run_add}[part](args)), flush=True)


if __name__ == "__main__":
    main()
