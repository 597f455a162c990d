"""Does JIST learn? Trained JIST against its own frozen start and untrained SeqGeM, on a held-out test pair.

Run from the repository root (CPU: about 15-40 minutes per dataset on 2 cores, see BENCHMARKS.md):

    .venv/bin/python bench/bench_jist.py demo --out runs/jist-demo
    .venv/bin/python bench/bench_jist.py gardenspoint --out runs/jist-gp [--data ../shared/data]

Datasets and splits:

* ``demo``: the rendered demo world (``write_demo_world``, 600 frames a traversal, 320x240, night queries one lane
  over); JIST trains on the train route's frames 0-449, selects its epoch on frames 450-599 and is tested on the
  whole test route (another part of the city). Radius 10 m (positives), negatives outside 25 m.
* ``gardenspoint``: the real colour images of Gardens Point Walking, reference ``day_left``, query
  ``night_right`` (day/night and left/right at once), frame-aligned: training frames 0-99, selection 100-129,
  test 130-199 (``--fold a``, the benchmark's Gardens Point split) or training 100-199, selection 70-99, test 0-69
  (``--fold b``), radius 2 frames (negatives outside 5). ``--extra day_right`` adds the third traversal's training
  frames to the classification branch.

Every row is scored on the test pair at L = 5 through ``seqvpr.match`` (what ``seqvpr match`` runs):

* ``single`` / ``seqgem``: the backbone's own descriptors (ImageNet EfficientNet-Lite0 + GeM, no training) by
  single-image retrieval and by untrained SeqGeM (p = 3);
* ``JIST frozen start``: the JIST model before any step (the seeded random head on the frozen backbone: what the
  training run's epoch 0 is);
* ``JIST trained``: the epoch with the best validation R@5 (JIST's selection).

The script prints a Markdown table and writes it, with the run's settings and seconds, to ``OUT/results.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

import torch
from _common import cpu_model

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from seqvpr.data.ground_truth import Radius
from seqvpr.data.sources import load_pair
from seqvpr.data.traversal import slice_frame_range
from seqvpr.evaluation.metrics import Evaluation
from seqvpr.experiments.jist_ablation import JistSplit, save_start, score, score_model
from seqvpr.features.describe import describe
from seqvpr.features.extraction import ExtractorConfig
from seqvpr.training.data import classification_traversals, training_data
from seqvpr.training.jist import jist_setup, train_jist

KS = (1, 5, 10)
LENGTH = 5


def demo_pairs(out: Path) -> tuple[tuple, tuple, tuple, Radius]:
    """Train, validation and test pairs of the rendered demo world (rendered once into ``out/world``)."""
    from seqvpr.synthetic.world import write_demo_world

    world = out / "world"
    if not (world / "test_query").is_dir():
        write_demo_world(world, frames=600, width=320, height=240, seed=0, query_condition="night")
    train_route = load_pair(str(world / "train_reference"), str(world / "train_query"))
    test = load_pair(str(world / "test_reference"), str(world / "test_query"))
    train = tuple(slice_frame_range(t, "0:450", "train") for t in train_route)
    validation = tuple(slice_frame_range(t, "450:600", "validation") for t in train_route)
    return train, validation, test, Radius(10.0, "m")


#: Gardens Point folds: training, selection and test frames (fold b mirrors fold a along the walk)
GP_FOLDS = {"a": ("0:100", "100:130", "130:200"), "b": ("100:200", "70:100", "0:70")}


def gardenspoint_pairs(data: Path, fold: str) -> tuple[tuple, tuple, tuple, Radius]:
    """Train, validation and test pairs of Gardens Point Walking (day_left reference, night_right query)."""
    folder = data / "gardenspoint_walking"
    whole = load_pair(str(folder / "day_left"), str(folder / "night_right"))
    cut = lambda frames: tuple(slice_frame_range(t, frames, frames) for t in whole)  # noqa: E731
    train, select, test = GP_FOLDS[fold]
    return cut(train), cut(select), cut(test), Radius(2.0, "frames")


def table(rows: list[tuple[str, Evaluation]]) -> str:
    lines = ["| L = 5 | " + " | ".join(f"R@{k}" for k in KS) + " | queries |", "|---" * (len(KS) + 2) + "|"]
    for name, evaluation in rows:
        cells = " | ".join(f"{evaluation.recall[k]:.3f}" for k in KS)
        lines.append(f"| {name} | {cells} | {evaluation.queries_evaluated} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", choices=("demo", "gardenspoint"))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--size", default=None, help="Training and test image size WxH (demo 160x120; GP 256x144 on "
                        "the CPU, the reference's 640x480 on CUDA).")
    parser.add_argument("--device", default="cpu", help="torch device: cpu, or cuda (mixed precision, JIST's default "
                        "there: the GPU recipe).")
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--refreshes", type=int, default=6)
    parser.add_argument("--iterations", type=int, default=10, help="Steps per refresh (max_iterations).")
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--stages", default="stage6,stage7,head", help="Backbone stages to train (comma list).")
    parser.add_argument("--select", type=int, default=5, choices=KS, help="Keep the epoch with the best validation R@K.")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fold", choices=sorted(GP_FOLDS), default="a",
                        help="gardenspoint: a = train 0-99, select 100-129, test 130-199; b = train 100-199, "
                             "select 70-99, test 0-69.")
    parser.add_argument("--extra", default=None,
                        help="gardenspoint: another traversal (day_right) whose training frames join the "
                             "classification branch's images (all conditions of a place).")
    args = parser.parse_args()
    started = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.dataset == "demo":
        (train, validation, test, radius), size, cell = demo_pairs(args.out), args.size or "160x120", 10.0
    else:
        gp_size = "640x480" if args.device.startswith("cuda") else "256x144"
        (train, validation, test, radius), size, cell = gardenspoint_pairs(args.data, args.fold), args.size or gp_size, 4.0
    width, height = (int(v) for v in size.split("x"))
    values = {
        "backbone": "efficientnet-lite0", "weights": "imagenet", "trainable_stages": args.stages.split(","),
        "lr": args.lr, "width": width, "height": height, "epochs": args.epochs, "refreshes": args.refreshes,
        "max_iterations": args.iterations, "queries_per_refresh": 4 * args.iterations, "negative_pool": 1000,
        "cell_m": cell, "min_images": 4, "seed": args.seed, "ks": list(KS), "select_k": args.select,
        "device": args.device,
    }
    config, settings = jist_setup(values, LENGTH)
    split = JistSplit(train, validation, test, radius)
    data = training_data("jist", train, validation, radius)
    extra = [str(args.data / "gardenspoint_walking" / args.extra)] if args.extra else []
    classification = classification_traversals(data, extra, GP_FOLDS[args.fold][0])
    result = train_jist(data, config, settings, args.out / "run", resume=True, classification=classification)
    trained_seconds = time.perf_counter() - started
    extractor = ExtractorConfig("efficientnet-lite0", "imagenet", width=width, height=height)
    described = tuple(describe(t, "efficientnet-lite0", extractor=extractor, device=args.device) for t in test)
    rows = [
        ("single (ImageNet GeM)", score("single", described, split, LENGTH)),
        ("SeqGeM, untrained (ImageNet GeM)", score("seqgem", described, split, LENGTH)),
        ("JIST frozen start", score_model(save_start(args.out / "frozen", config, settings), split, device=args.device)),
        (f"JIST trained (epoch {result.best_epoch})", score_model(result.folder, split, device=args.device)),
    ]
    text = table(rows)
    history = [{"epoch": r.epoch, "loss": round(r.loss, 3), "recall": r.recall, "seconds": round(r.epoch_seconds, 1)}
               for r in result.history]
    where = torch.cuda.get_device_name() if args.device.startswith("cuda") else f"{cpu_model()}, {torch.get_num_threads()} threads"
    report = (f"{args.dataset} at {width}x{height} on {args.device}: {where}, "
              f"{time.perf_counter() - started:.0f} s in all ({trained_seconds:.0f} s to train)\n\n{text}\n\n"
              f"settings: {json.dumps(values)}\nfold: {args.fold}, classification extra: {args.extra}\nmodel: {json.dumps(asdict(config))}\nhistory: {json.dumps(history)}\n")
    (args.out / "results.md").write_text(report)
    print(report)


if __name__ == "__main__":
    main()
