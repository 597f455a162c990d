"""What a frame costs: describing one camera frame as the localiser does, per engine; then stage by stage (decode, resize, normalise, network) per encoder
and engine (torch, ONNX Runtime), at 1 and 2 threads, idle and beside a load; then the whole-batch path (``map
build`` over Gardens Point Walking's day_left and day_right, 400 images) per engine, and the agreement of the
engines: descriptors' largest difference and Recall@K on Gardens Point Walking and Nordland.

Run from the repository root (CPU, about 6 minutes, ``../shared/data`` beside the checkout):

    .venv/bin/python bench/bench_frame_cost.py --work runs/frame-cost [--parts frame,stages,build,agreement]

Stages use one 960x540 Gardens Point JPEG: decode (PIL), resize to 320x240 (bilinear, as seqvpr reads), normalise
(uint8 -> float32 in [0, 1], [1, 3, H, W]), the network (torch: the backbone and the pooling head, timed together
and apart; ONNX Runtime: the exported network, both at once). Medians over ``--frames`` runs; the ratio is the ONNX
network's time over torch's in the same process. ``--load`` processes each spin one core beside the measurement.
The agreement part is the yardstick: the engines must give the same figures.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _common import cpu_model, median_time, spin_load

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
ENCODERS = {"efficientnet-lite0": "imagenet", "resnet18": None, "resnet50": None}


def median_ms(function, frames: int) -> float:
    return median_time(function, frames) * 1e3


def stage_times(image_path: Path, encoder: str, threads: int, frames: int) -> dict[str, float]:
    """Milliseconds a stage for one frame, in this process at ``threads`` threads."""
    import torch
    from PIL import Image

    from seqvpr.features.engines import with_engine
    from seqvpr.features.extraction import ExtractorConfig, build_extractor

    torch.set_num_threads(threads)
    data = image_path.read_bytes()
    import io

    decoded = Image.open(io.BytesIO(data)).convert("RGB")
    resized = decoded.resize((320, 240), Image.BILINEAR)
    batch = torch.from_numpy(np.asarray(resized, dtype=np.float32) / 255.0).permute(2, 0, 1)[None]
    module = build_extractor(ExtractorConfig(encoder, ENCODERS[encoder])).eval()
    onnx = with_engine(module, 320, 240, "onnx")
    onnx.session.get_session_options()  # built with the thread count set above
    channels_last = module.to(memory_format=torch.channels_last)
    features = channels_last.backbone.features
    with torch.no_grad():
        mapped = features((batch - channels_last.mean) / channels_last.std)
        times = {
            "decode": median_ms(lambda: Image.open(io.BytesIO(data)).convert("RGB"), frames),
            "resize": median_ms(lambda: decoded.resize((320, 240), Image.BILINEAR), frames),
            "normalise": median_ms(lambda: torch.from_numpy(np.asarray(resized, dtype=np.float32) / 255.0)
                                   .permute(2, 0, 1)[None], frames),
            "torch backbone": median_ms(lambda: features((batch.contiguous(memory_format=torch.channels_last)
                                                          - channels_last.mean) / channels_last.std), frames),
            "torch pooling": median_ms(lambda: channels_last.pooling(mapped), frames),
            "torch network": median_ms(lambda: channels_last(batch.contiguous(memory_format=torch.channels_last)),
                                       frames),
            "onnx network": median_ms(lambda: onnx(batch), frames),
        }
    times["onnx / torch"] = times["onnx network"] / times["torch network"]
    return times


def run_stages(args) -> list[str]:
    image = sorted((args.data / "gardenspoint_walking" / "day_left").glob("*.jpg"))[0]
    lines = ["| encoder | threads | load | decode | resize | normalise | torch backbone | torch pooling | torch network "
             "| onnx network | onnx / torch |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for encoder in args.encoders.split(","):
        for threads in (1, 2):
            for load in (0, args.load):
                spinners = spin_load(load) if load else []
                try:
                    done = subprocess.run([sys.executable, __file__, "--measure", str(image), encoder, str(threads),
                                           str(args.frames)], capture_output=True, text=True, check=True,
                                          env={**os.environ, "SEQVPR_CACHE": str(args.work / "cache")})
                finally:
                    for spinner in spinners:
                        spinner.kill()
                        spinner.wait()
                t = json.loads(done.stdout.strip().splitlines()[-1])
                lines.append(f"| {encoder} | {threads} | {load} | " + " | ".join(
                    f"{t[k]:.2f}" if k == "onnx / torch" else f"{t[k]:.1f}" for k in (
                        "decode", "resize", "normalise", "torch backbone", "torch pooling", "torch network",
                        "onnx network", "onnx / torch")) + " |")
                print(lines[-1], flush=True)
    return lines


def frame_times(threads: int, frames: int) -> dict[str, float]:
    """Milliseconds to describe one 320x240 camera frame (``ImageDescriber.encode``: what the localiser and the node
    run) per engine, in this process at ``threads`` threads, and the engines' largest difference."""
    import torch

    from seqvpr.localization.encoder import ImageDescriber
    from seqvpr.maps.build import FrameDescription

    torch.set_num_threads(threads)
    frame = np.random.default_rng(0).integers(0, 255, (240, 320, 3), dtype=np.uint8)
    describers = {engine: ImageDescriber(FrameDescription("efficientnet-lite0"), {}, "cpu", engine)
                  for engine in ("torch", "auto")}
    times = {engine: median_ms(lambda d=d: d.encode(frame), frames) for engine, d in describers.items()}
    times["difference"] = float((describers["torch"].encode(frame) - describers["auto"].encode(frame)).abs().max())
    return times


