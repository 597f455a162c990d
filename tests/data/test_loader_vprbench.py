"""VPR-Bench's object-array ground truth is read without unpickling: the rows numpy's own (unsafe) loader gives, in
every form such files hold, while a pickle naming anything else is one line and never runs."""

from __future__ import annotations

import numpy as np
import pytest

from seqvpr.data.loaders.ground_truth_files import load_ground_truth_file
from seqvpr.data.loaders.vprbench import read_object_rows
from tests.helpers import raises_one_line
from tests.test_arrays import Marker


def rows_file(path, refs) -> np.ndarray:
    """Rows ``[query, refs[query]]`` saved as VPR-Bench does (an object array, pickled by numpy)."""
    rows = np.empty((len(refs), 2), dtype=object)
    for query, ref in enumerate(refs):
        rows[query] = [np.int64(query) if query % 2 else query, ref]
    np.save(path, rows)
    return rows


@pytest.mark.parametrize("refs", [
    [[0, 1], [1], [], [2, 3, 4]],  # lists of Python ints
    [np.arange(2), np.array([1], np.int32), np.array([], np.int64), np.array([2, 3, 4], ">i8")],  # numpy arrays
    [[np.int64(0), 1], 1, [np.int32(7)], [2, 3]],  # numpy numbers, and a bare index
])
def test_rows_read_as_numpy_would_unpickle_them(tmp_path, refs):
    rows = rows_file(tmp_path / "gt.npy", refs)
    read = read_object_rows(tmp_path / "gt.npy")
    assert [q for q, _ in read] == [int(q) for q in rows[:, 0]]
    for (_, got), want in zip(read, rows[:, 1]):
        np.testing.assert_array_equal(got, np.atleast_1d(np.asarray(want, dtype=np.int64)))


def test_the_ground_truth_of_vprbench_rows(tmp_path):
    rows_file(tmp_path / "gt.npy", [[0, 1], [1], [], [2, 3]])
    gt = load_ground_truth_file(tmp_path / "gt.npy", 4, 4)
    assert sorted(zip(*(a.tolist() for a in gt.positives.nonzero()))) == [(0, 0), (0, 1), (1, 1), (3, 2), (3, 3)]


def test_a_pickle_naming_anything_else_is_one_line_and_never_runs(tmp_path):
    marker = tmp_path / "marker"
    rows_file(tmp_path / "gt.npy", [[0], [Marker(marker)]])
    message = raises_one_line("its pickle names 'io open', not part of a numpy array; seqvpr never unpickles a file",
                              load_ground_truth_file, tmp_path / "gt.npy", 2, 2)
    assert "save it as a dense boolean" in message and not marker.exists()


def test_other_object_arrays_are_one_line(tmp_path):
    np.save(tmp_path / "text.npy", np.array([["a", "b"]], dtype=object))
    raises_one_line("row 0 is not [query_index, [reference indices]]", read_object_rows, tmp_path / "text.npy")
    np.save(tmp_path / "wide.npy", np.zeros((2, 3), dtype=object))
    raises_one_line("expected VPR-Bench rows", read_object_rows, tmp_path / "wide.npy")
    (tmp_path / "cut.npy").write_bytes((tmp_path / "wide.npy").read_bytes()[:-5])
    raises_one_line("cut.npy", read_object_rows, tmp_path / "cut.npy")
