"""The README's examples are the documentation's: each shell or Python example (the install lines excepted: the
suite runs in the environment they make) is marked as "the same commands as" a documentation page, which
``tests/test_docs_blocks.py`` holds it to, command for command, and whose test runs them; an example nothing here
can run (the node, which needs a robot's DDS network) says why."""

from __future__ import annotations

from pathlib import Path

from tests.helpers import fenced_blocks
from tests.test_docs_blocks import ELSEWHERE

ROOT = Path(__file__).resolve().parents[1]


def examples() -> list[tuple[str, str, str | None]]:
    """The README's shell and Python examples: (language, code, why it is not run here)."""
    return [(language, code, why) for language, code, why in fenced_blocks((ROOT / "README.md").read_text())
            if language in ("bash", "python") and "pip install" not in code]


def test_every_readme_example_is_run_by_a_documentation_page_or_says_why_not():
    reasons = [why for _, _, why in examples()]
    assert len(reasons) == 4  # match and view; map and localise; the node; the same from Python
    assert all(why and why.strip() for why in reasons)
    elsewhere = [ELSEWHERE.search(why) for why in reasons]
    assert sum(found is not None for found in elsewhere) == 3
    assert all((ROOT / found.group(1)).is_file() for found in elsewhere if found)
