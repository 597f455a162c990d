"""The JIST GPU recipe (bench/bench_jist.py) runs on the CPU at a small size, so that on a lent GPU
(``--device cuda``: Gardens Point colour at the reference's 640x480, mixed precision) it runs in one call."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
@pytest.mark.realdata
def test_the_jist_recipe_trains_and_scores_gardens_point_at_a_small_size(shared_data, tmp_path):
    done = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "bench_jist.py"), "gardenspoint", "--data", str(shared_data),
         "--size", "64x48", "--epochs", "1", "--refreshes", "1", "--iterations", "1", "--device", "cpu",
         "--out", str(tmp_path / "run")], capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    report = (tmp_path / "run" / "results.md").read_text()
    assert "gardenspoint at 64x48 on cpu" in report
    rows = [line for line in report.splitlines() if line.startswith("| ") and "R@" not in line]
    assert [row.split("|")[1].strip().split(" (")[0] for row in rows] == [
        "single", "SeqGeM, untrained", "JIST frozen start", "JIST trained"]
