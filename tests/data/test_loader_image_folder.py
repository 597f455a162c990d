"""Image folder loader: natural order, CSV positions (metres and lat/lon), segments, and one-line errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import utm
from PIL import Image

from seqvpr.data.loaders.image_folder import load_image_folder, natural_key
from tests.helpers import raises_one_line


def _image(path: Path) -> None:
    """Write a tiny image whose format follows the extension."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fmt = {".jpg": "JPEG", ".jpeg": "JPEG", ".png": "PNG", ".bmp": "BMP", ".tif": "TIFF"}[path.suffix.lower()]
    Image.new("RGB", (4, 3), (10, 20, 30)).save(path, format=fmt)


def _images(folder: Path, names: list[str]) -> Path:
    for name in names:
        _image(folder / name)
    return folder


def _csv(path: Path, text: str) -> Path:
    path.write_text(text)
    return path



def test_natural_key_orders_digit_runs_by_value():
    names = ["img10.png", "img2.png", "Img1.png", "img2b.png"]
    assert sorted(names, key=natural_key) == ["Img1.png", "img2.png", "img2b.png", "img10.png"]


def test_folder_without_csv_is_natural_order_frame_aligned(tmp_path):
    folder = _images(tmp_path / "drive", ["img10.png", "img2.jpg", "img1.JPG"])
    (folder / "notes.txt").write_text("not an image")
    (folder / ".hidden.png").write_bytes(b"x")
    _image(folder / "sub" / "img0.png")  # subfolders are not read
    trav = load_image_folder(folder)
    assert trav.frame_names() == ["img1.JPG", "img2.jpg", "img10.png"]
    assert trav.name == "drive"
    assert trav.source == str(folder)
    assert trav.positions is None and trav.descriptors is None
    assert trav.frame_index.dtype == np.int64 and list(trav.frame_index) == [0, 1, 2]
    assert trav.segment_ids.dtype == np.int64 and trav.n_segments == 1
    assert all(p.is_absolute() and p.is_file() for p in trav.image_paths)


def test_folder_errors_name_the_folder(tmp_path):
    raises_one_line("nowhere", load_image_folder, tmp_path / "nowhere")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.txt").write_text("no images")
    raises_one_line("empty", load_image_folder, empty)


def test_csv_easting_northing_in_row_order_with_optional_columns(tmp_path):
    folder = _images(tmp_path / "imgs", ["b.png", "a.png", "c.png"])
    csv_path = _csv(
        tmp_path / "pos.csv",
        " Image , Easting,NORTHING,timestamp,heading\n"
        "b.png,500000,4000000,0.0,90\n"
        "a.png,500010.5,4000000,1.5,180\n"
        "\n"
        "c.png,500020,4000003,3.0,270\n",
    )
    trav = load_image_folder(folder, csv_path, name="ref")
    assert trav.name == "ref"
    assert trav.frame_names() == ["b.png", "a.png", "c.png"]
    assert list(trav.frame_index) == [0, 1, 2]
    assert trav.positions.dtype == np.float64 and trav.positions.shape == (3, 2)
    np.testing.assert_allclose(trav.positions, [[500000, 4000000], [500010.5, 4000000], [500020, 4000003]])
    np.testing.assert_allclose(trav.timestamps, [0.0, 1.5, 3.0])
    np.testing.assert_allclose(trav.headings, [90, 180, 270])
    assert trav.timestamps.dtype == np.float64 and trav.headings.dtype == np.float64
    assert trav.n_segments == 1
    assert trav.image_paths[0] == folder.absolute() / "b.png"


def test_csv_latlon_converted_in_the_first_rows_zone(tmp_path):
    folder = _images(tmp_path / "imgs", ["0.png", "1.png", "2.png"])
    # the route crosses the 6 degree line between UTM zones 31 and 32
    rows = [(48.85, 5.99), (48.851, 5.9995), (48.852, 6.01)]
    text = "filename,latitude,longitude\n" + "".join(f"{i}.png,{lat},{lon}\n" for i, (lat, lon) in enumerate(rows))
    trav = load_image_folder(folder, _csv(tmp_path / "gps.csv", text))
    _, _, zone, letter = utm.from_latlon(*rows[0])
    for i, (lat, lon) in enumerate(rows):
        east, north, _, _ = utm.from_latlon(lat, lon, force_zone_number=zone, force_zone_letter=letter)
        np.testing.assert_allclose(trav.positions[i], [east, north], atol=1e-6)
    steps = np.linalg.norm(np.diff(trav.positions, axis=0), axis=1)
    assert steps.max() < 1500  # no zone jump of hundreds of kilometres


