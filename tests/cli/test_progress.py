"""Progress when stderr is not a terminal (a log, CI, nohup): a line at least every 10 s and one at the end."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from seqvpr.cli.progress import line_progress


def test_a_line_every_ten_seconds_and_at_the_end():
    now, lines = [0.0], []
    update = line_progress(100, "describe", clock=lambda: now[0], echo=lines.append)
    for step in range(100):
        now[0] = step * 0.5  # 2 frames a second: a line every 20 frames
        update(1)
    assert lines[0] == "describe: 21/100 frames (21 %)" and lines[-1] == "describe: 100/100 frames (100 %)"
    assert len(lines) == 5  # at 10, 20, 30, 40 s and the end
    update(1)
    assert len(lines) == 5  # nothing more after the end


@pytest.mark.slow
def test_a_redirected_command_prints_progress_lines(tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    for i in range(3):
        Image.fromarray(np.full((32, 64, 3), 40 * i, np.uint8)).save(folder / f"{i}.png")
    command = [sys.executable, "-c", "from seqvpr.cli import main; main()", "extract", str(folder), "--out",
               str(tmp_path / "d.npz")]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "3/3 frames (100 %)" in done.stderr
