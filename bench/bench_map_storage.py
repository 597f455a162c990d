"""Compact maps on real data: bytes per frame against Recall@1 for float32, float16, sq8 (8-bit codes) and pq:M
(product-quantised, M bytes a frame) maps.

Run from the repository root (CPU, under a minute; needs ../shared/data):

    .venv/bin/python bench/bench_map_storage.py --work runs/bench-map-storage

Datasets: Nordland 64x32 (patch-normalised, 2048-D; summer map, winter query, frames 17-1999, ±1 frame) and
Gardens Point DELF-HDC (4096-D; day_left map, night_right query, ±2 frames). Each map is built with ``build_map``
and matched exactly with ``match_map`` (frame matching reads the coded rows decoded) at L = 1, 5 and 10.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from seqvpr.data.ground_truth import parse_radius
from seqvpr.data.sources import load_traversal
from seqvpr.data.traversal import slice_frame_range
from seqvpr.errors import SeqvprError
from seqvpr.maps import build_map, match_map
from seqvpr.evaluation.ground_truth import ground_truth
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.features.describe import describe
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec

GARDENS = "gardenspoint_delf_hdc/descriptors/GardensPointWalking/{}/delf_hdc_4096_ortho_sigma_nx5ny7.mat"
LENGTHS = (1, 5, 10)


def datasets(data: Path) -> dict[str, tuple[str, object, str, str | None]]:
    """name -> (map source, query traversal, radius, frames)."""
    nordland = data / "nordland_64x32"
    winter = describe(slice_frame_range(load_traversal(nordland / "winter", "query"), "17:2000"))
    return {
        "Nordland (2048-D)": (str(nordland / "summer"), winter, "1f", "17:2000"),
        "Gardens Point DELF-HDC (4096-D)": (str(data / GARDENS.format("day_left")),
                                            load_traversal(data / GARDENS.format("night_right"), "query"), "2f", None),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    args = parser.parse_args()
    lines = ["| dataset | storage | bytes / frame | " + " | ".join(f"R@1 L={n}" for n in LENGTHS) + " |",
             "|---|---|---:|" + "---:|" * len(LENGTHS)]
    for name, (source, query, radius, frames) in datasets(args.data).items():
        for dtype in ("float32", "float16", "sq8", "pq:256", "pq:64"):
            try:
                saved = build_map([source], args.work / f"{name.split()[0]}-{dtype.replace(':', '')}", dtype=dtype,
                                  frames=frames)
            except SeqvprError as error:  # PQ codebooks need 256 frames: Gardens Point has 200
                lines.append(f"| {name} | {dtype} | – | " + " | ".join("–" for _ in LENGTHS) + f" | ({error})")
                continue
            gt = ground_truth(saved.frames, query, parse_radius(radius))
            recalls = []
            for length in LENGTHS:
                result = match_map(saved, query, "matching", MatchSettings(SequenceSpec(length), k=20))
                recalls.append(evaluate_match(result, gt, (1,)).recall[1])
            per_frame = saved.descriptors.nbytes // saved.info.count
            lines.append(f"| {name} | {dtype} | {per_frame:,} | " + " | ".join(f"{r:.3f}" for r in recalls) + " |")
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    (args.work / "results.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
