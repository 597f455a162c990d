"""dbStruct files: fields read by name (gps not swapped), Nordland frame indices, time-gap segments, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io

from seqvpr.data.loaders.dbstruct import load_dbstruct, time_gap_segments
from tests.helpers import raises_one_line


def _cell(names: list[str]) -> np.ndarray:
    """A MATLAB cell [N, 1] of strings, as savemat writes an object array."""
    cell = np.empty((len(names), 1), dtype=object)
    cell[:, 0] = names
    return cell


def _struct(n_db: int = 4, n_q: int = 3, **overrides) -> dict:
    """A Pittsburgh/seqNet style dbStruct with distinct reference and query values."""
    fields = {
        "whichSet": "test",
        "dataset": "oxford",
        "dbImageFns": _cell([f"db/{i:03d}.jpg" for i in range(n_db)]),
        "utmDb": np.vstack([500000.0 + np.arange(n_db), 4000000.0 + np.zeros(n_db)]),
        "qImageFns": _cell([f"q/{i:03d}.jpg" for i in range(n_q)]),
        "utmQ": np.vstack([600000.0 + np.arange(n_q), 5000000.0 + np.zeros(n_q)]),
        "numImages": n_db,
        "numQueries": n_q,
        "posDistThr": 25.0,
        "posDistSqThr": 625.0,
        "nonTrivPosDistSqThr": 100.0,
    }
    for key, value in overrides.items():
        if value is None:
            fields.pop(key, None)
        else:
            fields[key] = value
    return fields


def _save(path: Path, fields: dict, variable: str = "dbStruct") -> Path:
    """Write a MATLAB v5 file (also for a .db extension)."""
    with open(path, "wb") as handle:
        scipy.io.savemat(handle, {variable: fields})
    return path



def test_savemat_round_trips_named_fields(tmp_path):
    path = _save(tmp_path / "s.mat", _struct())
    loaded = scipy.io.loadmat(path)["dbStruct"]
    assert set(loaded.dtype.names) == set(_struct())


def test_reads_pittsburgh_style_struct_by_name(tmp_path):
    fields = _struct()
    path = _save(tmp_path / "oxford_test_d-25_d2-10.db", fields)
    db = load_dbstruct(path)
    assert db.which_set == "test" and db.dataset == "oxford"
    assert db.pos_dist_thr == 25.0 and db.non_triv_pos_dist == 10.0
    assert not db.frame_aligned
    np.testing.assert_allclose(db.reference.positions, fields["utmDb"].T)
    np.testing.assert_allclose(db.query.positions, fields["utmQ"].T)
    assert db.reference.positions.dtype == np.float64 and db.reference.positions.shape == (4, 2)
    assert db.reference.frame_index.dtype == np.int64 and list(db.query.frame_index) == [0, 1, 2]
    assert db.reference.image_paths[1] == tmp_path.absolute() / "db/001.jpg"
    assert db.query.image_paths[2] == tmp_path.absolute() / "q/002.jpg"
    assert db.reference.n_segments == 1 and db.reference.timestamps is None
    assert db.gps_reference is None and db.gps_query is None
    assert db.reference.descriptors is None
    assert db.reference.source == str(path)


def test_alternative_field_names_and_image_root(tmp_path):
    fields = _struct(
        dbImageFns=None, qImageFns=None, numImages=None, numQueries=None, dataset=None,
        dbImage=_cell(["a.jpg", "b.jpg", "c.jpg", "d.jpg"]), qImage=np.array(["x.jpg", "yy.jpg", "z.jpg"]),
        numDb=4, numQ=3,
    )
    path = _save(tmp_path / "pitts30k_test.mat", fields)
    db = load_dbstruct(path, image_root=tmp_path / "images")
    assert db.dataset == "pitts30k_test"  # defaults to the file name
    assert db.reference.frame_names() == ["a.jpg", "b.jpg", "c.jpg", "d.jpg"]
    assert db.query.frame_names() == ["x.jpg", "yy.jpg", "z.jpg"]  # char-matrix padding is stripped
    assert db.query.image_paths[0] == (tmp_path / "images").absolute() / "x.jpg"


def test_gps_fields_are_not_swapped(tmp_path):
    gps_db = np.vstack([np.full(4, 51.75), np.full(4, -1.25)])
    gps_q = np.vstack([np.full(3, -27.47), np.full(3, 153.02)])
    db = load_dbstruct(_save(tmp_path / "s.db", _struct(gpsDb=gps_db, gpsQ=gps_q)))
    np.testing.assert_allclose(db.gps_reference, gps_db.T)
    np.testing.assert_allclose(db.gps_query, gps_q.T)


def test_nordland_one_row_utm_is_a_frame_index(tmp_path):
    fields = _struct(utmDb=np.arange(15100, 15104)[None, :], utmQ=np.arange(15100, 15103)[None, :])
    fields["posDistThr"] = 1.0
    fields["nonTrivPosDistSqThr"] = 1.0
    db = load_dbstruct(_save(tmp_path / "nordland_test_d-1_d2-1.db", fields))
    assert db.frame_aligned
    assert db.reference.positions is None and db.query.positions is None
    assert db.reference.frame_index.dtype == np.int64
    assert list(db.reference.frame_index) == [15100, 15101, 15102, 15103]
    assert list(db.query.frame_index) == [15100, 15101, 15102]
    assert db.pos_dist_thr == 1.0 and db.non_triv_pos_dist == 1.0


def test_timestamps_split_segments_at_large_gaps(tmp_path):
    stamps_db = np.array([[0.0, 1.0, 2.0, 3.0]])
    stamps_q = np.array([10.0, 11.0, 100.0])  # median step 45.5: no step is 10x larger
    db = load_dbstruct(_save(tmp_path / "s.db", _struct(dbTimeStamp=stamps_db, qTimeStamp=stamps_q)))
    np.testing.assert_allclose(db.reference.timestamps, [0, 1, 2, 3])
    assert db.reference.timestamps.dtype == np.float64
    assert db.reference.n_segments == 1 and db.query.n_segments == 1
    assert list(time_gap_segments(np.array([0.0, 1, 2, 3, 40, 41, 42]))) == [0, 0, 0, 0, 1, 1, 1]
    assert list(time_gap_segments(np.array([5.0, 6, 7, 1, 2]))) == [0, 0, 0, 1, 1]  # time runs backwards
    assert list(time_gap_segments(np.array([3.0]))) == [0]
    gapped = _struct(dbTimeStamp=np.array([[0.0, 1.0, 2.0, 50.0]]))
    assert list(load_dbstruct(_save(tmp_path / "g.db", gapped)).reference.segment_ids) == [0, 0, 0, 1]


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"whichSet": None}, "no field 'whichSet'"),
        ({"dbImageFns": None}, "'dbImageFns' or 'dbImage'"),
        ({"utmQ": None}, "no field 'utmQ'"),
        ({"posDistThr": None}, "no field 'posDistThr'"),
        ({"nonTrivPosDistSqThr": None}, "no field 'nonTrivPosDistSqThr'"),
        ({"numImages": 5}, "'numImages' is 5 but 'dbImageFns' has 4 images"),
        ({"numQueries": 2}, "'numQueries' is 2 but 'qImageFns' has 3 images"),
        ({"utmDb": np.zeros((2, 5))}, "'utmDb' has 5 columns but 'dbImageFns' has 4"),
        ({"utmDb": np.zeros((3, 4))}, "field 'utmDb' must be a numeric [2, N]"),
        ({"utmDb": np.arange(4.0)[None, :]}, "'utmDb' has 1 row(s) but 'utmQ' has 2"),
        ({"qTimeStamp": np.arange(5.0)}, "'qTimeStamp' must hold 3 numbers"),
        ({"gpsDb": np.zeros((2, 3))}, "'gpsDb' must be [2, 4]"),
        ({"posDistThr": "far"}, "'posDistThr' must be one finite number"),
    ],
)
def test_field_errors_are_one_line_and_name_file_and_field(tmp_path, overrides, match):
    path = _save(tmp_path / "broken_struct.db", _struct(**overrides))
    message = raises_one_line(match, load_dbstruct, path)
    assert "broken_struct.db" in message


def test_file_level_errors(tmp_path):
    raises_one_line("absent.db", load_dbstruct, tmp_path / "absent.db")
    text = tmp_path / "notes.db"
    text.write_text("this is not a MATLAB file at all\n" * 10)
    raises_one_line("notes.db: not a", load_dbstruct, text)
    empty = tmp_path / "empty.mat"
    empty.write_bytes(b"")
    raises_one_line("empty.mat: not a", load_dbstruct, empty)
    other = _save(tmp_path / "other.mat", _struct(), variable="something")
    raises_one_line("other.mat: no variable 'dbStruct' (variables: something)", load_dbstruct, other)
    array = tmp_path / "array.mat"
    scipy.io.savemat(array, {"dbStruct": np.zeros((2, 2))})
    raises_one_line("array.mat: variable 'dbStruct' is not a single struct", load_dbstruct, array)


def test_matlab_v73_hdf5_is_refused_with_advice(tmp_path):
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    header = header.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02IM"
    path = tmp_path / "v73.db"
    path.write_bytes(header + b"\x00" * 384 + b"\x89HDF\r\n\x1a\n" + b"\x00" * 64)
    message = raises_one_line("v73.db: MATLAB v7.3 (HDF5)", load_dbstruct, path)
    assert "-v7" in message
    no_magic = tmp_path / "v73_header_only.mat"
    no_magic.write_bytes(header + b"\x00" * 64)
    raises_one_line("v73_header_only.mat: MATLAB v7.3", load_dbstruct, no_magic)
