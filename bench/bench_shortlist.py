"""Exact against shortlisted sequence matching on large maps of real descriptors: time, memory, index build and
how much R@1 the approximation costs.

Run from the repository root (CPU; about 15 minutes and 2 GB of disk in ``--work``; needs ../shared/data):

    .venv/bin/python bench/bench_shortlist.py --work runs/bench-shortlist [--sizes 100000,1000000]

The data (there is no real 1M-frame traversal here): Nordland 64x32 summer and winter (frames 17-1999) are
described with patch normalisation (2048-D), PCA-reduced to 256-D (fitted on summer, seeded) and L2-normalised.
The map is the 1983 summer frames (the only true places) followed by distractor traversals up to N frames: each
a copy of summer turned part-way towards a random rotation of itself (``cos t x + sin t R x``, t from 0.7 to 1.4
rad, renormalised; a segment of its own), so sequences are as smooth as real ones and some look much alike. The
query is winter frames 500-1499 (1,000 frames); a query is right at K when one of its K best map frames is its
summer frame within one frame. Each size's map gets each index of ``--indexes`` over frames, with one row per
``--frame-shortlists`` S:H:NPROBE: each query frame's S nearest map frames place candidate windows, and so do the
H query frames before the window (carried forward at slope 1; up to (5 + H) S candidates). With ``--over both``
the index is also built over smoothed windows of 5 frames (each query window's 5 S nearest windows, as many
candidates as the first row). Every row matches the same query through ``seqvpr.maps.match_map`` (L = 5,
top-20) and reports its time, the shortlist's recall (a true place among the candidates), R@1, its top-1
agreement with the exact result, and the share of exact's right answers it keeps. When a row has H > 0, exact
matching with L = 5 + H (the query frames that row sees) is reported too, for reference.
"""

from __future__ import annotations

import argparse
import resource
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

from seqvpr.data.ground_truth import GroundTruth
from seqvpr.data.sources import load_traversal
from seqvpr.data.traversal import Traversal, slice_frame_range
from seqvpr.evaluation.metrics import evaluate
from seqvpr.features.whitening import fit_pca_whitening
from seqvpr.maps import FrameDescription, open_map, match_map
from seqvpr.maps.files import MapInfo, MapSource, write_map
from seqvpr.maps.index import add_index, parse_index_spec
from seqvpr.maps.match import shortlist_recall
from seqvpr.features.describe import describe
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec

DIM, LENGTH, K = 256, 5, 20
TURNS = (0.7, 1.4)  # radians a distractor copy is turned towards its rotation
QUERY_FRAMES = (500, 1500)


def nordland_256(data: Path) -> tuple[np.ndarray, np.ndarray]:
    """Summer and winter frames 17-1999 as 256-D unit vectors (patch normalisation, PCA fitted on summer)."""
    root = data / "nordland_64x32"
    summer, winter = (describe(slice_frame_range(load_traversal(root / side, "reference"), "17:2000"))
                      for side in ("summer", "winter"))
    pca = fit_pca_whitening(summer.descriptors, DIM)
    unit = lambda x: (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)  # noqa: E731
    return unit(pca.apply(summer.descriptors)), unit(pca.apply(winter.descriptors))


def write_distractor_map(folder: Path, summer: np.ndarray, n: int, seed: int = 0) -> None:
    """A map of N frames: the summer traversal (the true places), then distractor traversals, each the summer
    frames turned part-way towards a random rotation of themselves (``cos t x + sin t R x``, t drawn from
    0.7-1.4 rad per copy, renormalised): sequences as smooth as real ones, of places that look more or less alike."""
    rng = np.random.default_rng(seed)
    blocks, made = [summer], len(summer)
    while made < n:
        rotation, _ = np.linalg.qr(rng.standard_normal((DIM, DIM)))
        turn = rng.uniform(*TURNS)
        copy = np.cos(turn) * summer + np.sin(turn) * (summer @ rotation.T.astype(np.float32))
        blocks.append((copy / np.linalg.norm(copy, axis=1, keepdims=True)).astype(np.float32))
        made += len(summer)
    rows = np.concatenate(blocks)[:n]
    copy_of = np.arange(n) // len(summer)
    place = np.where(copy_of == 0, np.arange(n), -1)  # only the first copy holds true places
    frames = Traversal("nordland-distractors", np.arange(n, dtype=np.int64), copy_of.astype(np.int64), rows,
                       positions=np.stack([place.astype(np.float64), copy_of.astype(np.float64)], 1))
    description = {**FrameDescription().to_json(), "descriptor": "file"}
    info = MapInfo(n, DIM, "float32", True, description, (MapSource("nordland-distractors", "summer", 0, n),))
    write_map(folder, frames, info)


def _truth(lists: list[np.ndarray], n: int) -> GroundTruth:
    """Positives from a list of reference rows per query."""
    from scipy.sparse import csr_array

    rows = np.concatenate([np.full(len(p), i) for i, p in enumerate(lists)])
    cols = np.concatenate(lists)
    matrix = csr_array((np.ones(len(cols), bool), (rows, cols)), shape=(len(lists), n))
    return GroundTruth(matrix, description="the same summer frame within 1 frame")


