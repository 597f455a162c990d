"""Progress from Python: the entry points report long work on the ``seqvpr`` logger (the mechanism the CLI's lines
use), silent until logging is turned on."""

from __future__ import annotations

import logging
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from seqvpr.maps import build_map
from seqvpr.progress import line_progress


def image_folder(folder, n: int):
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        Image.fromarray(rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)).save(folder / f"{i:03d}.png")
    return folder


def test_build_map_reports_its_progress_on_the_seqvpr_logger(tmp_path, caplog, monkeypatch):
    monkeypatch.setattr(logging.getLogger("seqvpr"), "propagate", True)  # the CLI's tests route it to stderr
    caplog.set_level(logging.INFO, logger="seqvpr")
    build_map([str(image_folder(tmp_path / "images", 6))], tmp_path / "map")
    lines = [r.getMessage() for r in caplog.records if r.name == "seqvpr"]
    assert any(line.startswith("describe") and "6/6 frames (100 %)" in line for line in lines), lines


@pytest.mark.slow
def test_the_library_says_nothing_until_logging_is_on_and_then_the_cli_lines(tmp_path):
    folder = image_folder(tmp_path / "images", 4)
    code = """
import logging, sys
from seqvpr.maps import build_map
if sys.argv[1] == "on":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
build_map([sys.argv[2]], sys.argv[3])
"""
    quiet = subprocess.run([sys.executable, "-c", code, "off", str(folder), str(tmp_path / "a")], capture_output=True,
                           text=True, timeout=300)
    loud = subprocess.run([sys.executable, "-c", code, "on", str(folder), str(tmp_path / "b")], capture_output=True,
                          text=True, timeout=300)
    assert quiet.returncode == loud.returncode == 0, quiet.stderr + loud.stderr
    assert quiet.stdout == quiet.stderr == ""
    expected = []
    line_progress(4, f"describe {folder.name}", echo=expected.append)(4)
    assert expected[0] in loud.stderr.splitlines()
