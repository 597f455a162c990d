"""The documentation pages' examples run as written: every shell and Python block of every page runs in the suite,
in the page's order, from a folder with the project's data beside it (as the repository root has), unless the line
above it says ``<!-- not run: why -->``; and no code block is left without its language (an untagged block could
hide a command from this test)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import fenced_blocks

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
PAGES = sorted((ROOT / "docs").rglob("*.md"))
RUN = ("bash", "python")
SNIPPET = re.compile(r'^--8<-- "([^"]+)"$', re.M)
ELSEWHERE = re.compile(r"the same commands as (\S+\.md)")  # a marker's reason: another page's test runs them


def commands(code: str) -> list[str]:
    """A block's commands, one per logical line: continuations joined, comments and blank lines dropped."""
    joined = re.sub(r"\\\n\s*", " ", code)
    return [" ".join(line.split("  #")[0].split()) for line in joined.splitlines()
            if line.strip() and not line.startswith("#")]


def page_text(page: Path) -> str:
    """A page as the site shows it: a snippet line (``--8<-- "BENCHMARKS.md"``) replaced by the file it names."""
    return SNIPPET.sub(lambda line: (ROOT / line.group(1)).read_text(), page.read_text())


def runnable(page: Path) -> list[tuple[str, str]]:
    return [(language, code) for language, code, why in fenced_blocks(page_text(page)) if language in RUN and not why]


def test_a_snippet_brings_in_its_files_blocks(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    (tmp_path / "included.md").write_text("```bash\necho hi\n```\n")
    page = tmp_path / "page.md"
    page.write_text('# A page\n\n--8<-- "included.md"\n')
    assert runnable(page) == [("bash", "echo hi\n")]


def test_a_block_said_to_run_on_another_page_runs_there():
    """A block marked not run because another page runs the same commands: each of its commands is one of that
    page's run commands, so the two cannot drift apart."""
    said = [(page, code, ELSEWHERE.search(why)) for page in [ROOT / "README.md", *PAGES]
            for _, code, why in fenced_blocks(page_text(page)) if why and ELSEWHERE.search(why)]
    assert said  # the README's examples are
    for page, code, where in said:
        there = {command for _, block in runnable(ROOT / where.group(1)) for command in commands(block)}
        missing = [command for command in commands(code) if command not in there]
        assert not missing, (str(page.relative_to(ROOT)), where.group(1), missing)


def test_every_block_says_its_language():
    untagged = [str(p.relative_to(ROOT)) for p in PAGES for language, _, _ in fenced_blocks(page_text(p))
                if not language]
    assert not untagged


@pytest.mark.slow
@pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data is absent")
@pytest.mark.parametrize("page", [p for p in PAGES if runnable(p)], ids=lambda p: str(p.relative_to(ROOT)))
def test_a_pages_examples_run_as_written(page, tmp_path):
    (tmp_path / "shared").symlink_to(ROOT.parent / "shared")
    work = tmp_path / "root"
    work.mkdir()
    env = {**os.environ, "SEQVPR_THREADS": "1", "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    for number, (language, code) in enumerate(runnable(page)):
        script = tmp_path / f"block-{number}.{'sh' if language == 'bash' else 'py'}"  # as a reader saves it
        script.write_text(("set -euo pipefail\n" if language == "bash" else "") + code)
        command = ["bash", str(script)] if language == "bash" else [sys.executable, str(script)]
        done = subprocess.run(command, cwd=work, env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, (code[:200], done.stderr[-2000:])
