"""Descriptor comparison on real images: R@1/5/20 at L = 1 and L = 5 for each image descriptor.

Run from the repository root with ../shared/data beside the checkout (about 10 minutes on 2 cores):

    .venv/bin/python bench/bench_descriptors.py [--data ../shared/data] [--cache-dir runs/desc-cache] [--only NAME]

Datasets (reference, query, ground truth):

* corridor: ``ref/`` vs ``query/`` (111 frames each, 160x120), VPR-Bench ground truth file (+-2 frames);
* nordland_64x32: summer vs winter, frames [17, 2000), +-1 frame;
* gardenspoint_walking: the real colour images, ``day_left/`` vs ``night_right/`` (200 frames each, day/night and
  left/right at once), +-2 frames, read at 384x216 (16:9, as the images).

Descriptors: EfficientNet-Lite0 (packaged ImageNet weights) + GeM; EfficientNet-Lite0 + NetVLAD (64 clusters,
k-means over the reference's local features) + PCA-whitening fitted on the reference (to 4096 dimensions or
reference frames - 1), and, to show what the whitening does, to 256 dimensions and not at all; the weight-free
patch-normalised thumbnails (64x32, 8 px patches). Every row is the same
pipeline ``seqvpr match`` runs; the equivalent command is printed with each table.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, replace
from pathlib import Path

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from seqvpr.data.ground_truth import parse_radius
from seqvpr.data.sources import load_traversal
from seqvpr.features.extraction import ExtractorConfig
from seqvpr.features.patchnorm import PatchNormConfig
from seqvpr.matchers.sequence import SequenceMatcher
from seqvpr.evaluation.ground_truth import ground_truth
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.features.describe import describe, netvlad_extractor, whiten_pair
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec


@dataclass(frozen=True)
class Dataset:
    name: str
    reference: str
    query: str
    frames: tuple[int | None, int | None]
    radius: str | None
    gt_file: str | None
    image_size: tuple[int, int]


@dataclass(frozen=True)
class Descriptor:
    name: str
    flags: str
    pooling: str | None  # None: patchnorm
    pca_dim: int = 0


DESCRIPTORS = (
    Descriptor("EfficientNet-Lite0 + GeM", "--descriptor efficientnet-lite0", "gem"),
    Descriptor("EfficientNet-Lite0 + NetVLAD + PCA-W", "--descriptor efficientnet-lite0 --pooling netvlad --pca-dim 4096",
               "netvlad", 4096),
    Descriptor("EfficientNet-Lite0 + NetVLAD + PCA-W 256", "--descriptor efficientnet-lite0 --pooling netvlad --pca-dim 256",
               "netvlad", 256),
    Descriptor("EfficientNet-Lite0 + NetVLAD, no whitening", "--descriptor efficientnet-lite0 --pooling netvlad",
               "netvlad"),
    Descriptor("patch-normalised 64x32", "--descriptor patchnorm", None),
)


def datasets(root: Path) -> list[Dataset]:
    corridor, nordland, walking = root / "corridor", root / "nordland_64x32", root / "gardenspoint_walking"
    return [
        Dataset("corridor", str(corridor / "ref"), str(corridor / "query"), (None, None), None,
                str(corridor / "ground_truth_new.npy"), (320, 240)),
        Dataset("nordland_64x32", str(nordland / "summer"), str(nordland / "winter"), (17, 2000), "1f", None, (256, 128)),
        Dataset("gardenspoint_walking", str(walking / "day_left"), str(walking / "night_right"), (None, None), "2f",
                None, (384, 216)),
    ]


def described_pair(data: Dataset, descriptor: Descriptor, cache_dir: str | None):
    """Reference and query traversals with the descriptor's vectors (whitened when it says so)."""
    ref, qry = load_traversal(data.reference, "reference"), load_traversal(data.query, "query")
    ref, qry = ref.slice_frames(*data.frames), qry.slice_frames(*data.frames)
    gt = ground_truth(ref, qry, parse_radius(data.radius) if data.radius else None, data.gt_file)
    if descriptor.pooling is None:
        return describe(ref), describe(qry), gt
    config = ExtractorConfig(pooling=descriptor.pooling, width=data.image_size[0], height=data.image_size[1])
    model = netvlad_extractor(config, ref.image_paths) if descriptor.pooling == "netvlad" else None
    options = {"extractor": config, "cache_dir": cache_dir, "model": model}
    ref, qry = describe(ref, "efficientnet-lite0", PatchNormConfig(), **options), describe(qry, "efficientnet-lite0", PatchNormConfig(), **options)
    if descriptor.pca_dim:
        ref, qry, _ = whiten_pair(ref, qry, descriptor.pca_dim)
    return ref, qry, gt


def command(data: Dataset, descriptor: Descriptor) -> str:
    frames = f" --frames {data.frames[0]}:{data.frames[1]}" if data.frames[0] is not None else ""
    truth = f" --ground-truth {data.gt_file}" if data.gt_file else f" --radius {data.radius}"
    size = f" --image-size {data.image_size[0]}x{data.image_size[1]}" if descriptor.pooling else ""
    return f"seqvpr match -r {data.reference} -q {data.query}{frames}{truth} {descriptor.flags}{size} -L {{1,5}} --k 1,5,20"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    parser.add_argument("--cache-dir", default=None, help="extraction cache (reused across runs)")
    parser.add_argument("--only", action="append", help="run only this dataset (repeatable)")
    args = parser.parse_args()
    root = Path(args.data)
    if not root.is_dir():
        sys.exit(f"{root}: no such folder (the shared datasets)")
    for data in datasets(root):
        if args.only and data.name not in args.only:
            continue
        print(f"\n### {data.name}\n")
        print("| descriptor | dim | L=1 R@1 | R@5 | R@20 | L=5 R@1 | R@5 | R@20 |")
        print("|---|---|---|---|---|---|---|---|")
        commands = []
        for descriptor in DESCRIPTORS:
            ref, qry, gt = described_pair(data, descriptor, args.cache_dir)
            cells = []
            for length in (1, 5):
                result = SequenceMatcher(replace(MatchSettings(), sequence=SequenceSpec(length))).topk(ref, qry)
                recall = evaluate_match(result, gt, (1, 5, 20)).recall
                cells += [f"{recall[k]:.3f}" for k in (1, 5, 20)]
            print(f"| {descriptor.name} | {ref.descriptors.shape[1]} | " + " | ".join(cells) + " |", flush=True)
            commands.append(command(data, descriptor))
        print("\nCommands:\n\n```\n" + "\n".join(commands) + "\n```")


if __name__ == "__main__":
    main()
