"""Loop closures and growing maps at scale, each against a yardstick measured in the same run:

- ``loops``: ``find_loops`` over a drive of N random unit frames (D dimensions, L = 5, 100 frames excluded),
  exhaustive and with ``--shortlist S``, against one triangular GEMM of the same shapes (each block of rows
  against every row before it: the distance products the exhaustive search cannot avoid; past 40k frames timed on
  a sample of its blocks and scaled), and the streaming ``LoopDetector`` over its last frames (ms a frame).
- ``add``: ``seqvpr map add`` of A frames to a map of N frames against building the N + A map whole, from
  descriptor files (nothing to describe: the cost is the map's own writing, checking and digesting).

Run from the repository root (CPU; about 5 minutes at the default sizes):

    .venv/bin/python bench/bench_loops.py --work runs/loops-bench [--sizes 10000,100000,1000000] [--dim 256]
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


def triangular_gemm_seconds(rows: np.ndarray, block: int = 2048, every: int = 1) -> float:
    """Every block of rows times every row before its end: the lower triangle of the Gram matrix, in blocks. With
    ``every`` > 1 only every such block is multiplied and the time scaled by the triangle's products over the
    products done (at 1M frames the whole triangle takes most of an hour here)."""
    import torch

    tensor = torch.from_numpy(rows)
    done = total = 0
    started = time.perf_counter()
    for number, begin in enumerate(range(0, len(rows), block)):
        end = min(begin + block, len(rows))
        total += (end - begin) * end
        if number % every == every - 1:
            torch.mm(tensor[begin:end], tensor[:end].T)
            done += (end - begin) * end
    return (time.perf_counter() - started) * total / done


def detector_ms(rows: np.ndarray, settings, work: Path) -> float:
    """The streaming detector's median ms a frame over the drive's last frames, the rest entered as its past
    (what a restored detector holds; a shortlist's index grown over it before the timing)."""
    from seqvpr.localization.loop_detector import LoopDetector

    n = len(rows)
    detector = LoopDetector(settings, folder=work)
    for i in range(n - 20):
        detector._enter(rows[i], None, None)
    detector.since_break = n - 20
    detector.ring = []
    if settings.shortlist:
        detector.neighbours.extend(np.full((n - 20, settings.shortlist), -1, np.int64))
    else:  # the exhaustive detector's last L distance rows, as it would hold them
        detector.since_break = 0
    timed = []
    for i in range(n - 20, n):
        started = time.perf_counter()
        detector.update(rows[i])
        timed.append(time.perf_counter() - started)
    return float(np.median(timed[5:])) * 1e3


def run_loops(args) -> list[str]:
    from seqvpr.data.traversal import Traversal
    from seqvpr.localization.loops import LoopSettings, find_loops, make_drive

    lines = ["| frames | D | how | loops s | triangular GEMM s | loops / GEMM | LoopDetector ms a frame (at the end) |",
             "|---:|---:|---|---:|---:|---:|---:|"]
    for n in args.sizes:
        rows = unit_rows(n, args.dim, 0)
        drive = make_drive([Traversal("drive", np.arange(n), np.zeros(n, np.int64), rows, source="drive")])
        every = max(1, n // 40_000)
        gemm = triangular_gemm_seconds(rows, every=every)
        gemm_text = f"{gemm:.1f}" + (f" (1 block in {every}, scaled)" if every > 1 else "")
        for shortlist in ([0] if n <= args.exhaustive_up_to else []) + [args.shortlist]:
            settings = LoopSettings(seq_len=5, exclude="100f", shortlist=shortlist)
            started = time.perf_counter()
            find_loops(drive, settings)
            loops = time.perf_counter() - started
            per_frame = detector_ms(rows, settings, args.work)
            how = f"--shortlist {shortlist} (hnsw:32)" if shortlist else "exhaustive"
            lines.append(f"| {n:,} | {args.dim} | {how} | {loops:.1f} | {gemm_text} | {loops / gemm:.3f} | "
                         f"{per_frame:.1f} |")
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
    parser.add_argument("--shortlist", type=int, default=10)
    parser.add_argument("--exhaustive-up-to", type=int, default=100_000, help="larger drives: the shortlist only")
    parser.add_argument("--map-frames", type=int, default=200_000)
    parser.add_argument("--added", type=int, default=10_000)
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    print(cpu_model(), flush=True)
    for part in args.parts.split(","):
        print("\n".join({"loops": run_loops, "add": run_add}[part](args)), flush=True)


if __name__ == "__main__":
    main()
