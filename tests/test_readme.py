"""The README's Python examples run as written (from the repository root, with the project's data beside it)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "gardenspoint_delf_hdc"


def python_blocks(text: str) -> list[str]:
    """The README's fenced ``python`` blocks that use ``import seqvpr`` (the public face)."""
    return [b for b in re.findall(r"```python\n(.*?)```", text, re.S) if b.startswith("import seqvpr\n")]


@pytest.mark.slow
@pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data is absent")
@pytest.mark.parametrize("number", range(2))
def test_the_readmes_public_face_examples_run_as_written(number):
    blocks = python_blocks((ROOT / "README.md").read_text())
    assert len(blocks) == 2
    env = {**os.environ, "SEQVPR_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", blocks[number]], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    recall = eval(done.stdout.strip().splitlines()[-1])  # the printed Recall@K
    assert set(recall) == {1, 5, 10, 20} and 0.0 < recall[1] <= recall[20] <= 1.0
