"""Which frame encoder suits Nordland's 64x32 thumbnails as JIST's start? Untrained candidates on the selection
frames (1200-1599), scored through ``seqvpr.match``: single-image retrieval, SeqGeM at L = 5 and sequence matching
at L = 5, with the seconds to describe both sides.

Candidates: patch-normalised pixels (the dataset's own baseline, no encoder), and ImageNet EfficientNet-Lite0 + GeM
reading the thumbnails at their native 64x32 (a 2x1 last feature map) and upsampled 2x, 3x and 4x (4x2, 6x3, 8x4).

    .venv/bin/python bench/bench_jist_encoders.py [--data ../shared/data] [--frames 1200:1600]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from _common import cpu_model

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from seqvpr.api import match
from seqvpr.data.ground_truth import Radius, ground_truth_within_radius
from seqvpr.data.sources import load_pair
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.features.describe import describe
from seqvpr.features.extraction import ExtractorConfig
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec

SIZES = ("64x32", "128x64", "192x96", "256x128")
KS = (1, 5)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--frames", default="1200:1600")
    args = parser.parse_args()
    folder = args.data / "nordland_64x32"
    pair = load_pair(str(folder / "summer"), str(folder / "winter"), args.frames)
    gt = ground_truth_within_radius(pair[1], pair[0], Radius(1.0, "frames"))
    print(f"{cpu_model()}, {torch.get_num_threads()} threads, frames {args.frames}")
    print("| encoder | seconds | single R@1 | SeqGeM L=5 R@1 / R@5 | matching L=5 R@1 / R@5 |\n|---|---:|---:|---:|---:|")
    candidates = [("patch-normalised pixels", "patchnorm", None)]
    candidates += [(f"Lite0 ImageNet GeM at {s}", "efficientnet-lite0", s) for s in SIZES]
    for name, descriptor, size in candidates:
        started = time.perf_counter()
        if size is None:
            described = tuple(describe(t, "patchnorm") for t in pair)
        else:
            width, height = (int(v) for v in size.split("x"))
            extractor = ExtractorConfig("efficientnet-lite0", "imagenet", width=width, height=height)
            described = tuple(describe(t, descriptor, extractor=extractor) for t in pair)
        seconds = time.perf_counter() - started
        cells = []
        for method, length in (("single", 1), ("seqgem", 5), ("matching", 5)):
            result = match(*described, method, settings=MatchSettings(SequenceSpec(length), k=max(KS)))
            recall = evaluate_match(result, gt, KS).recall
            cells.append(f"{recall[1]:.3f}" if method == "single" else f"{recall[1]:.3f} / {recall[5]:.3f}")
        print(f"| {name} | {seconds:.1f} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
