"""UTM-named folders: positions/headings/timestamps from names, role selection, per-folder segments, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from seqvpr.data.loaders.utm_names import is_utm_named_folder, load_utm_named_folder
from tests.helpers import raises_one_line


def utm_name(east: float, north: float, heading: str = "", timestamp: str = "", note: str = "") -> str:
    """A full 14-field VPR-datasets-downloader name."""
    fields = [f"{east}", f"{north}", "32", "T", "45.0", "9.0", "pano_x-y", "00", heading, "0", "0", "", timestamp, note]
    return "@" + "@".join(fields) + "@.jpg"


def _image(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (4, 3)).save(path, format="JPEG")
    return path



def test_flat_folder_positions_headings_timestamps_ordered_by_time(tmp_path):
    folder = tmp_path / "queries_flat"
    _image(folder / utm_name(500002.5, 4000000, heading="180", timestamp="20"))
    _image(folder / utm_name(500000, 4000001, heading="90", timestamp="3"))
    _image(folder / utm_name(500001, 4000000.5, heading="270", timestamp="10"))
    trav = load_utm_named_folder(folder)
    assert trav.name == "queries_flat" and trav.source == str(folder)
    np.testing.assert_allclose(trav.timestamps, [3, 10, 20])
    np.testing.assert_allclose(trav.positions, [[500000, 4000001], [500001, 4000000.5], [500002.5, 4000000]])
    np.testing.assert_allclose(trav.headings, [90, 270, 180])
    assert trav.positions.dtype == np.float64 and trav.frame_index.dtype == np.int64
    assert list(trav.frame_index) == [0, 1, 2]
    assert trav.n_segments == 1
    assert all(p.is_absolute() and p.is_file() for p in trav.image_paths)


def test_minimal_names_sort_naturally_without_headings_or_timestamps(tmp_path):
    folder = tmp_path / "db"
    for east in (10, 9, 100):
        _image(folder / f"@{east}@5@.jpg")
    _image(folder / "@11@5.jpg")  # no trailing '@' is accepted too
    trav = load_utm_named_folder(folder)
    assert list(trav.positions[:, 0]) == [9, 10, 11, 100]
    assert trav.headings is None and trav.timestamps is None


def test_dataset_root_needs_a_role_and_selects_database_or_queries(tmp_path):
    root = tmp_path / "pitts30k_test"
    _image(root / "database" / utm_name(1, 1))
    _image(root / "database" / utm_name(2, 2))
    _image(root / "queries" / utm_name(3, 3))
    ref = load_utm_named_folder(root, role="reference")
    query = load_utm_named_folder(root, role="query", name="q")
    assert len(ref) == 2 and ref.name == "pitts30k_test-database"
    assert ref.source == str(root / "database")
    assert len(query) == 1 and query.name == "q"
    np.testing.assert_allclose(query.positions, [[3, 3]])
    raises_one_line("role='reference' or 'query'", load_utm_named_folder, root)
    raises_one_line("'db'", load_utm_named_folder, root, role="db")
    assert is_utm_named_folder(root)
    assert is_utm_named_folder(root / "queries")


def test_each_subfolder_is_a_segment_ordered_by_folder_then_time(tmp_path):
    folder = tmp_path / "seqs"
    _image(folder / "seq10" / utm_name(0, 0, timestamp="2"))
    _image(folder / "seq10" / utm_name(1, 0, timestamp="1"))
    _image(folder / "seq2" / utm_name(5, 0, timestamp="7"))
    _image(folder / "seq2" / utm_name(6, 0, timestamp="5"))
    _image(folder / "seq2" / utm_name(7, 0, timestamp="6"))
    trav = load_utm_named_folder(folder)
    assert [p.parent.name for p in trav.image_paths] == ["seq2"] * 3 + ["seq10"] * 2
    np.testing.assert_allclose(trav.timestamps, [5, 6, 7, 1, 2])
    assert list(trav.segment_ids) == [0, 0, 0, 1, 1]
    assert trav.segment_ids.dtype == np.int64


def test_distance_gap_splits_inside_a_folder(tmp_path):
    folder = tmp_path / "drive"
    for i, east in enumerate([0, 1, 2, 40, 41]):
        _image(folder / utm_name(east, 0, timestamp=str(i)))
    assert load_utm_named_folder(folder).n_segments == 1
    assert list(load_utm_named_folder(folder, max_distance_gap=10).segment_ids) == [0, 0, 0, 1, 1]


def test_partial_timestamps_fall_back_to_name_order(tmp_path):
    folder = tmp_path / "drive"
    _image(folder / utm_name(2, 0, timestamp="1"))
    _image(folder / utm_name(1, 0, timestamp="x"))
    trav = load_utm_named_folder(folder)
    assert list(trav.positions[:, 0]) == [1, 2] and trav.timestamps is None


def test_is_utm_named_folder(tmp_path):
    plain = tmp_path / "plain"
    _image(plain / "frame_0001.jpg")
    assert not is_utm_named_folder(plain)
    assert not is_utm_named_folder(tmp_path / "missing")
    bad = tmp_path / "bad"
    _image(bad / "@abc@def@.jpg")
    assert not is_utm_named_folder(bad)
    nested = tmp_path / "nested"
    _image(nested / "seq0" / "@1.5@2@.jpg")
    assert is_utm_named_folder(nested)


def test_errors_name_the_file_or_folder(tmp_path):
    bad = tmp_path / "bad"
    _image(bad / utm_name(1, 2))
    _image(bad / "@east@2@.jpg")
    raises_one_line("@east@2@.jpg", load_utm_named_folder, bad)
    plain = tmp_path / "plain"
    _image(plain / "frame_0001.jpg")
    raises_one_line("frame_0001.jpg", load_utm_named_folder, plain)
    empty = tmp_path / "empty"
    (empty / "sub").mkdir(parents=True)
    raises_one_line("empty", load_utm_named_folder, empty)
    raises_one_line("missing", load_utm_named_folder, tmp_path / "missing")


def test_jist_sequence_layout_orders_by_frame_number_and_breaks_on_jumps(tmp_path):
    from PIL import Image

    from seqvpr.data.loaders.utm_names import load_utm_named_folder

    folder = tmp_path / "seq_a"
    folder.mkdir()
    # easting decreases while frame numbers increase: name order would be wrong
    for east, frame in ((300, 1), (200, 2), (100, 3), (50, 7), (40, 8)):
        Image.new("RGB", (4, 4)).save(folder / f"@{east}@10@seqA@{frame}@pano@city@0@.jpg")
    traversal = load_utm_named_folder(tmp_path)
    assert list(traversal.positions[:, 0]) == [300, 200, 100, 50, 40]
    assert list(traversal.segment_ids) == [0, 0, 0, 1, 1]
