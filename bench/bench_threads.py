"""The thread policy on an idle and on a loaded machine: describe, match and the localiser with seqvpr's default
thread count against 1 and 2 threads, each alone and beside a competing load, in the same run.

Run from the repository root (CPU; about 10 minutes on 2 cores):

    .venv/bin/python bench/bench_threads.py --work runs/bench-threads [--load 2] [--repeats 3]

Each measurement is a fresh process (so the policy is chosen at its start, as a command's is) that runs one
workload through the public Python entry points and times the work alone (not the imports):
* describe: 24 images of 320x240 through EfficientNet-Lite0 (``features.describe.describe``, the map builder's path).
* match: sequence matching (``SequenceMatcher``, L = 5, top-20) of 1,000 query frames against 4,000 map
  frames, 512-D.
* localise: ``Localizer.update`` of 200 frames, one at a time, over a 20,000-frame 512-D map (exact causal
  matching, L = 5), and of 16 camera images one at a time through the map's EfficientNet-Lite0 (a robot's frames).
The competing load is ``--load`` processes each spinning one core, started a second before the measured process
and stopped after it. The settings: ``default`` (no ``SEQVPR_THREADS``: seqvpr's choice), ``1`` and ``2``. The
table gives median seconds over ``--repeats`` runs, and default / best setting per workload and load.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np
from _common import cpu_model, run_beside_load

SETTINGS = ("default", "1", "2")
WORKLOADS = ("describe", "match", "localise", "localise-images")
MAP_FRAMES, DIM = 20_000, 512


def worker(kind: str, work: Path) -> dict:
    """Run one workload in this process; its seconds and the thread counts in force afterwards."""
    from seqvpr import threads

    policy = threads.ensure_policy()  # what every public entry point does first
    started = time.perf_counter()
    {"describe": _describe, "match": _match, "localise": _localize, "localise-images": _localize_images}[kind](work)
    seconds = time.perf_counter() - started
    return {"seconds": seconds, "policy": policy.describe(), "pools": threads.pool_counts()}


def _describe(work: Path) -> None:
    from seqvpr.data.traversal import Traversal
    from seqvpr.features.extraction import ExtractorConfig
    from seqvpr.features.describe import describe

    paths = sorted((work / "images").glob("*.png"))
    traversal = Traversal("images", np.arange(len(paths)), np.zeros(len(paths), np.int64), image_paths=tuple(paths))
    describe(traversal, "efficientnet-lite0", extractor=ExtractorConfig(width=320, height=240))


def _match(work: Path) -> None:
    from seqvpr.data.traversal import Traversal
    from seqvpr.matchers.sequence import SequenceMatcher
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.sequences.windows import SequenceSpec

    rng = np.random.default_rng(1)
    reference = Traversal.from_descriptors(rng.standard_normal((4000, DIM)).astype(np.float32), "reference")
    query = Traversal.from_descriptors(rng.standard_normal((1000, DIM)).astype(np.float32), "query")
    SequenceMatcher(MatchSettings(SequenceSpec(length=5), k=20)).topk(reference, query)


def _localize(work: Path) -> None:
    from seqvpr.localization import Localizer

    localizer = Localizer.open(work / "map")
    rows = np.load(work / "map.npy", mmap_mode="r")
    noise = np.random.default_rng(2).standard_normal((200, DIM)).astype(np.float32) * 0.01
    for i in range(200):
        localizer.update(rows[5000 + i] + noise[i])


def _localize_images(work: Path) -> None:
    from seqvpr.localization import Localizer

    localizer = Localizer.open(work / "image-map")
    for path in sorted((work / "images").glob("*.png"))[:16]:
        localizer.update(path)


def prepare(work: Path) -> None:
    """Images, a descriptor map and an image map in ``work`` (made once)."""
    from PIL import Image

    from seqvpr.features.extraction import ExtractorConfig
    from seqvpr.maps import FrameDescription, build_map

    images = work / "images"
    if not images.is_dir():
        images.mkdir(parents=True)
        rng = np.random.default_rng(0)
        for i in range(24):
            Image.fromarray(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)).save(images / f"{i:03d}.png")
    if not (work / "map").is_dir():
        rng = np.random.default_rng(0)
        rows = rng.standard_normal((MAP_FRAMES, DIM)).astype(np.float32)
        np.save(work / "map.npy", rows / np.linalg.norm(rows, axis=1, keepdims=True))
        build_map([str(work / "map.npy")], work / "map")
    if not (work / "image-map").is_dir():
        build_map([str(images)], work / "image-map",
                  FrameDescription("efficientnet-lite0", extractor=ExtractorConfig(width=320, height=240)))


def measure(kind: str, setting: str, load: int, work: Path) -> dict:
    """One fresh process running ``kind`` at ``setting`` beside ``load`` spinning processes."""
    return run_beside_load([__file__, "--worker", kind, "--work", str(work)], setting, load)


def run(work: Path, loads: list[int], repeats: int, workloads: list[str]) -> str:
    lines = [f"{cpu_model()}, {os.cpu_count()} cores; median seconds of {repeats} runs (each a fresh process)", "",
             "| workload | load | default | 1 thread | 2 threads | default / best | default chose |",
             "|---|---|---|---|---|---|---|"]
    for kind in workloads:
        for load in loads:
            seconds, chosen = {}, ""
            for setting in SETTINGS:
                results = [measure(kind, setting, load, work) for _ in range(repeats)]
                seconds[setting] = statistics.median(r["seconds"] for r in results)
                if setting == "default":
                    chosen = "/".join(sorted({str(r["pools"].get("torch")) for r in results}))
            best = min(seconds.values())
            row = (f"| {kind} | {load} busy | {seconds['default']:.2f} | {seconds['1']:.2f} | {seconds['2']:.2f} | "
                   f"{seconds['default'] / best:.2f}x | {chosen} |")
            print(row, flush=True)
            lines.append(row)
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("runs/bench-threads"))
    parser.add_argument("--load", type=int, default=2, help="competing busy processes in the loaded runs")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workloads", default=",".join(WORKLOADS))
    parser.add_argument("--worker", choices=WORKLOADS, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.work)))
        return
    args.work.mkdir(parents=True, exist_ok=True)
    prepare(args.work)
    print(run(args.work, [0, args.load], args.repeats, args.workloads.split(",")))


if __name__ == "__main__":
    main()
