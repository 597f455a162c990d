"""Helpers shared by the benchmark scripts (run as ``python bench/<script>.py``, so this folder is on sys.path)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name, for the benchmark header."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def spin_load(n: int) -> list[subprocess.Popen]:
    """``n`` processes each keeping one core busy."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def run_beside_load(arguments: list[str], setting: str, load: int) -> dict:
    """A fresh Python process running ``arguments`` at thread ``setting`` (``default``: seqvpr's own choice, made at
    its start) beside ``load`` spinning processes, started a second before it; the JSON its last line prints."""
    env = {k: v for k, v in os.environ.items() if k not in ("SEQVPR_THREADS", "OMP_NUM_THREADS")}
    if setting != "default":
        env["SEQVPR_THREADS"] = setting
    spinners = spin_load(load)
    try:
        time.sleep(1.0 if load else 0.0)
        done = subprocess.run([sys.executable, *arguments], env=env, capture_output=True, text=True, timeout=1800)
    finally:
        for process in spinners:
            process.kill()
            process.wait()
    if done.returncode:
        raise SystemExit(f"{' '.join(arguments)} at {setting} failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def median_time(fn, repeats: int) -> float:
    """The median of ``repeats`` timed calls of ``fn`` (after one untimed call), in seconds."""
    import statistics
    import time

    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)