def run_frame(args) -> list[str]:
    lines = ["| one 320x240 frame, Lite0 + GeM | threads | torch ms | auto (ONNX Runtime) ms | auto / torch | max abs "
             "difference |", "|---|---:|---:|---:|---:|---:|"]
    for threads in (1, 2):
        done = subprocess.run([sys.executable, __file__, "--frame", str(threads), str(args.frames)], check=True,
                              capture_output=True, text=True, env={**os.environ, "SEQVPR_CACHE": str(args.work / "cache")})
        t = json.loads(done.stdout.strip().splitlines()[-1])
        lines.append(f"| ImageDescriber.encode | {threads} | {t['torch']:.1f} | {t['auto']:.1f} | "
                     f"{t['auto'] / t['torch']:.2f} | {t['difference']:.1e} |")
        print(lines[-1], flush=True)
    return lines


def run_build(args) -> list[str]:
    """``map build`` over the 400 Gardens Point Walking day images, Lite0 at 320x240, per engine: the command's wall
    time (a fresh process each, start-up included) and the build's own time in one warm process (``build_map``:
    describing, checking and writing; the images' throughput), alternated, the second of each counting. Each run has
    a new descriptor cache (nothing reused); the ONNX export, made once, is warm in the encoder cache."""
    import seqvpr

    walking = args.data / "gardenspoint_walking"
    sources = [str(walking / "day_left"), str(walking / "day_right")]
    env = {**os.environ, "SEQVPR_CACHE": str(args.work / "cache"), "PYTHONPATH": str(ROOT / "src")}
    os.environ["SEQVPR_CACHE"] = env["SEQVPR_CACHE"]
    command, inside = {}, {}
    for run, engine in enumerate(("onnx", "torch", "onnx", "torch")):
        out, cache = args.work / f"map-{engine}", args.work / f"descriptors-{run}"  # a new descriptor cache: no reuse
        for folder in (cache, args.work / f"descriptors-{run}-in"):
            shutil.rmtree(folder, ignore_errors=True)
        started = time.perf_counter()
        subprocess.run([sys.executable, "-m", "seqvpr.cli", "map", "build", *sources, "--descriptor",
                        "efficientnet-lite0", "--engine", engine, "--cache-dir", cache, "--out", out], env=env,
                       check=True, capture_output=True)
        command[engine] = time.perf_counter() - started
        from seqvpr.maps import FrameDescription

        description = FrameDescription("efficientnet-lite0")
        started = time.perf_counter()
        seqvpr.build_map(sources, out, description, engine=engine, cache_dir=args.work / f"descriptors-{run}-in")
        inside[engine] = time.perf_counter() - started
    return ["| map build, 400 images, Lite0 320x240 | torch s | onnx s | onnx / torch |", "|---|---:|---:|---:|",
            f"| the command (fresh process) | {command['torch']:.1f} | {command['onnx']:.1f} | "
            f"{command['onnx'] / command['torch']:.2f} |",
            f"| build_map in a warm process | {inside['torch']:.1f} | {inside['onnx']:.1f} | "
            f"{inside['onnx'] / inside['torch']:.2f} |"]