def test_csv_short_lat_lon_names(tmp_path):
    folder = _images(tmp_path / "imgs", ["x.png"])
    trav = load_image_folder(folder, _csv(tmp_path / "p.csv", "name,lat,lon\nx.png,-33.87,151.21\n"))
    east, north, _, _ = utm.from_latlon(-33.87, 151.21)
    np.testing.assert_allclose(trav.positions[0], [east, north])


def test_segment_column_defines_segments(tmp_path):
    folder = _images(tmp_path / "imgs", [f"{i}.png" for i in range(5)])
    text = "file,easting,northing,segment\n" + "".join(
        f"{i}.png,{i},0,{seg}\n" for i, seg in enumerate([3, 3, 7, 7, 7])
    )
    trav = load_image_folder(folder, _csv(tmp_path / "p.csv", text), max_distance_gap=0.5)
    assert trav.segment_ids.dtype == np.int64
    assert list(trav.segment_ids) == [3, 3, 7, 7, 7]  # the column wins over gap thresholds
    assert trav.n_segments == 2


def test_segments_from_time_and_distance_gaps(tmp_path):
    folder = _images(tmp_path / "imgs", [f"{i}.png" for i in range(6)])
    east = [0, 1, 2, 50, 51, 52]
    stamps = [0, 1, 2, 3, 30, 31]
    text = "name,easting,northing,timestamp\n" + "".join(
        f"{i}.png,{e},0,{t}\n" for i, (e, t) in enumerate(zip(east, stamps))
    )
    csv_path = _csv(tmp_path / "p.csv", text)
    assert load_image_folder(folder, csv_path).n_segments == 1
    by_time = load_image_folder(folder, csv_path, max_time_gap=5.0)
    assert list(by_time.segment_ids) == [0, 0, 0, 0, 1, 1]
    by_distance = load_image_folder(folder, csv_path, max_distance_gap=10.0)
    assert list(by_distance.segment_ids) == [0, 0, 0, 1, 1, 1]
    both = load_image_folder(folder, csv_path, max_time_gap=5.0, max_distance_gap=10.0)
    assert list(both.segment_ids) == [0, 0, 0, 1, 2, 2]


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "no header"),
        ("easting,northing\n1,2\n", "no image name column"),
        ("name,foo\na.png,1\n", "no position columns"),
        ("name,easting\na.png,1\n", "'easting' has no partner column 'northing'"),
        ("name,easting,northing\n", "no rows"),
        ("name,easting,northing\na.png,abc,2\n", "row 1 (line 2), column 'easting': 'abc' is not a finite number"),
        ("name,easting,northing\na.png,1,2\nb.png,1,\n", "row 2 (line 3), column 'northing': the value is empty"),
        ("name,easting,northing,timestamp\na.png,1,2,nan\n", "column 'timestamp'"),
        ("name,easting,northing,segment\na.png,1,2,1.5\n", "column 'segment': '1.5' is not an integer"),
        ("name,easting,northing\nmissing.png,1,2\n", "'missing.png' does not exist"),
        ("name,easting,northing\na.png,1,2\na.png,3,4\n", "listed twice (first at row 1)"),
        ("name,easting,northing\na.png,1\n", "row 1 (line 2) has 2 fields"),
        ("name,name,easting,northing\na.png,a.png,1,2\n", "appears twice"),
        ("name,lat,lon\na.png,85,10\n", "outside the UTM range"),
    ],
)
def test_csv_errors_are_one_line_and_name_the_csv(tmp_path, text, match):
    folder = _images(tmp_path / "imgs", ["a.png", "b.png"])
    csv_path = _csv(tmp_path / "broken_positions.csv", text)
    message = raises_one_line(match, load_image_folder, folder, csv_path)
    assert "broken_positions.csv" in message


def test_missing_csv_is_named(tmp_path):
    folder = _images(tmp_path / "imgs", ["a.png"])
    raises_one_line("absent.csv", load_image_folder, folder, tmp_path / "absent.csv")


def test_max_time_gap_without_timestamps_is_an_error(tmp_path):
    folder = _images(tmp_path / "imgs", ["a.png"])
    csv_path = _csv(tmp_path / "p.csv", "name,easting,northing\na.png,1,2\n")
    raises_one_line("timestamp column", load_image_folder, folder, csv_path, max_time_gap=1.0)
