"""``seqvpr convert``: a traversal pair written as the upstream code's .db + descriptors + seqBounds (+ the
dataset.toml tying them) reads back equal, and matches to the same figures; npz round trips."""

from __future__ import annotations

import json

import numpy as np

from seqvpr.data.sources import load_traversal, save_traversal_npz
from seqvpr.data.traversal import Traversal
from tests.helpers import run_cli, write_route_files


def test_dbstruct_set_reads_back_equal_and_matches_the_same(tmp_path, monkeypatch, capsys):
    write_route_files(tmp_path, 90, 16, 3)
    for name in ("ref", "qry"):  # give each side three segments, as seqBounds must carry them
        t = load_traversal(tmp_path / f"{name}.npz", "reference")
        save_traversal_npz(tmp_path / f"{name}.npz", Traversal(t.name, t.frame_index, np.arange(90) // 30,
                                                                t.descriptors, positions=t.positions))
    code, out, err = run_cli(monkeypatch, capsys, "convert", "-r", tmp_path / "ref.npz", "-q", tmp_path / "qry.npz",
                             "--radius", "10m", "--to", "dbstruct", "--out", tmp_path / "db" / "route.db")
    assert code == 0, err
    description = tmp_path / "db" / "route.toml"
    for role, name in (("reference", "ref"), ("query", "qry")):
        back, original = load_traversal(description, role), load_traversal(tmp_path / f"{name}.npz", role)
        np.testing.assert_array_equal(back.descriptors, original.descriptors)
        np.testing.assert_allclose(back.positions, original.positions)
        np.testing.assert_array_equal(back.segment_ids, original.segment_ids)
    figures = []
    for args in (("-r", description, "-q", description), ("-r", tmp_path / "ref.npz", "-q", tmp_path / "qry.npz",
                                                          "--radius", "10m")):
        code, out, err = run_cli(monkeypatch, capsys, "match", *args, "-L", "5", "--json", "--out", tmp_path / "o")
        assert code == 0, err
        figures.append(json.loads(out)["recall"])
    assert figures[0] == figures[1]


def test_npz_round_trip_and_bad_requests(tmp_path, monkeypatch, capsys):
    write_route_files(tmp_path, 40, 8, 1)
    code, _, err = run_cli(monkeypatch, capsys, "convert", "-r", tmp_path / "qry.npz", "--to", "npz", "--out",
                           tmp_path / "copy.npz")
    assert code == 0, err
    np.testing.assert_array_equal(load_traversal(tmp_path / "copy.npz", "query").descriptors,
                                  load_traversal(tmp_path / "qry.npz", "query").descriptors)
    code, _, err = run_cli(monkeypatch, capsys, "convert", "-r", tmp_path / "ref.npz", "--to", "dbstruct", "--out",
                           tmp_path / "x.db")
    assert code == 2 and "needs a --query and a --radius" in err and not (tmp_path / "x.db").exists()
    code, _, err = run_cli(monkeypatch, capsys, "convert", "-r", tmp_path / "ref.npz", "-q", tmp_path / "qry.npz",
                           "--radius", "2f", "--to", "dbstruct", "--out", tmp_path / "y.db")
    assert code == 2 and "use metres" in err
