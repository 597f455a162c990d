"""The one GPU check: every CUDA path of seqvpr in one run, each against the CPU, as a table.

Run from the repository root; on a lent GPU machine this is the one call to make (about 5 minutes at full size):

    .venv/bin/python bench/gpu_check.py --device cuda --work runs/gpu-check            # full size
    .venv/bin/python bench/gpu_check.py --device cpu --size tiny --work /tmp/gpu-check  # what the test suite runs

Rows:

* ``match <method>``: ``seqvpr.match`` of every method (models with random weights where one is needed; JIST's
  image model is checked by its training row) on ``--device`` against the same call on the CPU: the top-K distances must
  agree rank by rank to 1e-3 (rows within that of each other may swap);
* ``stream <method>``: the method's matcher a frame at a time (``Matcher.stream``) on the device against the CPU;
* ``train seqmatchnet|seqnet|jist``: one epoch of ``seqvpr train`` on the device (JIST under CUDA autocast with a
  gradient scaler, its default there; SeqMatchNet and SeqNet run in float32), which must write a model that loads;
* ``ddp seqmatchnet``: the same under ``torchrun --nproc-per-node 1`` (NCCL on CUDA, gloo on the CPU);
* ``map <N> float16``: a map of N random unit rows stored as float16 (10M at full size), matched by 200 query frames
  at L = 5 on the device and on the CPU (top-1 rows must agree);
* the peak GPU memory allocated (CUDA only).

Exit status 0 when every row is ``ok``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

try:
    import seqvpr  # noqa: F401
except ImportError:  # running from a checkout without an installed package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import seqvpr
from seqvpr.data.sources import save_traversal_npz
from seqvpr.data.traversal import Traversal
from seqvpr.methods import METHODS, build_matcher
from seqvpr.models.configs import TransformConfig
from seqvpr.models.registry import TrainedModel
from seqvpr.models.seqmatchnet import FrameTransform
from seqvpr.sequences.descriptors import SeqNet
from seqvpr.synthetic.routes import generate_route

SIZES = {"tiny": {"frames": 150, "dim": 16, "map": 20_000, "world": 40, "image": (64, 48)},
         "full": {"frames": 2000, "dim": 256, "map": 10_000_000, "world": 120, "image": (320, 240)}}
STREAMED = ("matching", "single", "hmm")


@dataclass
class Row:
    check: str
    status: str
    seconds: float
    note: str


def timed(check: str, work: Callable[[], str]) -> Row:
    """One check: ``ok`` and its note, or ``FAILED`` and the error's last line."""
    started = time.perf_counter()
    try:
        note = work()
        status = "ok"
    except Exception as error:  # every check runs, whatever failed before it
        traceback.print_exc()
        status, note = "FAILED", f"{type(error).__name__}: {str(error).splitlines()[0][:100] if str(error) else ''}"
    return Row(check, status, time.perf_counter() - started, note)


def same_topk(device_result, cpu_result, compared: np.ndarray | None = None) -> str:
    """The device's top-K distances equal the CPU's rank by rank to 1e-3 (a one-line difference otherwise), over
    the ``compared`` queries (all by default). Rows may differ only where that holds: two rows within 1e-3 of each
    other may swap in float arithmetic."""
    a, b = device_result.topk, cpu_result.topk
    if compared is not None:
        a, b = replace(a, indices=a.indices[compared], distances=a.distances[compared]), \
            replace(b, indices=b.indices[compared], distances=b.distances[compared])
    finite = np.isfinite(b.distances)
    if not np.array_equal(finite, np.isfinite(a.distances)):
        raise AssertionError(f"{int((finite != np.isfinite(a.distances)).any(1).sum())} queries found another "
                             "number of candidates")
    gap = float(np.abs(a.distances[finite] - b.distances[finite]).max()) if finite.any() else 0.0
    if gap > 1e-3:
        raise AssertionError(f"distances differ by up to {gap:.2g}")
    swapped = int((a.indices != b.indices).any(1).sum())
    note = f"{len(a.indices)} queries, max |d| gap {gap:.1e}"
    return note + (f"; {swapped} swap rows within that gap" if swapped else "; every row the CPU's")


def random_models(dim: int) -> dict[str, TrainedModel]:
    """A SeqMatchNet transform and a SeqNet of random weights (fixed seeds), for the methods that need one."""
    torch.manual_seed(0)
    return {"seqmatchnet": TrainedModel("seqmatchnet", FrameTransform(TransformConfig(dim), seed=1).eval(), 5,
                                        Path("seqmatchnet")),
            "seqnet": TrainedModel("seqnet", SeqNet(dim, dim, 3).eval(), 5, Path("seqnet"))}


def models_for(method: str, models: dict[str, TrainedModel]) -> dict[str, TrainedModel]:
    record = METHODS[method]
    if record.family == "hierarchical":
        return dict(models)
    return {record.needs: models[record.needs]} if record.needs in models else {}