def run_agreement(args) -> list[str]:
    """Largest descriptor difference and Recall@1/5 per engine: Gardens Point Walking day_left vs night_right (Lite0,
    320x240, 2 frames) and Nordland 64x32 summer vs winter frames 0-399 (Lite0 at 64x32, 1 frame), L = 5."""
    import seqvpr

    data, lines = args.data, ["| data | encoder | max abs difference | R@1 torch / onnx | R@5 torch / onnx |",
                              "|---|---|---:|---|---|"]
    cases = [("Gardens Point Walking", data / "gardenspoint_walking" / "day_left",
              data / "gardenspoint_walking" / "night_right", (320, 240), "2f"),
             ("Nordland 0-399", data / "nordland_64x32" / "summer", data / "nordland_64x32" / "winter", (64, 32), "1f")]
    os.environ["SEQVPR_CACHE"] = str(args.work / "cache")
    from seqvpr.features.describe import describe
    from seqvpr.features.extraction import ExtractorConfig

    for name, reference, query, size, radius in cases:
        found = {}
        for engine in ("torch", "onnx"):
            sides = []
            for folder, role in ((reference, "reference"), (query, "query")):
                traversal = seqvpr.load_traversal(str(folder), role)
                traversal = traversal.slice_frames(0, 400) if len(traversal) > 400 else traversal
                sides.append(describe(traversal, "efficientnet-lite0", extractor=ExtractorConfig(
                    width=size[0], height=size[1]), engine=engine))
            result = seqvpr.match(sides[0], sides[1], "matching", seq_len=5)
            found[engine] = (sides, seqvpr.evaluate(result, radius=radius, ks=(1, 5)).recall)
        difference = max(float(np.abs(a.descriptors - b.descriptors).max())
                         for a, b in zip(found["torch"][0], found["onnx"][0]))
        lines.append(f"| {name} | Lite0 {size[0]}x{size[1]} | {difference:.1e} | "
                     f"{found['torch'][1][1]:.3f} / {found['onnx'][1][1]:.3f} | "
                     f"{found['torch'][1][5]:.3f} / {found['onnx'][1][5]:.3f} |")
        print(lines[-1], flush=True)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=Path("runs/frame-cost"))
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    parser.add_argument("--parts", default="frame,stages,build,agreement")
    parser.add_argument("--encoders", default="efficientnet-lite0,resnet18,resnet50")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--load", type=int, default=2, help="spinning processes beside the loaded runs")
    parser.add_argument("--measure", nargs=4, help=argparse.SUPPRESS)
    parser.add_argument("--frame", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.frame:
        print(json.dumps(frame_times(int(args.frame[0]), int(args.frame[1]))))
        return
    if args.measure:
        image, encoder, threads, frames = args.measure
        print(json.dumps(stage_times(Path(image), encoder, int(threads), int(frames))))
        return
    args.work.mkdir(parents=True, exist_ok=True)
    print(f"{cpu_model()}")
    parts = {"frame": run_frame, "stages": run_stages, "build": run_build, "agreement": run_agreement}
    for part in args.parts.split(","):
        print("\n".join(parts[part](args)), "\n", flush=True)


if __name__ == "__main__":
    main()
