"""The README's examples run as written, from the repository root with the project's data beside it: its Python
blocks that use ``import seqvpr`` (the public face), and its shell blocks in order in one shell (the install lines
excepted: the suite runs in the environment they make). A block preceded by ``<!-- not run: why -->`` is skipped,
saying why."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import fenced_blocks

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
pytestmark = [pytest.mark.slow, pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data is absent")]


def test_the_readmes_python_examples_run_as_written():
    blocks = [(code, why) for _, code, why in fenced_blocks((ROOT / "README.md").read_text(), "python")
              if code.startswith("import seqvpr\n")]
    assert blocks
    for code, why in blocks:
        if why:
            continue
        done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env={**os.environ, "SEQVPR_THREADS": "1"},
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
        recall = eval(done.stdout.strip().splitlines()[-1])  # the printed Recall@K
        assert set(recall) == {1, 5, 10, 20} and 0.0 < recall[1] <= recall[20] <= 1.0


def test_the_readmes_shell_examples_run_as_written(tmp_path):
    """The example blocks (not the install and test commands) in one shell, in order, from a folder with the
    project's data beside it as the repository root has (``../shared`` linked), so what they write stays there."""
    blocks = [(code, why) for _, code, why in fenced_blocks((ROOT / "README.md").read_text(), "bash")
              if "pip install" not in code]
    run = [code for code, why in blocks if not why]
    assert len(run) == 1 and len(blocks) == 3  # match and view (map and localise: the tutorial's; the node: not run)
    (tmp_path / "shared").symlink_to(ROOT.parent / "shared")
    (tmp_path / "root").mkdir()
    env = {**os.environ, "SEQVPR_THREADS": "1", "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    done = subprocess.run(["bash", "-c", "set -euo pipefail\n" + "\n".join(run)], cwd=tmp_path / "root", env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, (done.stdout[-2000:], done.stderr[-2000:])
    assert "R@1" in done.stdout
    assert (tmp_path / "root" / "runs" / "nordland-L10" / "view" / "index.html").is_file()
