"""What proving a map's content costs: writing (digests computed as the map is sealed), opening again (a stat per
file), opening for the first time on this machine (one streamed read), and ``seqvpr map check`` (every file read and
every row checked), each as a ratio to a yardstick timed in the same run.

Run from the repository root (CPU; about 3 minutes and 2.5 GB of disk in ``--work`` at 1M frames):

    .venv/bin/python bench/bench_identity.py --work runs/bench-identity [--frames 1000000]

Yardsticks: ``np.save`` of the same rows (for the write), ``np.load(..., mmap_mode="r")`` of ``descriptors.npy``
(for an open), and one plain read of the map's files (for a first open and the check).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import cpu_model

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from seqvpr.data.traversal import Traversal
from seqvpr.maps.build import map_sources
from seqvpr.maps.files import MapInfo, open_map, write_map

DIM = 256


def timed(function, repeat: int = 1) -> float:
    """The best of ``repeat`` wall times of ``function()``, in seconds."""
    best = float("inf")
    for _ in range(repeat):
        started = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - started)
    return best


def read_all(folder: Path) -> None:
    """Every file of a folder read once, in 4 MiB chunks (what a first open's streamed digest must at least do)."""
    for path in folder.iterdir():
        with open(path, "rb") as handle:
            while handle.read(1 << 22):
                pass


def unit_rows(n: int, seed: int = 0) -> np.ndarray:
    rows = np.random.default_rng(seed).standard_normal((n, DIM), dtype=np.float32)
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def measure(work: Path, frames: int) -> list[tuple[str, float, float]]:
    """(what, seconds, yardstick seconds) of each step at ``frames`` rows."""
    from seqvpr.maps.check import check_map

    rows = unit_rows(frames)
    traversal = Traversal.from_descriptors(rows, "bench")
    info = MapInfo(frames, DIM, "float32", True, {"descriptor": "file"}, map_sources([traversal], ["bench"]))
    target = work / "map"
    shutil.rmtree(target, ignore_errors=True)
    saved = timed(lambda: np.save(work / "plain.npy", rows))
    written = timed(lambda: write_map(target, traversal, info))
    bare_open = timed(lambda: np.load(target / "descriptors.npy", mmap_mode="r"), repeat=20)
    warm_open = timed(lambda: open_map(target), repeat=20)
    one_read = timed(lambda: read_all(target))
    os.environ["SEQVPR_CACHE"] = tempfile.mkdtemp(dir=work)  # nothing remembered: a first open on this machine
    cold_open = timed(lambda: open_map(target))
    checked = timed(lambda: check_map(target))
    return [("write the map (digests sealed)", written, saved), ("open again (a stat a file)", warm_open, bare_open),
            ("first open on a machine (one streamed read)", cold_open, one_read),
            ("seqvpr map check (read all, rows checked)", checked, one_read)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=1_000_000)
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    os.environ["SEQVPR_CACHE"] = tempfile.mkdtemp(dir=args.work)
    results = measure(args.work, args.frames)
    yardsticks = ["np.save of the rows", "np.load mmap of descriptors.npy", "one plain read of the files",
                  "one plain read of the files"]
    print(f"{args.frames:,} frames x {DIM}-D float32, {cpu_model()}\n")
    print("| step | seconds | yardstick | yardstick seconds | ratio |\n|---|---:|---:|---:|---:|")
    for (what, seconds, base), name in zip(results, yardsticks):
        print(f"| {what} | {seconds:.4f} | {name} | {base:.4f} | {seconds / base:.2f}x |")


if __name__ == "__main__":
    main()
