"""The documentation site cannot rot: ``mkdocs build --strict`` passes, the command-line reference (generated from
the click commands by mkdocs-click) lists every command and option ``seqvpr --help`` does, and the API reference
(generated from the docstrings by mkdocstrings) covers every public name."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import click
import pytest

ROOT = Path(__file__).resolve().parents[1]
pytest.importorskip("mkdocs", reason="mkdocs (the test extra) is not installed")
pytest.importorskip("mkdocs_click", reason="mkdocs-click (the test extra) is not installed")
pytest.importorskip("mkdocstrings", reason="mkdocstrings (the test extra) is not installed")


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    out = tmp_path_factory.mktemp("site")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-f", str(ROOT / "mkdocs.yml"),
                           "-d", str(out)], cwd=ROOT, capture_output=True, text=True,
                          env={"NO_MKDOCS_2_WARNING": "1", "PATH": "/usr/bin:/bin", "HOME": str(Path.home())})
    assert done.returncode == 0, done.stderr[-3000:]
    return out


def commands(group: click.Group, ctx: click.Context, path: str = "seqvpr"):
    """Every command under ``group`` with its path (``seqvpr map build``), depth first."""
    for name in group.list_commands(ctx):
        command = group.get_command(ctx, name)
        yield f"{path} {name}", command
        if isinstance(command, click.Group):
            yield from commands(command, click.Context(command, info_name=name, parent=ctx), f"{path} {name}")


def test_the_command_line_reference_lists_every_command_and_option(site):
    from seqvpr.cli import cli

    page = (site / "reference" / "cli.html").read_text()
    found = list(commands(cli, click.Context(cli, info_name="seqvpr")))
    assert len(found) > 20
    for path, command in found:
        anchor = "-".join(path.split())
        assert f'id="{anchor}"' in page, path
        section = page.split(f'id="{anchor}"', 1)[1]
        flags = [f for p in command.params if isinstance(p, click.Option) for f in p.opts if f.startswith("--")]
        missing = [f for f in flags if f not in section]
        assert not missing, f"{path}: {missing}"


def test_the_api_reference_covers_every_public_name(site):
    import seqvpr

    listed = set(re.findall(r"^::: [\w.]+\.(\w+)$", (ROOT / "docs" / "reference" / "api.md").read_text(), re.M))
    public = {name for name in seqvpr.__all__ if name != "__version__"}
    assert listed == public
    page = (site / "reference" / "api.html").read_text()
    for name in public:
        module = seqvpr.EXPORTS.get(name, "seqvpr.errors")
        assert f'id="{module}.{name}"' in page, name
