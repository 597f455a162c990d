"""``--help`` a user can read: options under titled sections (``seqvpr.cli.help``), method-specific options naming
their methods, and ``seqvpr --help`` loading no heavy library."""

from __future__ import annotations

import ast
import re
import resource
import subprocess
import sys

import click
import pytest
from click.testing import CliRunner

from seqvpr.cli.help import OTHER, SectionedCommand, option, section
from seqvpr.cli.options import with_options
from seqvpr.methods import METHODS
from tests.helpers import run_cli

MATCH_SECTIONS = ["Input", "Sequences", "Method", "Map", "Ground truth and scoring", "Descriptors", "Output",
                  "Compute", OTHER]
#: option -> the methods it applies to, which its help line starts with
METHOD_OPTIONS = {
    "--steps": ("adaptive", "casevpr", "graph"),
    "--contrast-window": ("seqslam", "seqslam-hybrid"),
}


def help_sections(text: str) -> dict[str, list[str]]:
    """Section title -> the option names of its rows (``-r``, ``--reference``), in the order shown."""
    found: dict[str, list[str]] = {}
    title = None
    for line in text.splitlines():
        if line and not line[0].isspace() and line.endswith(":"):
            title = line[:-1]
            found[title] = []
        elif title is not None and re.match(r"  -", line):
            names = re.split(r"\s{2,}", line.strip())[0]
            found[title] += re.findall(r"(?<![\w-])--?\w[\w-]*", names)
    return found


def command_help(monkeypatch, capsys, *command: str) -> str:
    code, out, err = run_cli(monkeypatch, capsys, *command, "--help")
    assert code == 0, err
    return out


def option_names(*command: str) -> list[str]:
    """Every option name ``seqvpr COMMAND --help`` should list: those of each parameter with a help record."""
    from seqvpr.cli import cli

    ctx = click.Context(cli)
    found: click.Command = cli
    for name in command:
        found = found.get_command(ctx, name)  # type: ignore[attr-defined]
        ctx = click.Context(found, parent=ctx)
    return [name for param in found.get_params(ctx) if param.get_help_record(ctx) is not None
            for name in (*param.opts, *param.secondary_opts)]


def test_match_help_shows_the_sections_in_order(monkeypatch, capsys):
    shown = help_sections(command_help(monkeypatch, capsys, "match"))
    assert list(shown) == MATCH_SECTIONS
    assert shown[OTHER] == ["-h", "--help"]  # every option of seqvpr's own is in a titled section
    assert {"--method", "--model", "--steps", "--contrast-window", "--index", "--rerank"} <= set(shown["Method"])
    assert shown["Method"][0] == "--method"
    assert {"--descriptor", "--image-size", "--skip-bad", "--pca-dim"} <= set(shown["Descriptors"])
    assert {"--shortlist", "--shortlist-history", "--nprobe"} == set(shown["Map"])
    assert {"--threads", "--device", "--memory-budget"} <= set(shown["Compute"])
    assert {"--reference", "--query", "--map", "--topic"} <= set(shown["Input"])


@pytest.mark.parametrize("command", [("match",), ("localize",), ("map", "build")])
def test_every_option_is_listed_exactly_once(monkeypatch, capsys, command):
    shown = help_sections(command_help(monkeypatch, capsys, *command))
    listed = [name for names in shown.values() for name in names]
    expected = option_names(*command)
    assert len(expected) > 25
    assert sorted(listed) == sorted(expected)
    assert len(listed) == len(set(listed))


def test_each_method_specific_option_names_its_methods():
    from seqvpr.cli.match import match

    helps = {p.opts[-1]: p.help for p in match.params if isinstance(p, click.Option)}
    for name, methods in METHOD_OPTIONS.items():
        assert helps[name].startswith(", ".join(methods) + ": "), name
    for name in ("--index", "--rerank"):  # the methods that search sequence descriptors, alone or as a shortlist
        named = helps[name].split(": ")[0].split(", ")
        assert {"smoothing", "seqgem-signed", "seqnet", "jist", "hvpr", "casevpr"} <= set(named)
        assert all(METHODS[m].family in ("retrieval", "hierarchical") for m in named), name
    assert all(m in METHODS for methods in METHOD_OPTIONS.values() for m in methods)


def test_method_help_is_short_and_the_methods_are_one_row_each(monkeypatch, capsys):
    text = command_help(monkeypatch, capsys, "match")
    method_part = text[text.index("\nMethod:\n"):text.index("\nMap:\n")]
    rows = re.findall(r"^    (\S+)  +(\S.*)$", method_part, flags=re.MULTILINE)
    assert [name for name, _ in rows] == list(METHODS)
    assert all(METHODS[name].summary.startswith(line.split()[0]) for name, line in rows)
    from seqvpr.cli.match import match

    method_option = next(p for p in match.params if p.name == "method")
    assert len(method_option.help) < 100 and method_option.metavar == "METHOD"


def test_a_sectioned_command_groups_without_reordering_the_parse():
    @click.command(cls=SectionedCommand, sections=("Beta", "Alpha"))
    @option("Alpha", "--alpha", help="first")
    @click.option("--plain", help="untagged")
    @option("Beta", "--beta", help="third")
    @section("Alpha", with_options([click.option("--gamma", help="g"), option("Beta", "--delta", help="d")]))
    def toy(**values):
        click.echo(sorted(values.items()))

    assert [p.name for p in toy.params] == ["alpha", "plain", "beta", "gamma", "delta"]  # click parses as declared
    result = CliRunner().invoke(toy, ["--help"], terminal_width=80)
    shown = help_sections(result.output)
    assert shown == {"Beta": ["--beta", "--delta"], "Alpha": ["--alpha", "--gamma"], OTHER: ["--plain", "--help"]}
    columns = {line.index(word) for line in result.output.splitlines() for word in ("first", "untagged", "third")
               if word in line}
    assert len(columns) == 1  # one column width for every section
    assert CliRunner().invoke(toy, ["--delta", "4", "--alpha", "1"]).output.startswith("[('alpha', '1'), ")


def loading(args: list[str]) -> tuple[list[str], float]:
    """The heavy libraries ``seqvpr ARGS`` loads in a fresh interpreter, and the CPU seconds it took."""
    code = ("import sys\nfrom seqvpr.cli import main\nsys.argv = ['seqvpr', *%r]\ntry:\n    main()\nexcept "
            "SystemExit:\n    pass\nprint(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'faiss', "
            "'numba'}))" % (args,))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert done.returncode == 0, done.stderr
    seconds = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return ast.literal_eval(done.stdout.splitlines()[-1]), seconds


@pytest.mark.parametrize("args", [["--help"], ["match", "--help"]])
def test_help_loads_no_torch_faiss_or_numba_and_is_quick(args):
    runs = [loading(args) for _ in range(3)]
    assert all(loaded == [] for loaded, _ in runs)
    if args == ["--help"]:
        assert min(seconds for _, seconds in runs) < 0.5  # of CPU: the best of three, on a busy machine
