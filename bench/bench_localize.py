"""The online localiser: per-frame latency against the floor of one matrix-vector product over the map, a
shortlisted localiser against the exact one at 1M frames, and the topological filter against causal sequence
matching on real and rendered routes.

Run from the repository root (CPU; about 15 minutes and 3 GB of disk in ``--work``; needs ../shared/data):

    .venv/bin/python bench/bench_localize.py --work runs/bench-localize [--parts latency,shortlist,filter]

* latency: a 100k-frame map of 512-D unit vectors (random directions turning slowly along the route, as in
  ``bench_maps.py``) and 300 query frames (map rows plus noise). In the same run, per frame: the floor is
  ``torch.mv`` of the memory-mapped map (a torch view of the same pages) with the query; the exact update is
  ``Localizer.update`` with L = 5. Medians over the frames; the ratio is update / floor. ms per stage.
* loaded: the exact update against the floor at 10k and 1M frames (256-D, L = 5), each in a fresh process
  (so seqvpr's default thread count is chosen at its start, as a command's is) beside ``--loads`` processes each
  spinning one core, at the default thread setting and at ``--settings``; the floor runs at the same thread count
  in the same process, interleaved with the updates.
* shortlist: the 1M-frame Nordland-with-distractors map of ``bench_shortlist.py`` (256-D; its data is described
  there), 1,000 winter query frames replayed through the exact localiser and through a shortlisted one
  (``ivf:4096``, S = 5 a frame, the 20 frames before the window carried forward, nprobe 8): ms per frame and R@1
  (the summer frame within one frame).
* filter: Nordland 64x32 (summer map, winter query, frames 17-1999, +-1 frame) and the demo world (rendered test
  route, EfficientNet-Lite0, 10 m): causal sequence matching (L = 5, 10) against the filter (``--method hmm``),
  R@1 and recall at 100 % precision by the localiser's score.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _common import cpu_model, run_beside_load

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from seqvpr.data.ground_truth import Radius, parse_radius
from seqvpr.data.sources import load_traversal
from seqvpr.data.traversal import Traversal, slice_frame_range
from seqvpr.localization import Localizer
from seqvpr.localization.replay import replay, score_replay
from seqvpr.maps import build_map, open_map
from seqvpr.maps.files import MapInfo, MapSource, write_map
from seqvpr.maps.index import add_index, parse_index_spec
from seqvpr.evaluation.ground_truth import ground_truth
from seqvpr.features.describe import describe

LATENCY_MAP, LATENCY_DIM, LATENCY_QUERIES = 100_000, 512, 300


def slow_path(n: int, dim: int, seed: int, run: int = 50) -> np.ndarray:
    """n unit vectors: random directions, each ``run`` consecutive frames turning slowly (sequences exist)."""
    rng = np.random.default_rng(seed)
    anchors = rng.standard_normal((n // run + 2, dim)).astype(np.float32)
    t = (np.arange(n) % run / run)[:, None].astype(np.float32)
    rows = (1 - t) * anchors[np.arange(n) // run] + t * anchors[np.arange(n) // run + 1]
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def write_plain_map(folder: Path, rows: np.ndarray) -> None:
    frames = Traversal.from_descriptors(rows, "latency")
    info = MapInfo(len(rows), rows.shape[1], "float32", True, {"descriptor": "file"},
                   (MapSource("latency", "generated", 0, len(rows)),))
    write_map(folder, frames, info)


def floor_and_update(saved, localizer: Localizer, queries: np.ndarray, skip: int) -> tuple[float, float, np.ndarray]:
    """Per query frame, the floor (``torch.mv`` of the map's memory map with the frame) and ``localizer.update``,
    interleaved so both see the same machine state: their medians (ms) after the first ``skip`` frames, and the
    median ms of the update's describe, distance and sequence stages."""
    matrix = torch.from_numpy(saved.descriptors)
    floors, updates, stages = [], [], []
    for q in queries:
        vector = torch.from_numpy(q / np.linalg.norm(q))
        started = time.perf_counter()
        torch.mv(matrix, vector)
        floors.append(time.perf_counter() - started)
        started = time.perf_counter()
        estimate = localizer.update(q)
        updates.append(time.perf_counter() - started)
        stages.append([estimate.latency[s] for s in ("describe", "distance", "sequence")])
    return (float(np.median(floors[skip:]) * 1e3), float(np.median(updates[skip:]) * 1e3),
            np.median(np.array(stages[skip:]), axis=0))


def latency(work: Path) -> str:
    """Exact update against the matrix-vector floor, 100k x 512, L = 5."""
    folder = work / "latency_map"
    if not (folder / "map.json").exists():
        write_plain_map(folder, slow_path(LATENCY_MAP, LATENCY_DIM, 0))
    saved = open_map(folder)
    rng = np.random.default_rng(1)
    rows = np.asarray(saved.descriptors[20_000 : 20_000 + LATENCY_QUERIES])
    queries = rows + 0.05 * rng.standard_normal(rows.shape).astype(np.float32)
    floor, update, stage = floor_and_update(saved, Localizer.open(saved, seq_len=5), queries, skip=5)
    return (f"| {LATENCY_MAP:,} x {LATENCY_DIM} | {floor:.2f} ms | {update:.2f} ms | **{update / floor:.2f}x** | "
            f"{stage[0]:.2f} / {stage[1]:.2f} / {stage[2]:.2f} ms |")


LOADED_SIZES, LOADED_DIM, LOADED_QUERIES = (10_000, 1_000_000), 256, 400


def loaded_worker(folder: Path) -> dict:
    """In a fresh process (its thread policy chosen at start, as a command's is): per frame, the floor (``torch.mv``
    of the map's memory map with the frame, at the same thread count) and ``Localizer.update``, interleaved; medians
    over the frames after the first 20."""
    from seqvpr import threads

    saved = open_map(folder)
    localizer = Localizer.open(saved, seq_len=5)  # applies the default policy, as every entry point does
    n = saved.info.count
    rng = np.random.default_rng(1)
    rows = np.asarray(saved.descriptors[n // 5 : n // 5 + LOADED_QUERIES])
    queries = rows + 0.05 * rng.standard_normal(rows.shape).astype(np.float32)
    floor, update, stage = floor_and_update(saved, localizer, queries, skip=20)
    policy = threads.current_policy()
    return {"floor": floor, "update": update, "stages": stage.tolist(), "threads": policy.threads,
            "policy": policy.describe()}


def loaded(work: Path, loads: list[int], settings: list[str]) -> list[str]:
    """Exact update against the floor at 10k and 1M frames (256-D, L = 5) in fresh processes beside ``loads``
    spinning processes, at the default thread setting and at fixed ones."""
    lines = []
    for n in LOADED_SIZES:
        folder = work / f"loaded_map_{n}"
        if not (folder / "map.json").exists():
            write_plain_map(folder, slow_path(n, LOADED_DIM, 0))
        for load in loads:
            for setting in settings:
                r = run_beside_load([__file__, "--worker", str(folder)], setting, load)
                stage = r["stages"]
                lines.append(f"| {n:,} x {LOADED_DIM} | {load} | {setting} ({r['threads']}) | {r['floor']:.3f} ms | "
                             f"{r['update']:.3f} ms | **{r['update'] / r['floor']:.2f}x** | "
                             f"{stage[0]:.3f} / {stage[1]:.3f} / {stage[2]:.3f} ms |")
                print(lines[-1], flush=True)
    return lines


def shortlist(work: Path, data: Path) -> list[str]:
    """Exact against shortlisted localisation on the 1M-frame distractor map (bench_shortlist's data)."""
    from bench_shortlist import QUERY_FRAMES, _truth, nordland_256, write_distractor_map

    n = 1_000_000
    summer, winter = nordland_256(data)
    folder = work / f"map_{n}"
    if not (folder / "map.json").exists():
        write_distractor_map(folder, summer, n)
    saved = open_map(folder)
    if (saved.info.index or {}).get("spec") != "ivf:4096" or saved.info.index.get("over") != "frames":
        add_index(saved, parse_index_spec("ivf:4096"), seed=0)
        saved = open_map(folder)
    first, last = QUERY_FRAMES
    query = Traversal.from_descriptors(winter[first:last], "winter")
    gt = _truth([np.arange(max(p - 1, 0), min(p + 2, len(summer))) for p in range(first, last)], n)
    lines = []
    for label, options in (("exact", {}), ("ivf:4096, S = 5, H = 20, nprobe 8",
                                            {"shortlist": 5, "history": 20, "nprobe": 8})):
        localizer = Localizer.open(saved, seq_len=5, **options)
        started = time.perf_counter()
        run = replay(localizer, query)
        per_frame = (time.perf_counter() - started) / len(query) * 1e3
        scores = score_replay(run, gt)
        stage = np.median(run.latency[run.scored], axis=0)
        lines.append(f"| {label} | {per_frame:.2f} ms | {stage[1]:.2f} / {stage[2]:.2f} ms | "
                     f"{scores.evaluation.recall[1]:.3f} | {scores.evaluation.recall[20]:.3f} |")
    return lines


def filter_rows(name: str, saved, query: Traversal, gt) -> list[str]:
    """Causal matching at L = 5, 10 against the filter on one route: R@1, R@100P by the score."""
    lines = []
    for label, options in (("causal matching, L = 5", {"seq_len": 5}), ("causal matching, L = 10", {"seq_len": 10}),
                           ("filter (hmm)", {"method": "hmm"})):
        localizer = Localizer.open(saved, **options)
        scores = score_replay(replay(localizer, query), gt)
        e = scores.evaluation
        lines.append(f"| {name} | {label} | {e.recall[1]:.3f} | {e.recall[5]:.3f} | {e.pr.auc:.3f} | "
                     f"{e.pr.recall_at_100_precision:.3f} |")
    return lines


def filters(work: Path, data: Path) -> list[str]:
    root = data / "nordland_64x32"
    winter = describe(slice_frame_range(load_traversal(root / "winter", "query"), "17:2000"))
    if not (work / "nordland_map" / "map.json").exists():
        build_map([str(root / "summer")], work / "nordland_map", frames="17:2000")
    saved = open_map(work / "nordland_map")
    lines = filter_rows("Nordland", saved, winter, ground_truth(saved.frames, winter, parse_radius("1f")))
    from seqvpr.experiments.demo import DemoSettings, describe_world, render_world
    from seqvpr.features.extraction import ExtractorConfig
    from seqvpr.maps import FrameDescription

    settings = DemoSettings()
    world = describe_world(render_world(work / "demo" / "world", settings), settings, work / "demo" / "cache")
    reference, query = world["test_reference"], world["test_query"]
    if not (work / "demo_map" / "map.json").exists():
        extractor = ExtractorConfig(width=settings.width, height=settings.height)
        build_map([str(work / "demo" / "world" / "test_reference")], work / "demo_map",
                  FrameDescription("efficientnet-lite0", extractor=extractor), cache_dir=work / "demo" / "cache")
    saved = open_map(work / "demo_map")
    gt = ground_truth(reference, query, Radius(settings.radius_m, "m"))
    return lines + filter_rows("demo world", saved, query, gt)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path)
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--shortlist-work", type=Path, help="Where bench_shortlist.py left its maps (reused).")
    parser.add_argument("--parts", default="latency,shortlist,filter", help="latency, loaded, shortlist, filter")
    parser.add_argument("--loads", default="0,2", help="loaded: spinning processes beside the localiser.")
    parser.add_argument("--settings", default="default,1,2", help="loaded: thread settings (default: seqvpr's).")
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        import json

        print(json.dumps(loaded_worker(args.worker)))
        return
    if args.work is None:
        parser.error("--work is required")
    args.work.mkdir(parents=True, exist_ok=True)
    parts = args.parts.split(",")
    text = [f"{cpu_model()}, {torch.get_num_threads()} threads"]
    if "latency" in parts:
        text += ["", "| map | matrix-vector floor | exact update | ratio | describe / distance / sequence |",
                 "|---|---:|---:|---:|---|", latency(args.work)]
        print("\n".join(text), flush=True)
    if "loaded" in parts:
        text += ["", "| map | busy processes | threads (count) | matrix-vector floor | exact update | ratio | "
                 "describe / distance / sequence |", "|---|---:|---|---:|---:|---:|---|",
                 *loaded(args.work, [int(x) for x in args.loads.split(",")], args.settings.split(","))]
    if "shortlist" in parts:
        text += ["", "| 1M frames, L = 5 | per frame | distance / sequence (median) | R@1 | R@20 |",
                 "|---|---:|---|---:|---:|", *shortlist(args.shortlist_work or args.work, args.data)]
        print("\n".join(text[-4:]), flush=True)
    if "filter" in parts:
        text += ["", "| route | localiser | R@1 | R@5 | PR-AUC (score) | R@100P (score) |", "|---|---|---:|---:|---:|---:|",
                 *filters(args.work, args.data)]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    text.append(f"\npeak RSS of the whole script {peak:.2f} GiB")
    (args.work / "results.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))


if __name__ == "__main__":
    main()
