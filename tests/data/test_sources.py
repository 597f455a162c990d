"""Dataset descriptions (``dataset.toml``): a side given as descriptors + the seqNet/SeqMatchNet ``.db`` struct +
a seqBounds file reads as the same traversal as a ``.npz`` with those positions and segments; unknown keys are
errors naming them."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.io

from seqvpr.data.loaders.seq_bounds import load_seq_bounds, seq_bounds_rows
from seqvpr.data.sources import load_traversal, save_traversal_npz
from seqvpr.data.traversal import Traversal
from tests.helpers import raises_one_line, run_cli

N_DB, N_Q, DB_SEQUENCES, Q_SEQUENCES = 953, 835, 43, 27  # the published MSLS Amman test struct's sizes


def _cell(names):
    cell = np.empty((len(names), 1), dtype=object)
    cell[:, 0] = names
    return cell


def _sequences(n: int, count: int, rng) -> np.ndarray:
    """Segment ids of ``count`` consecutive sequences of uneven length over n frames."""
    cuts = np.sort(rng.choice(np.arange(1, n), size=count - 1, replace=False))
    return np.searchsorted(cuts, np.arange(n), side="right")


@pytest.fixture(scope="module")
def msls_like(tmp_path_factory):
    """The struct (exact MSLS field names and shapes), per-side descriptors and seqBounds, and the description."""
    folder = tmp_path_factory.mktemp("msls")
    rng = np.random.default_rng(0)
    track = np.cumsum(rng.normal(2.0, 0.3, size=N_DB))
    utm_db = np.vstack([500000.0 + track, 3500000.0 + 0.1 * track])
    picks = np.sort(rng.choice(N_DB, size=N_Q, replace=False))
    utm_q = utm_db[:, picks] + rng.normal(0, 1.0, size=(2, N_Q))
    scipy.io.savemat(folder / "amman_test.db", {"dbStruct": {
        "whichSet": "test", "dataset": "msls", "dbImageFns": _cell([f"database/{i}.jpg" for i in range(N_DB)]),
        "utmDb": utm_db, "qImageFns": _cell([f"query/{i}.jpg" for i in range(N_Q)]), "utmQ": utm_q,
        "numImages": N_DB, "numQueries": N_Q, "posDistThr": 10, "posDistSqThr": 100, "nonTrivPosDistSqThr": 100}})
    field = rng.normal(size=(N_DB, 16))
    sides = {"reference": (field + 0.3 * rng.normal(size=field.shape), _sequences(N_DB, DB_SEQUENCES, rng), utm_db),
             "query": (field[picks] + 0.6 * rng.normal(size=(N_Q, 16)), _sequences(N_Q, Q_SEQUENCES, rng), utm_q)}
    for role, (rows, segments, utm) in sides.items():
        np.save(folder / f"{role}.npy", rows.astype(np.float32))
        np.savetxt(folder / f"{role}_seqBounds.txt", seq_bounds_rows(segments), fmt="%d")
        save_traversal_npz(folder / f"{role}.npz", Traversal("x", np.arange(len(rows)), segments,
                                                             rows.astype(np.float32), positions=utm.T))
    (folder / "dataset.toml").write_text("".join(
        f'[{role}]\ndescriptors = "{role}.npy"\ndbstruct = "amman_test.db"\nseq_bounds = "{role}_seqBounds.txt"\n\n'
        for role in sides))
    return folder


def test_db_descriptors_and_seq_bounds_read_as_the_traversal_they_describe(msls_like):
    described = load_traversal(msls_like / "dataset.toml", "query")
    direct = load_traversal(msls_like / "query.npz", "query")
    np.testing.assert_array_equal(described.segment_ids, direct.segment_ids)
    np.testing.assert_allclose(described.positions, direct.positions)
    assert len(np.unique(described.segment_ids)) == Q_SEQUENCES
    assert len(np.unique(load_traversal(msls_like / "dataset.toml", "reference").segment_ids)) == DB_SEQUENCES


def test_the_description_gives_the_figures_of_the_traversal_files(msls_like, tmp_path, monkeypatch, capsys):
    toml = msls_like / "dataset.toml"
    code, out, err = run_cli(monkeypatch, capsys, "match", "-r", toml, "-q", toml, "-L", "5", "--json",
                             "--out", tmp_path / "a")
    assert code == 0, err
    by_description = json.loads(out)
    assert "10" in by_description["settings"]["ground_truth_rule"]  # posDistThr as the radius
    code, out, err = run_cli(monkeypatch, capsys, "match", "-r", msls_like / "reference.npz", "-q",
                             msls_like / "query.npz", "--radius", "10m", "-L", "5", "--json", "--out", tmp_path / "b")
    assert code == 0, err
    assert json.loads(out)["recall"] == by_description["recall"]
    assert by_description["queries_evaluated"] < N_Q - Q_SEQUENCES * 2  # windows stop at every sequence's ends


def test_unknown_description_keys_name_the_key(tmp_path):
    (tmp_path / "d.toml").write_text('[reference]\ndescriptors = "r.npy"\n[ground_truth]\nraduis = "25m"\n')
    raises_one_line("unknown key 'raduis' in [ground_truth]; did you mean radius?", load_traversal,
                    tmp_path / "d.toml", "reference")
    (tmp_path / "e.toml").write_text('[refrence]\ndescriptors = "r.npy"\n')
    raises_one_line("unknown table [refrence]", load_traversal, tmp_path / "e.toml", "reference")


def test_bad_seq_bounds_are_one_line(tmp_path):
    (tmp_path / "b.txt").write_text("0 2\n0 2\n3 4\n")
    raises_one_line("line 3: frame 2 is not inside its sequence [3, 4)", load_seq_bounds, tmp_path / "b.txt", 3)
    raises_one_line("expected 4 rows", load_seq_bounds, tmp_path / "b.txt", 4)
    np.testing.assert_array_equal(load_seq_bounds(_write(tmp_path, "0 2\n0 2\n2 3\n"), 3), [0, 0, 1])


def _write(folder, text):
    (folder / "ok.txt").write_text(text)
    return folder / "ok.txt"


@pytest.mark.parametrize("content", [b"", b"hello world\n" * 10, bytes(range(256)) * 2])
def test_a_file_that_is_no_mat_is_named_by_the_descriptor_loader(tmp_path, content):
    path = tmp_path / "x.mat"
    path.write_bytes(content)
    raises_one_line(str(path), load_traversal, str(path), "reference")


def test_an_archive_with_members_that_are_no_arrays_names_the_file(tmp_path):
    import zipfile

    path = tmp_path / "x.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("notes.txt", "not an array")
    raises_one_line(f"{path}: name the descriptor variable", load_traversal, str(path), "reference")


def test_an_archive_with_a_pickled_member_is_refused_not_passed_over(tmp_path):
    path = tmp_path / "x.npz"
    np.savez(path, descriptors=np.array([{"a": 1}], dtype=object))
    raises_one_line("descriptors", load_traversal, str(path), "reference")
