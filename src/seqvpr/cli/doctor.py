"""``seqvpr doctor``: what a bug report needs: versions, the torch devices seen, faiss's SIMD level, numba's
threading layer and thread counts, and the cache folders with their sizes (seqvpr's cache, ``seqvpr.cache``, and
the bag frames in it unless ``$SEQVPR_BAG_FRAMES`` puts them elsewhere)."""

from __future__ import annotations

import importlib.metadata
import json
import os
import platform
from pathlib import Path
from typing import Any

import click

PACKAGES = ("seqvpr", "torch", "numpy", "scipy", "faiss-cpu", "numba", "safetensors", "pillow", "rosbags", "click",
            "onnxruntime", "onnx", "cyclonedds")


@click.command("doctor")
@click.option("--cache-dir", type=click.Path(), help="A descriptor cache folder to report on (its size and entries).")
@click.option("--json", "as_json", is_flag=True, help="One JSON object instead of lines.")
def doctor(cache_dir: str | None, as_json: bool) -> None:
    """Print versions, devices, SIMD and threading, and cache sizes: paste it into a bug report."""
    report = environment_report(cache_dir)
    if as_json:
        click.echo(json.dumps(report, indent=2))
        return
    for section, values in report.items():
        click.echo(f"{section}:")
        for key, value in values.items():
            click.echo(f"  {key:<22} {value}")


def environment_report(cache_dir: str | None = None) -> dict[str, dict[str, Any]]:
    import faiss
    import numba
    import numpy as np
    import torch

    from seqvpr.sequences._fused import squared_norms
    from seqvpr.threads import ensure_policy

    squared_norms(np.ones((4, 2), np.float32))  # starts numba's pool, so its threading layer is known
    policy = ensure_policy()  # re-asserted after that launch, as every entry point does
    versions = {"python": platform.python_version(), "platform": platform.platform()}
    for name in PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = "not installed"
    devices = {"torch threads": torch.get_num_threads(), "cuda available": torch.cuda.is_available(),
               "cuda devices": ", ".join(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count()))
               or "none", "mps available": bool(getattr(torch.backends, "mps", None) and torch.backends.mps.is_available())}
    compute = {"thread policy": policy.describe(), "faiss SIMD": faiss.get_compile_options().strip() or "generic",
               "faiss threads": faiss.omp_get_max_threads(), "numba threading layer": numba.threading_layer(),
               "numba threads": numba.get_num_threads(), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "unset")}
    from seqvpr.cache import cache_folder, cache_root
    from seqvpr.data.loaders.rosbag import frames_root

    caches = {"cache": _folder_line(cache_root()), "bag frames": _folder_line(frames_root()),
              "ONNX encoders": _folder_line(cache_folder("encoders"))}
    if cache_dir:
        caches["descriptor cache"] = _folder_line(Path(cache_dir))
    return {"versions": versions, "devices": devices, "compute": compute, "caches": caches}


def _folder_line(folder: Path) -> str:
    """``folder (N files, X MiB)`` or that it does not exist."""
    if not folder.is_dir():
        return f"{folder} (none yet)"
    files = [p for p in folder.rglob("*") if p.is_file()]
    size = sum(p.stat().st_size for p in files) / 2**20
    return f"{folder} ({len(files)} files, {size:.1f} MiB)"
