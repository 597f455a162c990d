"""Coordinate systems: latitude/longitude to UTM with its zone and back (``seqvpr.data.geo``), and the ``crs`` each
loader records."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from seqvpr.data.geo import latlon_to_utm, parse_crs, positions_in, utm_to_latlon
from tests.helpers import raises_one_line


@pytest.mark.parametrize("lat, lon, crs", [
    ([48.137, 48.138], [11.575, 11.576], "utm:32N"),
    ([-33.86, -33.87], [151.21, 151.22], "utm:56S"),
    ([59.9, 59.91], [5.99, 6.02], "utm:32N"),  # a route across the zone line keeps the first fix's zone
    ([0.0001, -0.0001], [10.0, 10.0], "utm:32N"),  # and across the equator, its hemisphere
])
def test_latitudes_and_longitudes_go_to_utm_with_their_zone_and_back(lat, lon, crs):
    positions, found = latlon_to_utm(np.array(lat), np.array(lon), "fixes.csv")
    assert found == crs and positions.shape == (len(lat), 2)
    np.testing.assert_allclose(utm_to_latlon(positions, crs), np.c_[lat, lon], rtol=0, atol=1e-8)


def test_local_positions_do_not_go_back_and_bad_ones_are_one_line():
    assert utm_to_latlon(np.zeros((3, 2)), "local") is None and utm_to_latlon(np.zeros((3, 2)), None) is None
    assert parse_crs("utm:7S") == (7, False) and parse_crs("local") is None
    raises_one_line("map.json: coordinate system 'utm:32X' is not", parse_crs, "utm:32X", "map.json")
    raises_one_line("fixes.csv: row 2, latitude 85 is outside the UTM range", latlon_to_utm, np.array([1.0, 85.0]),
                    np.array([1.0, 1.0]), "fixes.csv")
    raises_one_line("q.npz: positions in local cannot be compared with positions in utm:32N", positions_in,
                    np.zeros((2, 2)), "local", "utm:32N", "q.npz")


def test_positions_in_another_zone_are_the_same_places():
    """Fixes on both sides of 12 degrees E (the line between zones 32 and 33), each side in the zone of its own
    first fix: expressed in the other zone they are the places the other zone's own conversion gives."""
    lat, lon = np.array([48.1, 48.1, 48.1001]), np.array([11.9995, 12.0005, 12.001])
    in_32, crs_32 = latlon_to_utm(lat, lon, "a")
    in_33, crs_33 = latlon_to_utm(lat[::-1], lon[::-1], "b")
    assert (crs_32, crs_33) == ("utm:32N", "utm:33N")
    np.testing.assert_allclose(positions_in(in_33, crs_33, crs_32, "b")[::-1], in_32, atol=1e-6)
    assert positions_in(in_32, crs_32, crs_32, "a") is in_32  # one frame already: as it is


def test_each_loader_records_the_coordinate_system_of_its_positions(tmp_path):
    from seqvpr.data.loaders.image_folder import load_image_folder
    from seqvpr.data.loaders.utm_names import load_utm_named_folder

    folder = tmp_path / "images"
    folder.mkdir()
    for name in ("a.png", "b.png"):
        Image.new("RGB", (4, 4)).save(folder / name)
    (folder / "ll.csv").write_text("name,lat,lon\na.png,-33.86,151.21\nb.png,-33.87,151.22\n")
    (folder / "en.csv").write_text("name,easting,northing\na.png,1,2\nb.png,3,4\n")
    assert load_image_folder(folder, folder / "ll.csv").crs == "utm:56S"
    assert load_image_folder(folder, folder / "en.csv").crs == "local"
    assert load_image_folder(folder).crs is None
    named = tmp_path / "named"
    named.mkdir()
    for east in (500000, 500010):
        Image.new("RGB", (4, 4)).save(named / f"@{east}@4000000@33@T@36.1@15.0@@@@@@@@@.jpg")
    assert load_utm_named_folder(named).crs == "utm:33N"
    Image.new("RGB", (4, 4)).save(named / "@500020@4000000@@.jpg")  # a name without a zone
    assert load_utm_named_folder(named).crs == "local"
