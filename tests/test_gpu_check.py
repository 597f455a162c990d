"""The prepared GPU check (bench/gpu_check.py) runs at a tiny size on the CPU, so that on a lent GPU it runs in one
call: every row ok, every method and online method checked."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from seqvpr.methods import METHODS

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_gpu_check_runs_every_row_on_the_cpu_at_a_tiny_size(tmp_path):
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "gpu_check.py"), "--device", "cpu", "--size", "tiny",
                           "--work", str(tmp_path / "work")], capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    rows = [line.split("|")[1:3] for line in done.stdout.splitlines() if line.startswith("| ") and "---" not in line]
    checks = {check.strip(): status.strip() for check, status in rows[1:]}
    assert set(checks.values()) == {"ok"}
    assert {f"match {m}" for m in METHODS if m != "jist"} <= set(checks)
    assert {"stream matching", "stream hmm", "train seqmatchnet", "train seqnet", "train jist",
            "ddp seqmatchnet"} <= set(checks)
    assert any(check.startswith("map ") for check in checks)
