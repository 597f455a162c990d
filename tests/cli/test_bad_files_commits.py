"""Outputs committed whole (issue 28): an --out that the swap would wrongly delete, or a set's name that is taken by
a folder, is one line on stderr naming it, exit status 2, before any output is written and with the user's files
kept."""

from __future__ import annotations

import shutil

import pytest

from tests.helpers import QuietCapsys, run_bad_case, run_cli, write_route_files


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A route, a map of it, a folder of a user's files, a previous match output holding its own input, and a
    folder where a dbstruct set's descriptors file would go."""
    w = tmp_path_factory.mktemp("commits")
    write_route_files(w, 60, 8, 1)
    (w / "mine").mkdir()
    (w / "mine" / "notes.txt").write_text("a user's own file")
    (w / "prev").mkdir()
    (w / "prev" / "run.json").write_text("{}")
    shutil.copy(w / "ref.npz", w / "prev" / "ref.npz")
    (w / "sets" / "route_query.npy").mkdir(parents=True)
    assert run_cli(pytest.MonkeyPatch(), QuietCapsys(), "map", "build", w / "ref.npz", "--out", w / "map")[0] == 0
    return w



M = ("match", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m")
L = ("localize", "--map", "{w}/map", "-q", "{w}/qry.npz", "--radius", "10m")
CASES = {
    "match: --out a folder of the user's files (they would be swapped away)": ((*M, "--out", "{w}/mine"), "holds other files"),
    "match: the reference inside --out (the swap would delete it)": (
        ("match", "-r", "{w}/prev/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m", "--out", "{w}/prev"), "holds the input"),
    "match: --cache-dir inside --out": ((*M, "--cache-dir", "{out}/cache", "--out", "{out}"), "holds the input"),
    "localize: --out a folder of the user's files": ((*L, "--out", "{w}/mine"), "holds other files"),
    "localize: --save-state inside --out (the swap would delete it)": ((*L, "--save-state", "{out}/s.npz", "--out", "{out}"),
                                                                       "holds the input"),
    "convert: a folder where the set's descriptors file goes": (
        ("convert", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m", "--to", "dbstruct", "--out",
         "{w}/sets/route.db"), "route_query.npy is a folder"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_output_is_one_line_exit_2_and_no_partial_output(world, tmp_path, monkeypatch, capsys, case):
    args, fragment = CASES[case]
    out = tmp_path / "out"
    before = {p: p.read_bytes() for p in world.rglob("*") if p.is_file() and "map" not in p.parts}
    run_bad_case(monkeypatch, capsys, args, fragment, world, out)
    after = {p: p.read_bytes() for p in world.rglob("*") if p.is_file() and "map" not in p.parts}
    assert after == before
    assert sorted(p.name for p in (world / "sets").iterdir()) == ["route_query.npy"]
