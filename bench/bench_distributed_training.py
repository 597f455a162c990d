"""Training on 1 process against 2 torchrun ranks: wall time as a ratio, and how far the weights are apart.

Run from the repository root (CPU, with ../shared/data beside the repository; about 3 minutes):

    .venv/bin/python bench/bench_distributed_training.py [--epochs 3] [--threads 2] [--work runs/bench-ddp]

The same ``seqvpr train seqmatchnet`` (Nordland 64x32 patch-normalised frames, summer reference, winter query,
train 17:1200, validation 1200:1600, +-1 frame, L = 5, the command's defaults otherwise) runs once alone with
``--threads`` torch threads and once under ``torchrun --standalone --nproc-per-node 2`` with ``--threads / 2``
threads a rank, so both use the same cores. It reports wall seconds, the ratio, the largest absolute weight
difference of the two final states, and whether their mined triplet counts per epoch are the same.
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from _common import cpu_model

NORDLAND = Path(__file__).resolve().parents[2] / "shared" / "data" / "nordland_64x32"


def train_args(out: Path, epochs: int) -> list[str]:
    return ["train", "seqmatchnet", "-r", str(NORDLAND / "summer"), "-q", str(NORDLAND / "winter"),
            "--train-frames", "17:1200", "--val-frames", "1200:1600", "--radius", "1f", "-L", "5",
            "--epochs", str(epochs), "--out", str(out)]


def timed(command: list[str], threads: int) -> float:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    started = time.perf_counter()
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{done.stderr[-2000:]}")
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--work", type=Path, default=Path("runs/bench-ddp"))
    args = parser.parse_args()
    if not NORDLAND.is_dir():
        raise SystemExit(f"{NORDLAND}: the shared Nordland data is needed")
    shutil.rmtree(args.work, ignore_errors=True)
    bin_dir = Path(sys.executable).parent
    seqvpr = shutil.which("seqvpr", path=str(bin_dir))
    one = timed([seqvpr, *train_args(args.work / "one", args.epochs)], args.threads)
    two = timed([str(bin_dir / "torchrun"), "--standalone", "--nproc-per-node", "2", seqvpr,
                 *train_args(args.work / "two", args.epochs)], max(1, args.threads // 2))
    from seqvpr.models import files as ckpt
    from seqvpr.training.state import STATE_JSON

    weights = [ckpt.read_tensors(args.work / run / ckpt.read_json(args.work / run / STATE_JSON)["state_dir"] /
                                 ckpt.MODEL_FILE) for run in ("one", "two")]
    difference = max(float((weights[0][k] - weights[1][k]).abs().max()) for k in weights[0])
    triplets = [[row["triplets"] for row in csv.DictReader(open(args.work / run / "history.csv"))]
                for run in ("one", "two")]
    print(f"CPU: {cpu_model()}; SeqMatchNet, Nordland 17:1200, L = 5, {args.epochs} epochs, {args.threads} threads")
    print("| run | wall | x one process |")
    print("|---|---:|---:|")
    print(f"| one process | {one:.1f} s | 1.00x |")
    print(f"| torchrun, 2 ranks | {two:.1f} s | {two / one:.2f}x |")
    print(f"largest weight difference: {difference:.2e}; same triplets every epoch: {triplets[0] == triplets[1]}")


if __name__ == "__main__":
    main()
