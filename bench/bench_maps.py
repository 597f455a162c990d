"""Saved maps at scale: exact sequence matching against a memory-mapped map, as ratios to the bare GEMM.

Run from the repository root (CPU; about 5 minutes and 4 GB of disk in ``--work``):

    .venv/bin/python bench/bench_maps.py --work runs/bench-maps [--sizes 10000,100000,1000000]
    .venv/bin/python bench/bench_maps.py --work runs/bench-maps --sizes 1000000,10000000 --builds float32,float16,sq8
    .venv/bin/python bench/bench_maps.py --work runs/bench-maps --sizes 10000000 --builds float16 --shards 4
    .venv/bin/python bench/bench_maps.py --work runs/bench-maps --scale --sizes 1000000,10000000 --localise 1000,200

``--scale`` (about 45 minutes and 11 GB at 10M; needs ../shared/data): issue 14's real-derived map at each size
(Nordland summer, PCA to 256-D, then copies turned towards seeded random rotations, made on access), written,
indexed with ``--index auto``, matched exactly and shortlisted (1,000 winter queries) and localised exactly and
shortlisted: time, peak RSS so far, R@1 and top-1 agreement with exact.

For each map size N (D = 256, float32 unit vectors: random directions, each ``--run`` consecutive frames a slowly
turning path so that sequences exist) the script writes the reference as a ``.npy`` (100,000 rows at a time, so
ten million frames are never held), builds the map from it with ``seqvpr map build`` and matches 1,000 query frames
(map rows ``N/3 ...`` plus noise, numbered as those rows) with ``seqvpr match --map -L 5 --k 20 --radius 2f`` under
``/usr/bin/time -v``. In the same process it times:

* the yardstick: the bare distance GEMM of the same shapes, ``torch.mm(query [1000, 256], map.T)`` over the map's
  memory map in 65,536-row blocks into one reused output buffer (and, up to 1M frames, in one call over a copy);
* ``seqvpr.maps.match_map`` (exact, L = 5, top-20) on the opened map, under a 2 GB and a 256 MB budget, whose
  top-K must be identical.

It prints a Markdown table (and writes it to ``WORK/results.md``): build seconds, match seconds, their ratio to
the GEMM, the CLI's wall time and peak RSS, and the growth exponent of build and match time over the sizes.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _common import cpu_model

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from seqvpr.data.sources import load_traversal, save_traversal_npz
from seqvpr.data.traversal import Traversal
from seqvpr.maps import open_map, match_map
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec

DIM, QUERIES, LENGTH, K = 256, 1000, 5, 20


def unit_rows(rng: np.random.Generator, n: int, run: int = 50, out: np.ndarray | None = None) -> np.ndarray:
    """N unit vectors in runs of ``run`` frames that turn slowly (neighbouring frames alike, as along a route),
    made 100,000 at a time into ``out`` (a memory-mapped file for ten million) or a new array."""
    out = np.empty((n, DIM), dtype=np.float32) if out is None else out
    for begin in range(0, n, 100_000):
        size = min(100_000, n - begin)
        anchors = rng.standard_normal((size // run + 2, DIM)).astype(np.float32)
        t = (np.arange(size) % run / run)[:, None].astype(np.float32)
        base = anchors[np.arange(size) // run] * (1 - t) + anchors[np.arange(size) // run + 1] * t
        rows = base + 0.3 * rng.standard_normal((size, DIM)).astype(np.float32)
        out[begin : begin + size] = rows / np.linalg.norm(rows, axis=1, keepdims=True)
    return out


def write_npy_source(work: Path, n: int, seed: int = 0) -> Path:
    """The reference rows alone as a ``.npy`` written 100,000 rows at a time (what a map of ten million frames is
    built from: a memory-mapped source)."""
    from numpy.lib.format import open_memmap

    path = work / f"ref_{n}.npy"
    if not path.exists():
        partial = work / f"ref_{n}.partial.npy"
        rows = open_memmap(partial, mode="w+", dtype=np.float32, shape=(n, DIM))
        unit_rows(np.random.default_rng(seed), n, out=rows)
        rows.flush()
        del rows
        partial.rename(path)
    return path


def measure_builds(work: Path, n: int, dtypes: list[str], shards: int = 0) -> list[dict]:
    """``seqvpr map build`` of an N-frame ``.npy`` into each storage (``--shards``, when given): wall seconds, peak
    RSS, map bytes a frame."""
    import shutil

    source = write_npy_source(work, n)
    rows = []
    for dtype in dtypes:
        folder = work / f"map_{n}_{dtype.replace(':', '')}"
        shutil.rmtree(folder, ignore_errors=True)
        sharding = ("--shards", str(shards)) if shards else ()
        seconds, peak = timed_cli(seqvpr_command("map", "build", source, "--dtype", dtype, *sharding, "--out", folder))
        stored = sum(p.stat().st_size for p in folder.rglob("descriptors.npy"))
        rows.append({"n": n, "dtype": dtype + (f", {shards} shards" if shards else ""), "build_s": seconds,
                     "build_gb": peak, "bytes": stored / n})
        shutil.rmtree(folder)
        print(rows[-1], flush=True)
    return rows


def build_table(rows: list[dict]) -> str:
    lines = ["| map frames | storage | build (CLI) | build peak RSS | stored bytes a frame |",
             "|---:|---|---:|---:|---:|"]
    lines += [f"| {r['n']:,} | {r['dtype']} | {r['build_s']:.1f} s | {r['build_gb']:.2f} GiB | {r['bytes']:.0f} |"
              for r in rows]
    return "\n".join(lines)


def seqvpr_command(*args: str | Path) -> list[str]:
    return [sys.executable, "-m", "seqvpr.cli", *map(str, args)]


def timed_cli(args: list[str]) -> tuple[float, float]:
    """Wall seconds and peak RSS (GiB) of a command, by /usr/bin/time -v."""
    started = time.perf_counter()
    done = subprocess.run(["/usr/bin/time", "-v", *args], capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed:\n{done.stderr[-2000:]}")
    peak_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr).group(1))
    return seconds, peak_kb / 2**20


def write_query(work: Path, n: int, reference: Path, seed: int = 1) -> Path:
    """The query: 1,000 map rows from N/3 on plus noise, each frame numbered as its map row (``--radius 2f``)."""
    from dataclasses import replace

    path = work / f"qry_{n}.npz"
    if not path.exists():
        rows = np.load(reference, mmap_mode="r")
        first = n // 3
        rng = np.random.default_rng(seed)
        noisy = np.asarray(rows[first : first + QUERIES]) + 0.1 * rng.standard_normal((QUERIES, DIM)).astype(np.float32)
        query = Traversal.from_descriptors(noisy.astype(np.float32), "query")
        save_traversal_npz(path, replace(query, frame_index=np.arange(first, first + QUERIES)))
    return path


def gemm_seconds(query: torch.Tensor, reference: np.ndarray) -> tuple[float, float]:
    """The yardstick: the distance GEMM over the map's memory map in 65,536-row blocks into one reused buffer (what
    any exact pass must at least do); and, for maps up to 1M frames, as one call over a copy in memory."""
    one = float("nan")
    if len(reference) <= 1_000_000:
        full = torch.from_numpy(np.array(reference))
        started = time.perf_counter()
        torch.mm(query, full.T)
        one = time.perf_counter() - started
        del full
    block = 65_536
    out = torch.empty(len(query), block)
    started = time.perf_counter()
    for begin in range(0, len(reference), block):
        part = torch.from_numpy(reference[begin : begin + block])
        torch.mm(query, part.T, out=out[:, : len(part)])
    return one, time.perf_counter() - started


def measure(work: Path, n: int) -> dict:
    reference = write_npy_source(work, n)
    query_file = write_query(work, n, reference)
    folder = work / f"map_{n}"
    import shutil

    shutil.rmtree(folder, ignore_errors=True)
    build_s, build_gb = timed_cli(seqvpr_command("map", "build", reference, "--out", folder))
    saved = open_map(folder)
    query = load_traversal(query_file, "query")
    q = torch.nn.functional.normalize(torch.from_numpy(np.asarray(query.descriptors)), dim=1)
    settings = MatchSettings(SequenceSpec(LENGTH), k=K)
    match_map(saved, query.select(np.arange(50)), "matching", settings)  # compile the numba kernels once
    gemm, gemm_blocked = gemm_seconds(q, saved.descriptors)
    results = {}
    for budget in (2 * 1024**3, 256 * 1024**2):
        started = time.perf_counter()
        results[budget] = match_map(saved, query, "matching", MatchSettings(SequenceSpec(LENGTH), k=K,
                                                                             memory_budget=budget))
        results[f"s{budget}"] = time.perf_counter() - started
    same = np.array_equal(results[2 * 1024**3].topk.indices, results[256 * 1024**2].topk.indices)
    cli_s, cli_gb = timed_cli(seqvpr_command("match", "--map", folder, "-q", query_file, "-L", LENGTH, "--k", "1,5,20",
                                             "--radius", "2f", "--out", work / f"out_{n}"))
    match_s = results[f"s{2 * 1024**3}"]
    return {"n": n, "map_gb": saved.descriptors.nbytes / 2**30, "build_s": build_s, "build_gb": build_gb,
            "gemm_s": gemm, "gemm_blocked_s": gemm_blocked, "match_s": match_s,
            "match_256m_s": results[f"s{256 * 1024**2}"], "ratio": match_s / gemm_blocked, "same": same,
            "cli_s": cli_s, "cli_gb": cli_gb}


class DistractorRows:
    """The real-derived map of ``bench_shortlist.py`` at any size, made on access (never held): the Nordland summer
    frames (256-D), then copies of them each turned part-way towards its own seeded random rotation
    (``cos t x + sin t R x``, t in 0.7-1.4 rad, renormalised). Row blocks are computed a copy at a time."""

    ndim = 2
    dtype = np.dtype(np.float32)

    def __init__(self, summer: np.ndarray, n: int, seed: int = 0) -> None:
        self.summer, self.seed, self.shape = summer, seed, (n, summer.shape[1])
        self.cached: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return self.shape[0]

    def copy(self, number: int) -> np.ndarray:
        from bench_shortlist import TURNS

        if number == 0:
            return self.summer
        if number not in self.cached:
            rng = np.random.default_rng([self.seed, number])
            rotation, _ = np.linalg.qr(rng.standard_normal((DIM, DIM)))
            turn = rng.uniform(*TURNS)
            made = np.cos(turn) * self.summer + np.sin(turn) * (self.summer @ rotation.T.astype(np.float32))
            self.cached = {number: (made / np.linalg.norm(made, axis=1, keepdims=True)).astype(np.float32)}
        return self.cached[number]

    def __getitem__(self, key: slice) -> np.ndarray:
        start, stop, _ = key.indices(len(self))
        size = len(self.summer)
        parts = [self.copy(c)[max(start - c * size, 0) : min(stop - c * size, size)]
                 for c in range(start // size, (stop - 1) // size + 1)] if stop > start else []
        return np.concatenate(parts) if parts else np.zeros((0, DIM), np.float32)


def peak_gb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def measure_scale(work: Path, data: Path, n: int, localize: int) -> dict:
    """The real-derived map of N frames: written, indexed (``--index auto``), matched exactly and shortlisted (1,000
    winter queries), and localised exactly and shortlisted (the first ``localise`` of them): seconds, peak RSS so
    far, R@1 (the summer frame within one frame) and agreement with exact."""
    from bench_shortlist import QUERY_FRAMES, _truth, nordland_256

    from seqvpr.localization import Localizer
    from seqvpr.localization.replay import replay, score_replay
    from seqvpr.maps.files import MapInfo, MapSource, write_map
    from seqvpr.maps.index import add_index, parse_index_spec

    summer, winter = nordland_256(data)
    folder = work / f"real_{n}"
    record: dict = {"n": n}
    started = time.perf_counter()
    if not (folder / "map.json").exists():
        rows = DistractorRows(summer, n)
        copy_of = (np.arange(n) // len(summer)).astype(np.int64)
        frames = Traversal("nordland-distractors", np.arange(n, dtype=np.int64), copy_of, rows)
        info = MapInfo(n, DIM, "float32", True, {"descriptor": "file"}, (MapSource("generated", "summer", 0, n),))
        write_map(folder, frames, info)
    record.update(write_s=time.perf_counter() - started, write_gb=peak_gb())
    saved = open_map(folder)
    if (saved.info.index or {}).get("over") != "frames":
        add_index(saved, parse_index_spec("auto"), seed=0)
        saved = open_map(folder)
    index = saved.info.index
    record.update(spec=index["spec"], index_s=index["build_seconds"], index_gb=peak_gb(),
                  index_bytes=(folder / index["file"]).stat().st_size / n)
    first, last = QUERY_FRAMES
    query = Traversal.from_descriptors(winter[first:last], "winter")
    gt = _truth([np.arange(max(p - 1, 0), min(p + 2, len(summer))) for p in range(first, last)], n)
    settings = MatchSettings(SequenceSpec(LENGTH), k=K)
    match_map(saved, query.select(np.arange(20)), "matching", settings)  # compile once
    results = {}
    for label, options in (("exact", {}), ("shortlist", {"shortlist": 20, "nprobe": 16}),
                           ("shortlist+history", {"shortlist": 5, "history": 20, "nprobe": 8})):
        started = time.perf_counter()
        top = match_map(saved, query, "matching", settings, **options).topk
        right = np.array([top.indices[i, 0] in gt.positives_of(i) for i in range(len(query))])
        results[label] = top.indices[:, 0]
        record.update({f"{label}_s": time.perf_counter() - started, f"{label}_gb": peak_gb(),
                       f"{label}_r1": float(right[top.has_window].mean()),
                       f"{label}_agree": float(np.mean(top.indices[top.has_window, 0] ==
                                                       results["exact"][top.has_window]))})
    part = query.select(np.arange(localize))
    part_gt = _truth([np.arange(max(p - 1, 0), min(p + 2, len(summer))) for p in range(first, first + localize)], n)
    exact_top = None
    for label, options in (("localise", {}), ("localise-shortlist", {"shortlist": 5, "history": 20, "nprobe": 8})):
        localizer = Localizer.open(saved, seq_len=LENGTH, **options)
        started = time.perf_counter()
        run = replay(localizer, part)
        seconds = time.perf_counter() - started
        scores = score_replay(run, part_gt)
        top = run.indices[:, 0]
        exact_top = top if exact_top is None else exact_top
        record.update({f"{label}_ms": seconds / localize * 1e3, f"{label}_gb": peak_gb(),
                       f"{label}_r1": scores.evaluation.recall[1],
                       f"{label}_agree": float(np.mean(top[run.scored] == exact_top[run.scored]))})
    print(record, flush=True)
    return record


def scale_table(rows: list[dict]) -> str:
    lines = ["| map frames | stage | time | peak RSS so far | R@1 | top-1 = exact |", "|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        n = f"{r['n']:,}"
        lines.append(f"| {n} | write the map (float32) | {r['write_s']:.0f} s | {r['write_gb']:.2f} GiB | | |")
        lines.append(f"| {n} | index `auto` = `{r['spec']}`, {r['index_bytes']:.1f} B a frame | {r['index_s']:.0f} s | "
                     f"{r['index_gb']:.2f} GiB | | |")
        for label, what in (("exact", "exact match, 1,000 queries"),
                            ("shortlist", "shortlisted match, S = 20, nprobe 16"),
                            ("shortlist+history", "shortlisted match, S = 5, H = 20, nprobe 8")):
            lines.append(f"| {n} | {what} | {r[label + '_s']:.2f} s | {r[label + '_gb']:.2f} GiB | "
                         f"{r[label + '_r1']:.3f} | {r[label + '_agree']:.3f} |")
        for label, what in (("localise", "exact localiser"), ("localise-shortlist", "shortlisted localiser, S = 5, H = 20")):
            lines.append(f"| {n} | {what} | {r[label + '_ms']:.2f} ms a frame | {r[label + '_gb']:.2f} GiB | "
                         f"{r[label + '_r1']:.3f} | {r[label + '_agree']:.3f} |")
    return "\n".join(lines)


def exponent(rows: list[dict], key: str) -> float:
    """Slope of log(time) against log(N): 1 is linear growth."""
    if len(rows) < 2:
        return float("nan")
    return float(np.polyfit(np.log([r["n"] for r in rows]), np.log([r[key] for r in rows]), 1)[0])


def table(rows: list[dict]) -> str:
    lines = ["| map frames | map file | build (CLI) | build peak RSS | GEMM (1 call, in memory) | GEMM (blocked, mapped) | "
             "match 2 GB budget | match 256 MB | ratio to blocked GEMM | top-K identical | CLI match wall | "
             "CLI peak RSS |",
             "|---:" * 12 + "|"]
    for r in rows:
        lines.append(f"| {r['n']:,} | {r['map_gb']:.2f} GiB | {r['build_s']:.1f} s | {r['build_gb']:.2f} GiB | "
                     f"{r['gemm_s']:.2f} s | {r['gemm_blocked_s']:.2f} s | {r['match_s']:.2f} s | "
                     f"{r['match_256m_s']:.2f} s | **{r['ratio']:.2f}x** | {'yes' if r['same'] else 'NO'} | "
                     f"{r['cli_s']:.1f} s | {r['cli_gb']:.2f} GiB |")
    lines.append(f"\ngrowth exponent over the sizes: build {exponent(rows, 'build_s'):.2f}, "
                 f"exact match {exponent(rows, 'match_s'):.2f}, blocked GEMM {exponent(rows, 'gemm_blocked_s'):.2f}")
    large = [r for r in rows if r["n"] >= 1_000_000]
    if len(large) >= 2:
        lines.append(f"from 1M frames: exact match {exponent(large, 'match_s'):.2f} (2 GB budget), "
                     f"{exponent(large, 'match_256m_s'):.2f} (256 MB), blocked GEMM "
                     f"{exponent(large, 'gemm_blocked_s'):.2f}")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, required=True, help="Folder for the data, maps and outputs.")
    parser.add_argument("--sizes", default="10000,100000,1000000", help="Map sizes, comma-separated.")
    parser.add_argument("--builds", help="Only build: these storages (e.g. float32,float16,sq8) from a .npy of each "
                                         "size, with their peak memory")
    parser.add_argument("--shards", type=int, default=0, help="--builds: build straight into this many shards.")
    parser.add_argument("--scale", action="store_true",
                        help="Instead: the real-derived map (Nordland summer and turned copies of it, as "
                             "bench_shortlist.py) at each size: write, index auto, exact and shortlisted match and "
                             "localiser, with R@1 and agreement with exact")
    parser.add_argument("--localise", default="1000", help="--scale: query frames localised at each size "
                                                           "(comma-separated, one per size).")
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    if args.scale:
        sizes = [int(n) for n in args.sizes.split(",")]
        counts = [int(c) for c in args.localize.split(",")] * (len(sizes) if "," not in args.localize else 1)
        rows = [measure_scale(args.work, args.data, n, c) for n, c in zip(sizes, counts)]
        text = (f"{cpu_model()}, {torch.get_num_threads()} threads; real-derived maps, D = {DIM}, L = {LENGTH}, "
                f"top-{K}\n\n{scale_table(rows)}\n")
        (args.work / "scale.md").write_text(text)
        print(text)
        return
    if args.builds:
        built = [r for n in args.sizes.split(",")
                 for r in measure_builds(args.work, int(n), args.builds.split(","), args.shards)]
        text = f"{cpu_model()}, map build from a memory-mapped .npy, D = {DIM}\n\n{build_table(built)}\n"
        (args.work / "builds.md").write_text(text)
        print(text)
        return
    rows = []
    for n in (int(s) for s in args.sizes.split(",")):
        rows.append(measure(args.work, n))
        print(rows[-1], flush=True)
    text = (f"{cpu_model()}, {torch.get_num_threads()} threads; {QUERIES} queries, D = {DIM}, L = {LENGTH}, "
            f"top-{K}, exact\n\n{table(rows)}\n")
    (args.work / "results.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
