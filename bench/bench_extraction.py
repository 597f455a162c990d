"""Benchmark of image -> descriptor extraction: seqvpr's batched extractor against a plain unbatched loop.

Run from the repository root (about a minute on 2 cores):

    .venv/bin/python bench/bench_extraction.py [--images 128] [--size 320x240] [--batch 32] [--threads N] [--repeats 3]

Both sides use the same EfficientNet-Lite0 + GeM model (the packaged ImageNet weights) on the same seeded
generated PNG images written to a temporary folder, and both read and resize every image from disk:

* seqvpr: ``extract_descriptors(paths, ExtractorConfig(width, height, batch_size))`` (no cache): batches of
  ``batch_size`` images are read, then go through the model in CPU micro-batches (``CPU_MICRO_BATCH``) in
  channels-last layout;
* yardstick: for each path, ``load_image`` then ``model(image[None])`` under ``torch.no_grad()``, one at a time.

Each side is warmed up on 8 images, then the two are timed alternately ``--repeats`` times over all images with
``time.perf_counter`` (the median is reported, so a burst of load on the machine hits both); the script checks
that both give the same descriptors (max abs difference) and prints images/s and the ratio.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _common import cpu_model
from PIL import Image

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from seqvpr.threads import use_threads
from seqvpr.features.extraction import ExtractorConfig, build_extractor, extract_descriptors, load_image


def write_images(folder: Path, count: int, width: int, height: int, seed: int = 0) -> list[Path]:
    """Smooth seeded colour images (upsampled noise), saved as PNG."""
    rng = np.random.default_rng(seed)
    paths = []
    for index in range(count):
        coarse = rng.integers(0, 255, size=(6, 8, 3), dtype=np.uint8)
        image = Image.fromarray(coarse).resize((width, height), Image.BILINEAR)
        path = folder / f"{index:05d}.png"
        image.save(path)
        paths.append(path)
    return paths


def unbatched(model, paths: list[Path], width: int, height: int) -> np.ndarray:
    with torch.no_grad():
        return np.stack([model(load_image(p, width, height)[None])[0].numpy() for p in paths])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--images", type=int, default=128)
    parser.add_argument("--size", default="320x240", help="input WIDTHxHEIGHT")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    use_threads(args.threads)  # the one policy: the library re-asserts it, so a bare torch count would not hold
    width, height = (int(v) for v in args.size.split("x"))
    config = ExtractorConfig(width=width, height=height, batch_size=args.batch)
    model = build_extractor(config)
    print(f"CPU: {cpu_model()} ({os.cpu_count()} logical CPUs); torch {torch.__version__} threads={torch.get_num_threads()}")
    print(f"model: EfficientNet-Lite0 + GeM (1280-D), input {width}x{height}, batch {args.batch}, {args.images} images")
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_images(Path(tmp), args.images, width, height)
        extract_descriptors(paths[:8], config, extractor=model)
        unbatched(model, paths[:8], width, height)
        fast_times, slow_times = [], []
        for _ in range(args.repeats):
            start = time.perf_counter()
            fast = extract_descriptors(paths, config, extractor=model).descriptors
            fast_times.append(time.perf_counter() - start)
            start = time.perf_counter()
            slow = unbatched(model.to(memory_format=torch.contiguous_format), paths, width, height)
            slow_times.append(time.perf_counter() - start)
    fast_s, slow_s = float(np.median(fast_times)), float(np.median(slow_times))
    print(f"same descriptors: max abs difference {np.abs(fast - slow).max():.2e}")
    print(f"seqvpr batched:   {fast_s:7.2f} s  {args.images / fast_s:7.1f} images/s  (median of {args.repeats})")
    print(f"unbatched loop:   {slow_s:7.2f} s  {args.images / slow_s:7.1f} images/s  (median of {args.repeats})")
    print(f"ratio seqvpr / unbatched throughput = {slow_s / fast_s:.2f}x")


if __name__ == "__main__":
    main()