def run_rows(saved, query: Traversal, gt: GroundTruth, exact: dict | None, label: str, shortlist: int,
             nprobe: int, history: int = 0, length: int = LENGTH) -> dict:
    settings = MatchSettings(SequenceSpec(length), k=K)
    started = time.perf_counter()
    result = match_map(saved, query, "matching", settings, shortlist=shortlist, history=history, nprobe=nprobe)
    seconds = time.perf_counter() - started
    top = result.topk
    scores = evaluate(top.indices, top.distances, top.has_window, gt, (1, 5, 20))
    scored = top.has_window
    right = np.array([top.indices[i, 0] in gt.positives_of(i) for i in range(len(scored))], dtype=bool)
    agree = float(np.mean(top.indices[scored, 0] == exact["top1"][scored])) if exact else 1.0
    kept = float(np.mean(right[exact["right"] & scored])) if exact else 1.0
    return {"label": label, "seconds": seconds, "r1": scores.recall[1], "r20": scores.recall[20],
            "shortlist_recall": shortlist_recall(result, gt), "agree": agree, "kept": kept, "top1": top.indices[:, 0],
            "right": right}


def parse_frame_shortlists(text: str) -> list[tuple[int, int, int]]:
    """``S:H:NPROBE`` triples separated by commas: neighbours per query frame, history frames, IVF lists probed."""
    return [tuple(int(v) for v in item.split(":")) for item in text.split(",")]


def measure(work: Path, summer: np.ndarray, winter: np.ndarray, n: int, specs: list[str],
            frame_rows: list[tuple[int, int, int]], both: bool = True) -> list[dict]:
    folder = work / f"map_{n}"
    if not (folder / "map.json").exists():
        write_distractor_map(folder, summer, n)
    saved = open_map(folder)
    first, last = QUERY_FRAMES
    query = Traversal.from_descriptors(winter[first:last], "winter")
    gt = _truth([np.arange(max(p - 1, 0), min(p + 2, len(summer))) for p in range(first, last)], n)
    match_map(saved, query.select(np.arange(50)), "matching", MatchSettings(SequenceSpec(LENGTH), k=K))  # warm-up
    rows = [run_rows(saved, query, gt, None, "exact", 0, 16)]
    longest = max(h for _, h, _ in frame_rows)
    if longest:  # exact matching over as many query frames as the longest history sees, for reference
        rows.append(run_rows(saved, query, gt, rows[0], f"exact, L = {LENGTH + longest}", 0, 16,
                             length=LENGTH + longest))
    for spec in specs:
        record = add_index(saved, parse_index_spec(spec), seed=0)
        for per, history, nprobe in frame_rows:
            label = f"{spec} over frames, S = {per}, H = {history}, nprobe {nprobe}"
            rows.append(run_rows(open_map(folder), query, gt, rows[0], label, per, nprobe, history)
                        | {"build": record["build_seconds"]})
        if both:  # an index over smoothed windows re-ranking as many candidates as the first frame row
            per = frame_rows[0][0] * LENGTH
            record = add_index(saved, parse_index_spec(spec), seed=0, windows=LENGTH)
            label = f"{spec} over {record['over']}, S = {per}"
            rows.append(run_rows(open_map(folder), query, gt, rows[0], label, per, frame_rows[0][2])
                        | {"build": record["build_seconds"]})
    for row in rows:
        row.setdefault("build", 0.0)
        row["n"] = n
        row["speedup"] = rows[0]["seconds"] / row["seconds"]
    return rows


def table(rows: list[dict]) -> str:
    lines = ["| map frames | matching | index build | match 1,000 queries | speed-up | shortlist recall | R@1 | R@20 | "
             "top-1 = exact | exact's right kept |", "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        recall = "-" if r["shortlist_recall"] is None else f"{r['shortlist_recall']:.3f}"
        lines.append(f"| {r['n']:,} | {r['label']} | {r['build']:.1f} s | {r['seconds']:.3f} s | {r['speedup']:.0f}x | "
                     f"{recall} | {r['r1']:.3f} | {r['r20']:.3f} | {r['agree']:.3f} | {r['kept']:.3f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--sizes", default="100000,1000000")
    parser.add_argument("--indexes", default="ivf:4096,ivf:4096+pq:32,hnsw:16",
                        help="Index specs separated by commas; '+' stands for the comma inside one spec.")
    parser.add_argument("--frame-shortlists", default="20:0:16,5:20:8",
                        help="Rows over frames as S:H:NPROBE (nearest map frames per query frame, query frames "
                             "before the window that also place candidates, IVF lists probed), separated by commas.")
    parser.add_argument("--over", choices=("both", "frames"), default="both", help="Index frames and windows, or frames.")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    summer, winter = nordland_256(args.data)
    specs = [s.replace("+", ",") for s in args.indexes.split(",")]
    rows = []
    for n in (int(s) for s in args.sizes.split(",")):
        rows += measure(args.work, summer, winter, n, specs, parse_frame_shortlists(args.frame_shortlists),
                        args.over == "both")
        print(table(rows), flush=True)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    text = (f"{cpu_model()}, {torch.get_num_threads()} threads; 1,000 queries, D = {DIM}, L = {LENGTH}, top-{K}, "
            f"peak RSS of the whole script {peak:.2f} GiB\n\n{table(rows)}\n")
    (args.work / "results.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
