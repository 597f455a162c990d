"""What the input checks cost: the paths every run takes through them (reading a traversal file and a .mat,
building and opening a map, a match, a localiser frame), timed for two source trees in one session, so the ratio
new / old says whether checking arguments, outputs, positions and MAT elements changed anything beyond noise.

Run from the repository root (CPU, about 3 minutes):

    .venv/bin/python bench/bench_checks.py --old /path/to/old/src --new src --work runs/bench-checks

Each tree runs in its own process (``PYTHONPATH`` set to it), ``--rounds`` times, alternating; the table gives each
path's median over the rounds (best of ``--repeats`` a round) and the ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

N_REFERENCE, N_QUERY, DIM = 20_000, 2_000, 256


def write_inputs(work: Path) -> None:
    """A reference and a query traversal file (positions along a route) and the reference as a .mat."""
    import scipy.io

    rng = np.random.default_rng(0)
    work.mkdir(parents=True, exist_ok=True)
    for name, n in (("ref", N_REFERENCE), ("qry", N_QUERY)):
        rows = rng.standard_normal((n, DIM)).astype(np.float32)
        np.savez(work / f"{name}.npz", descriptors=rows, positions=np.c_[np.arange(n) * 2.0, np.zeros(n)] + 500_000,
                 timestamps=np.arange(n) * 0.1)
        if name == "ref":
            scipy.io.savemat(work / "ref.mat", {"Y": rows})


def timed(function, repeats: int) -> float:
    """Best of ``repeats`` runs, in milliseconds."""
    best = float("inf")
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - started)
    return best * 1e3


def measure(work: Path, repeats: int) -> dict[str, float]:
    """Milliseconds a path, with the seqvpr on ``sys.path``."""
    import shutil

    import seqvpr

    ref, qry, mat = str(work / "ref.npz"), str(work / "qry.npz"), str(work / "ref.mat")
    maps = work / f"maps-{os.getpid()}"

    def build():
        shutil.rmtree(maps, ignore_errors=True)
        seqvpr.build_map([ref], maps)

    build()
    saved = seqvpr.open_map(maps)
    localizer = seqvpr.Localizer.open(saved, seq_len=5)
    frames = seqvpr.load_traversal(qry, "query").descriptors[:200]

    def localise():
        for row in frames:
            localizer.update(row)

    query = seqvpr.load_traversal(qry, "query")
    times = {
        "load a traversal file (20k x 256)": timed(lambda: seqvpr.load_traversal(ref, "reference"), repeats),
        "load a .mat (20k x 256)": timed(lambda: seqvpr.load_traversal(mat, "reference"), repeats),
        "build a map (20k frames)": timed(build, repeats),
        "open a map": timed(lambda: seqvpr.open_map(maps), repeats),
        "match 2k x 20k, L = 5": timed(lambda: seqvpr.match(saved.frames, query, seq_len=5), repeats),
        "localiser, 200 frames": timed(localise, repeats),
        "evaluate": timed(lambda: seqvpr.evaluate(seqvpr.match(ref, qry, "single"), radius="10m"), repeats),
    }
    shutil.rmtree(maps, ignore_errors=True)
    return times


def run_tree(source: str, work: Path, repeats: int) -> dict[str, float]:
    """``measure`` in a fresh process importing seqvpr from ``source``."""
    env = {**os.environ, "PYTHONPATH": str(Path(source).resolve()) + os.pathsep + str(Path(__file__).parent)}
    done = subprocess.run([sys.executable, __file__, "--measure", "--work", str(work), "--repeats", str(repeats)],
                          env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--old", help="the old tree's src folder")
    parser.add_argument("--new", default="src", help="the new tree's src folder")
    parser.add_argument("--work", type=Path, default=Path("runs/bench-checks"))
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--measure", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(args.work, args.repeats)))
        return
    write_inputs(args.work)
    rounds: dict[str, list[dict[str, float]]] = {"old": [], "new": []}
    for _ in range(args.rounds):
        for name, source in (("old", args.old), ("new", args.new)):
            rounds[name].append(run_tree(source, args.work, args.repeats))
    print(f"| path (ms, median of {args.rounds} rounds) | old | new | new / old |\n|---|---:|---:|---:|")
    for path in rounds["new"][0]:
        old, new = (statistics.median(r[path] for r in rounds[name]) for name in ("old", "new"))
        print(f"| {path} | {old:.1f} | {new:.1f} | {new / old:.2f} |")


if __name__ == "__main__":
    main()