def match_rows(device: str, size: dict) -> list[Row]:
    """Every method by ``seqvpr.match`` on the device against the CPU (JIST describes images: its training row)."""
    reference, query = generate_route(n_frames=size["frames"], dim=size["dim"], seed=3)
    models = random_models(size["dim"])
    rows = []
    for method in METHODS:
        if method == "jist":
            continue
        used = models_for(method, models)
        length = None if METHODS[method].length else 5

        def check(method=method, used=used, length=length) -> str:
            got = seqvpr.match(reference, query, method, seq_len=length, models=used, device=device)
            expected = seqvpr.match(reference, query, method, seq_len=length, models=used, device="cpu")
            if METHODS[method].family != "hierarchical":
                return same_topk(got, expected)
            same = same_shortlists(reference, query, used, device)
            return same_topk(got, expected, same) + f"; {int((~same).sum())} shortlists differ (near-ties)"

        rows.append(timed(f"match {method}", check))
    return rows


def same_shortlists(reference: Traversal, query: Traversal, models: dict, device: str) -> np.ndarray:
    """Per query, whether the SeqNet shortlist (hvpr's and casevpr's first stage, N = 20) holds the same rows on the
    device as on the CPU. Where a near-tie swaps a row across the shortlist's edge the re-ranked result may differ
    legitimately; the shortlist's own ranking is the ``match seqnet`` row."""
    def shortlist(on: str) -> np.ndarray:
        return seqvpr.match(reference, query, "seqnet", seq_len=5, models={"seqnet": models["seqnet"]}, k=20,
                            device=on).topk.indices
    mine, cpu = shortlist(device), shortlist("cpu")
    return np.array([set(a) == set(b) for a, b in zip(mine, cpu)])


def streamed(matcher, reference: Traversal, query: Traversal) -> np.ndarray:
    stepper = matcher.stream(reference)
    found = np.full(len(query), -1)
    for row, frame in enumerate(query.descriptors):
        scored = stepper.push(matcher.prepare_frame(frame))
        if scored is not None:
            found[row] = scored.indices[0]
    return found


def stream_rows(device: str, size: dict) -> list[Row]:
    """The online methods a frame at a time on the device against the CPU (the best row of every frame)."""
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.sequences.windows import SequenceSpec

    reference, query = generate_route(n_frames=min(size["frames"], 400), dim=size["dim"], seed=4)
    rows = []
    for method in STREAMED:
        def check(method=method) -> str:
            spec = SequenceSpec(5, "causal")
            on = streamed(build_matcher(method, MatchSettings(spec, k=5, device=device)), reference, query)
            off = streamed(build_matcher(method, MatchSettings(spec, k=5)), reference, query)
            if not np.array_equal(on, off):
                raise AssertionError(f"best rows differ in {int((on != off).sum())} of {len(query)} frames")
            return f"{len(query)} frames, every best row the CPU's"
        rows.append(timed(f"stream {method}", check))
    return rows


def run_cli(args: list, work: Path) -> str:
    """A ``seqvpr`` command in this process (what a user's command runs, without another interpreter's start-up):
    the first line it printed; its error's last line raised."""
    from click.testing import CliRunner

    from seqvpr.cli import cli

    done = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=True)
    if done.exit_code != 0:
        error = done.exception if done.exception and not isinstance(done.exception, SystemExit) else None
        raise RuntimeError(str(error) if error else (done.output.strip().splitlines() or ["no output"])[-1])
    return (done.stdout.strip().splitlines() or [""])[0][:100]


def run_command(command: list[str], work: Path) -> str:
    done = subprocess.run(command, cwd=work, capture_output=True, text=True, timeout=1800,
                          env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "2")})
    if done.returncode != 0:
        (work / "command.log").write_text(done.stdout + done.stderr)
        lines = done.stderr.strip().splitlines() or ["no output"]
        raise RuntimeError(next((line for line in reversed(lines) if "Error" in line), lines[-1]).strip())
    return (done.stdout.strip().splitlines() or [""])[0][:100]


