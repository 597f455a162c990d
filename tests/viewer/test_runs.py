"""The viewer's reading of seqvpr's outputs: a match run's rows are its predictions in rows of its traversals, two
runs over one pair are compared, a run whose sources moved still gives a page (placeholders and a note), and what
is not a seqvpr output, or a match of no query, is one line."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from seqvpr.evaluation.predictions import read_predictions
from seqvpr.viewer import view_page
from seqvpr.viewer.runs import read_views
from tests.helpers import raises_one_line, run_cli, write_route_files


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A small route of descriptor files (ref.npz, qry.npz)."""
    root = tmp_path_factory.mktemp("runs")
    write_route_files(root, 60, 16, 3)
    return root


def cli(monkeypatch, capsys, *args):
    code, out, err = run_cli(monkeypatch, capsys, *map(str, args))
    assert code == 0, err
    return out


def test_two_match_runs_are_their_predictions_in_rows(runs, tmp_path, monkeypatch, capsys):
    for method, length in (("single", 1), ("matching", 5)):
        cli(monkeypatch, capsys, "match", "-r", runs / "ref.npz", "-q", runs / "qry.npz", "--method", method, "-L",
            length, "--radius", "2f", "--out", tmp_path / method)
    view = read_views([tmp_path / "single", tmp_path / "matching"])
    assert [m.name for m in view.methods] == ["single (single L=1)", "matching (matching L=5)"]
    for method, name in zip(view.methods, ("single", "matching")):
        found = read_predictions(tmp_path / name / "predictions.csv")
        np.testing.assert_array_equal(method.refs[found.query, : found.references.shape[1]], found.references)
    assert view.positives is not None and len(view.positives) == len(view.query.names)
    page = view_page([tmp_path / "single", tmp_path / "matching"], tmp_path / "page")
    data = json.loads(page.read_text().split('<script id="data" type="application/json">')[1].split("</script>")[0])
    assert data["kind"] == "match" and len(data["methods"]) == 2 and data["query"]["xy"] is not None


def test_a_run_whose_sources_moved_still_gives_a_page_with_a_note(runs, tmp_path, monkeypatch, capsys):
    shutil.copytree(runs, tmp_path / "data")
    cli(monkeypatch, capsys, "match", "-r", tmp_path / "data" / "ref.npz", "-q", tmp_path / "data" / "qry.npz",
        "--radius", "2f", "-L", "3", "--out", tmp_path / "run")
    shutil.rmtree(tmp_path / "data")
    view = read_views([tmp_path / "run"])
    assert any("cannot be read now" in note for note in view.notes) and view.positives is None
    assert (view_page([tmp_path / "run"], tmp_path / "page")).is_file()


def test_what_is_not_a_seqvpr_output_or_holds_no_query_is_one_line(runs, tmp_path, monkeypatch, capsys):
    raises_one_line("not a folder seqvpr wrote", read_views, [runs])
    cli(monkeypatch, capsys, "match", "-r", runs / "ref.npz", "-q", runs / "qry.npz", "--radius", "2f", "-L", "3",
        "--out", tmp_path / "run")
    (tmp_path / "run" / "predictions.csv").write_text("query,query_name,references,distances,correct\n")
    raises_one_line("no prediction rows", read_views, [tmp_path / "run"])
    other = tmp_path / "other"
    cli(monkeypatch, capsys, "match", "-r", runs / "qry.npz", "-q", runs / "ref.npz", "--radius", "2f", "-L", "3",
        "--out", other)
    raises_one_line("other traversals", read_views, [other, tmp_path / "run"])


def test_the_page_never_lands_on_a_run_but_may_go_in_its_own_view_folder(runs, tmp_path, monkeypatch, capsys):
    cli(monkeypatch, capsys, "match", "-r", runs / "ref.npz", "-q", runs / "qry.npz", "--radius", "2f", "-L", "3",
        "--out", tmp_path / "run")
    raises_one_line("write it elsewhere", view_page, [tmp_path / "run"], tmp_path / "run")
    raises_one_line("write it elsewhere", view_page, [tmp_path / "run"], tmp_path / "run" / "report")
    raises_one_line("write it elsewhere", view_page, [tmp_path / "run"], tmp_path)
    assert view_page([tmp_path / "run"], tmp_path / "run" / "view").is_file()



def test_a_run_whose_images_moved_opens_with_placeholders_and_a_note(tmp_path, monkeypatch, capsys):
    import json

    from PIL import Image

    rng = np.random.default_rng(0)
    for side in ("ref", "qry"):
        (tmp_path / side).mkdir()
        for i in range(8):
            Image.fromarray(rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)).save(tmp_path / side / f"{i:03d}.png")
    cli(monkeypatch, capsys, "match", "-r", tmp_path / "ref", "-q", tmp_path / "qry", "--radius", "1f", "-L", "3",
        "--out", tmp_path / "run")
    shutil.move(tmp_path / "ref", tmp_path / "elsewhere")
    page = view_page([tmp_path / "run"], tmp_path / "page")
    data = json.loads(page.read_text().split('<script id="data" type="application/json">')[1].split("</script>")[0])
    assert any("cannot be read now" in note for note in data["notes"])
    assert data["reference"]["thumbs"] == [] and all(data["query"]["thumbs"])  # placeholders; the query's still shown
