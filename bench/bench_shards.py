"""A sharded map matched by 1 process against 2 torchrun ranks, as a ratio, with the peak memory of a rank.

Run from the repository root (CPU; about 3 minutes and 2 GB more disk in ``--work``, after bench_maps.py made the
map, or it is made here):

    .venv/bin/python bench/bench_shards.py --work runs/bench-maps [--size 1000000] [--threads 2]

The map is ``bench_maps.py``'s (N frames of 256-D float32, D = 256), built with ``seqvpr map build`` and split by
``seqvpr map shard --shards 2``. The same ``seqvpr match --map SHARDED -q QUERY -L 5 --k 1,5,20`` (1,000 query
frames) runs, each under ``/usr/bin/time -v``:

* the yardstick: one process, ``--threads`` torch threads, on the unsharded map;
* one process on the sharded map (it matches both shards in turn);
* ``torchrun --standalone --nproc-per-node 2`` on the sharded map, each rank ``--threads / 2`` threads, so both
  runs use the same cores.

It reports wall seconds, the ratio to the yardstick, and the peak RSS of the largest process (under torchrun the
largest rank), and checks that the three predictions files are identical.

With ``--shortlist S`` it also gives the whole map and every shard a flat faiss index (``seqvpr map index``) and
runs the shortlisted match (``--shortlist S``) alone on the whole map (its own yardstick) and on 2 ranks, and checks
that those two predictions files are identical.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

from _common import cpu_model
from bench_maps import seqvpr_command, timed_cli, write_sources


def match_args(folder: Path, query: Path, out: Path, shortlist: int = 0) -> list[str]:
    extra = ["--shortlist", str(shortlist)] if shortlist else []
    return ["match", "--map", str(folder), "-q", str(query), "-L", "5", "--k", "1,5,20", "--radius", "3m",
            *extra, "--out", str(out)]


def shortlisted_rows(whole: Path, sharded: Path, query: Path, work: Path, shortlist: int, threads: int, torchrun):
    """The shortlisted match alone on the whole map and on 2 ranks over the shards (flat indexes built first)."""
    for folder in (whole, sharded):
        if not (folder / "index.faiss").is_file() and not (folder / "shard-000" / "index.faiss").is_file():
            timed_cli(seqvpr_command("map", "index", folder, "--index", "flat"))
    os.environ["OMP_NUM_THREADS"] = str(threads)
    rows = [(f"one process, unsharded map, shortlist {shortlist}",
             *timed_cli(seqvpr_command(*match_args(whole, query, work / "l1", shortlist))))]
    os.environ["OMP_NUM_THREADS"] = str(max(1, threads // 2))
    rows.append((f"torchrun, 2 ranks x 2 shards, shortlist {shortlist}",
                 *timed_cli([*torchrun, *match_args(sharded, query, work / "l2", shortlist)])))
    same = (work / "l1" / "predictions.csv").read_text() == (work / "l2" / "predictions.csv").read_text()
    return rows, same


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("runs/bench-maps"))
    parser.add_argument("--size", type=int, default=1_000_000)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--shortlist", type=int, default=0, help="also the shortlisted match, S a query frame")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    reference, query = write_sources(args.work, args.size)
    whole, sharded = args.work / f"map_{args.size}", args.work / f"map_{args.size}_2shards"
    if not (whole / "map.json").is_file():
        timed_cli(seqvpr_command("map", "build", reference, "--out", whole))
    if not (sharded / "shards.json").is_file():
        timed_cli(seqvpr_command("map", "shard", whole, "--shards", "2", "--out", sharded))
    os.environ["OMP_NUM_THREADS"] = str(args.threads)
    rows = [("one process, unsharded map", *timed_cli(seqvpr_command(*match_args(whole, query, args.work / "s1"))))]
    rows.append(("one process, 2 shards", *timed_cli(seqvpr_command(*match_args(sharded, query, args.work / "s2")))))
    os.environ["OMP_NUM_THREADS"] = str(max(1, args.threads // 2))
    torchrun = [str(Path(sys.executable).parent / "torchrun"), "--standalone", "--nproc-per-node", "2",
                shutil.which("seqvpr", path=str(Path(sys.executable).parent))]
    rows.append(("torchrun, 2 ranks x 2 shards", *timed_cli([*torchrun, *match_args(sharded, query,
                                                                                      args.work / "s3")])))
    same = len({(args.work / name / "predictions.csv").read_text() for name in ("s1", "s2", "s3")}) == 1
    shortlisted, same_shortlisted = ([], None) if not args.shortlist else shortlisted_rows(
        whole, sharded, query, args.work, args.shortlist, args.threads, torchrun)
    print(f"CPU: {cpu_model()}; {args.size} x 256 map, 1,000 query frames, L = 5, K = 20, {args.threads} threads")
    print("| run | wall | x one process | peak RSS (largest process) |")
    print("|---|---:|---:|---:|")
    for name, seconds, peak in rows:
        print(f"| {name} | {seconds:.2f} s | {seconds / rows[0][1]:.2f}x | {peak:.2f} GiB |")
    print(f"identical predictions: {same}")
    for name, seconds, peak in shortlisted:
        print(f"| {name} | {seconds:.2f} s | {seconds / shortlisted[0][1]:.2f}x | {peak:.2f} GiB |")
    if shortlisted:
        print(f"identical shortlisted predictions: {same_shortlisted}")


if __name__ == "__main__":
    main()