def training_rows(device: str, size: dict, work: Path) -> list[Row]:
    """One epoch of each trainer on the device, and SeqMatchNet under torchrun with one rank."""
    from seqvpr.synthetic.world import write_demo_world

    reference, query = generate_route(n_frames=size["frames"], dim=size["dim"], seed=5)
    save_traversal_npz(work / "ref.npz", reference)
    save_traversal_npz(work / "qry.npz", query)
    train, val = f"0:{size['frames'] * 3 // 5}", f"{size['frames'] * 3 // 5}:{size['frames'] * 4 // 5}"
    common = ["-r", work / "ref.npz", "-q", work / "qry.npz", "--train-frames", train, "--val-frames", val,
              "--radius", "5m", "-L", "3", "--epochs", "1", "--batch-size", "8", "--device", device]
    width, height = size["image"]
    commands = {
        "train seqmatchnet": (["train", "seqmatchnet", *common, "--out", work / "smn"], work / "smn"),
        "train seqnet": (["train", "seqnet", *common, "--w", "2", "--out", work / "seqnet"], work / "seqnet"),
    }
    rows = [timed(name, lambda c=c, out=out: checked_model(run_cli(c, work), out, device))
            for name, (c, out) in commands.items()]

    def jist() -> str:
        world = write_demo_world(work / "world", frames=size["world"], width=width, height=height, seed=0,
                                 query_condition="dusk")
        n = size["world"]
        run_cli([
            "train", "jist", "-r", world["train_reference"], "-q", world["train_query"], "--train-frames",
            f"0:{n * 3 // 4}", "--val-frames", f"{n * 3 // 4}:{n}", "--radius", "25m", "--pos-radius", "10m",
            "--out-dim", "32", "-L", "3", "--epochs", "1", "--refreshes", "1", "--max-iterations", "2",
            "--batch-size", "2", "--images-per-batch", "8", "--image-size", f"{width}x{height}", "--cell-size", "15",
            "--min-images", "2", "--device", device, "--out", work / "jist"], work)
        return checked_model("", work / "jist", device) + (" (autocast)" if device.startswith("cuda") else "")

    rows.append(timed("train jist", jist))
    launcher = [str(Path(sys.executable).parent / "torchrun"), "--standalone", "--nproc-per-node", "1"]
    # the package's own entry point as a module: no installed console script is needed
    ddp = [*launcher, "-m", "seqvpr.cli", "train", "seqmatchnet", *map(str, common), "--out", str(work / "ddp")]
    rows.append(timed("ddp seqmatchnet", lambda: checked_model(run_command(ddp, work), work / "ddp", device)
                      + (" (nccl)" if device.startswith("cuda") else " (gloo)")))
    return rows


def checked_model(said: str, folder: Path, device: str) -> str:
    """The trained folder loads on the device; its kind (and what the run printed first)."""
    from seqvpr.models.registry import load_trained_model

    model = load_trained_model(folder, device)
    return f"{model.kind} loads on {device}" + (f"; {said}" if said else "")


def map_row(device: str, size: dict, work: Path) -> Row:
    """A map of N unit rows stored as float16, matched on the device and on the CPU."""
    from seqvpr.maps.files import MapInfo, MapSource, write_map

    count, dim = size["map"], 64

    def check() -> str:
        rng = np.random.default_rng(0)
        rows = rng.standard_normal((count, dim), dtype=np.float32)
        rows /= np.linalg.norm(rows, axis=1, keepdims=True)
        frames = Traversal.from_descriptors(rows, "big")
        info = MapInfo(count, dim, "float16", True, {"descriptor": "file"}, (MapSource("random", "big", 0, count),))
        write_map(work / "big", frames, info)
        del frames, rows
        saved = seqvpr.open_map(work / "big")
        start = count // 3
        truth = np.asarray(saved.descriptors[start : start + 200], np.float32)
        noisy = truth + 0.05 * rng.standard_normal(truth.shape, dtype=np.float32)
        query = Traversal.from_descriptors(noisy / np.linalg.norm(noisy, axis=1, keepdims=True), "query")
        started = time.perf_counter()
        on = seqvpr.match(saved, query, "matching", seq_len=5, k=5, device=device)
        seconds = time.perf_counter() - started
        off = seqvpr.match(saved, query, "matching", seq_len=5, k=5, device="cpu")
        if not np.array_equal(on.topk.indices[:, 0], off.topk.indices[:, 0]):
            raise AssertionError("top-1 rows differ from the CPU's")
        hits = float(np.mean(on.topk.indices[2:-2, 0] == np.arange(start + 2, start + 198)))
        return f"{count:,} rows: matched in {seconds:.1f} s on {device}, top-1 = CPU's, R@1 {hits:.2f}"

    return timed(f"map {count:,} float16", check)


def table(rows: list[Row], device: str) -> str:
    lines = [f"device: {device}" + (f" ({torch.cuda.get_device_name()})" if device.startswith("cuda") else ""),
             "| check | status | seconds | note |", "|---|---|---:|---|"]
    lines += [f"| {r.check} | {r.status} | {r.seconds:.1f} | {r.note} |" for r in rows]
    if device.startswith("cuda"):
        lines.append(f"peak GPU memory allocated: {torch.cuda.max_memory_allocated() / 2**30:.2f} GiB")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--size", choices=sorted(SIZES), default="full")
    parser.add_argument("--work", type=Path, default=Path("runs/gpu-check"))
    parser.add_argument("--only", default="match,stream,train,map", help="comma-separated sections to run")
    args = parser.parse_args()
    size, sections = SIZES[args.size], set(args.only.split(","))
    shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True)
    rows: list[Row] = []
    if "match" in sections:
        rows += match_rows(args.device, size)
    if "stream" in sections:
        rows += stream_rows(args.device, size)
    if "train" in sections:
        rows += training_rows(args.device, size, args.work)
    if "map" in sections:
        rows.append(map_row(args.device, size, args.work))
    report = table(rows, args.device)
    print(report)
    (args.work / "results.md").write_text(report + "\n")
    sys.exit(0 if all(r.status == "ok" for r in rows) else 1)


if __name__ == "__main__":
    main()
