"""A route across a UTM zone line: each side starts in its own zone (the reference east of 11.997 degrees E in zone
32, the query driving back from 12.003 degrees E in zone 33), and matching it evaluates every query, with the
figures a copy of the same route inside one zone gives (match, match against a map, localize). The copy lies as far
from its zone's central meridian as the route does, so the projection scales both alike."""

from __future__ import annotations

import json

import numpy as np
import pytest

from seqvpr.data.geo import latlon_to_utm
from seqvpr.data.sources import save_traversal_npz
from seqvpr.data.traversal import Traversal
from seqvpr.synthetic.routes import generate_route
from tests.helpers import run_cli

LAT = 48.1


def drives(centre_lon: float) -> tuple[Traversal, Traversal]:
    """The synthetic route's reference and its query driven the other way, placed around ``centre_lon``, each in the
    UTM zone of its own first fix (as a loader of latitude/longitude places them)."""
    reference, query = generate_route(n_frames=160, dim=16, seed=6)
    sides = []
    for side, order in ((reference, slice(None)), (query, slice(None, None, -1))):  # the query the other way
        xy = side.positions[order]
        lon = centre_lon + (xy[:, 0] - 150.0) / (111_320.0 * np.cos(np.radians(LAT)))
        lat = LAT + xy[:, 1] / 111_320.0
        positions, crs = latlon_to_utm(lat, lon, side.name)
        sides.append(Traversal(side.name, side.frame_index, np.zeros(len(side), np.int64), side.descriptors[order],
                               positions=positions, crs=crs))
    return sides[0], sides[1]


def figures(folder, reference: Traversal, query: Traversal, monkeypatch, capsys) -> list[dict]:
    save_traversal_npz(folder / "ref.npz", reference)
    save_traversal_npz(folder / "qry.npz", query)
    assert run_cli(monkeypatch, capsys, "map", "build", folder / "ref.npz", "--out", folder / "map")[0] == 0
    found = []
    for arguments in (("match", "-r", folder / "ref.npz", "-q", folder / "qry.npz", "--out", folder / "a"),
                      ("match", "--map", folder / "map", "-q", folder / "qry.npz", "--out", folder / "b"),
                      ("localize", "--map", folder / "map", "-q", folder / "qry.npz", "--out", folder / "c")):
        code, out, err = run_cli(monkeypatch, capsys, *arguments, "--radius", "10m", "--json")
        assert code == 0, err
        result = json.loads(out)
        found.append({k: result[k] for k in ("recall", "queries_evaluated")})
    return found


@pytest.mark.slow
def test_a_route_across_a_zone_line_gives_the_figures_of_the_same_route_in_one_zone(tmp_path, monkeypatch, capsys):
    reference, query = drives(12.0)
    assert (reference.crs, query.crs) == ("utm:32N", "utm:33N")  # each side in the zone of its own first fix
    one_zone = drives(6.0035)  # as far west of zone 32's central meridian (9 E) as 12 E is east: the same scale
    assert one_zone[0].crs == one_zone[1].crs == "utm:32N"
    (tmp_path / "across").mkdir()
    (tmp_path / "inside").mkdir()
    across = figures(tmp_path / "across", reference, query, monkeypatch, capsys)
    inside = figures(tmp_path / "inside", *one_zone, monkeypatch, capsys)
    assert [f["queries_evaluated"] for f in across] == [160, 160, 156]  # localize: the first L - 1 frames warm up
    assert across == inside
