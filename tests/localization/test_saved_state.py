"""A localiser's saved files name the map they belong to: a state or a calibration of another map is refused by the
map's identity where the map has one; maps written before identities keep today's check."""

from __future__ import annotations

import json
import shutil
import warnings

import numpy as np
import pytest

from seqvpr.localization import Localizer
from seqvpr.localization.localizer import LocalizerSettings, read_calibrations, store_calibration, stored_threshold
from seqvpr.localization.saved_state import STATE_VERSION
from seqvpr.maps import build_map, open_map
from tests.helpers import raises_one_line, write_route_files

RECORD = {"threshold": 0.3, "calibration": "q", "target_precision": 0.9, "precision": 0.95, "reached": True}


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    """Two maps of other frames with the same count, dimension and second of creation (each its own identity)."""
    folder = write_route_files(tmp_path_factory.mktemp("route"), 60, 8, 4)
    build_map([str(folder / "ref.npz")], folder / "map")
    build_map([str(folder / "qry.npz")], folder / "other")
    created = json.loads((folder / "map" / "map.json").read_text())["created"]
    rewrite_info(folder / "other", created=created)
    return folder


def rewrite_info(folder, **values) -> None:
    path = folder / "map.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), **values}))


def state_of(folder, path, route) -> None:
    localizer = Localizer.open(open_map(folder))
    for row in np.load(route / "qry.npz")["descriptors"][:8]:
        localizer.update(row)
    localizer.save_state(path)


def test_a_map_without_an_identity_keeps_todays_check(route, tmp_path):
    shutil.copytree(route / "map", tmp_path / "old")  # as an older seqvpr wrote it: no digests, no identity
    info = json.loads((tmp_path / "old" / "map.json").read_text())
    (tmp_path / "old" / "map.json").write_text(json.dumps(
        {k: v for k, v in info.items() if k not in ("files", "identity")} | {"version": 1}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # such a map opens with a warning of its own
        state_of(tmp_path / "old", tmp_path / "state.npz", route)
        shutil.copytree(tmp_path / "old", tmp_path / "again")  # same count, dimension and creation: accepted
        Localizer.open(open_map(tmp_path / "again")).restore(tmp_path / "state.npz")
    header = json.loads(str(np.load(tmp_path / "state.npz")["header"]))
    assert "identity" not in header["map"] and header["version"] == STATE_VERSION


def test_a_state_names_its_map_by_identity(route, tmp_path):
    mine, other = open_map(route / "map"), open_map(route / "other")
    assert (mine.info.count, mine.info.dim, mine.info.created) == (other.info.count, other.info.dim, other.info.created)
    assert mine.info.identity and other.info.identity and mine.info.identity != other.info.identity
    state_of(route / "map", tmp_path / "state.npz", route)
    assert json.loads(str(np.load(tmp_path / "state.npz")["header"]))["map"]["identity"] == mine.info.identity
    Localizer.open(mine).restore(tmp_path / "state.npz")
    raises_one_line("a localiser state for another map (identity", Localizer.open(other).restore,
                    tmp_path / "state.npz")


def test_a_calibration_records_its_map_and_is_refused_for_another(route, tmp_path):
    for name in ("map", "other"):
        shutil.copytree(route / name, tmp_path / name)
    settings = LocalizerSettings()
    store_calibration(tmp_path / "map", settings, RECORD)
    stored = json.loads((tmp_path / "map" / "localizer.json").read_text())
    assert stored["map"] == open_map(tmp_path / "map").info.identity
    assert stored_threshold(tmp_path / "map", settings)[0] == 0.3
    shutil.copy(tmp_path / "map" / "localizer.json", tmp_path / "other" / "localizer.json")  # onto another map
    raises_one_line("localizer.json: calibrated for another map", read_calibrations, tmp_path / "other")
    raises_one_line("calibrated for another map", Localizer.open, tmp_path / "other")
    store_calibration(tmp_path / "other", LocalizerSettings(method="hmm"), {**RECORD, "threshold": 0.6})
    entries = read_calibrations(tmp_path / "other")  # calibrating again replaces the other map's thresholds
    assert [e["threshold"] for e in entries] == [0.6]


def test_a_calibration_file_from_before_map_identities_still_reads(route, tmp_path):
    shutil.copytree(route / "map", tmp_path / "m")
    entry = {"settings": LocalizerSettings().key(), **RECORD}
    (tmp_path / "m" / "localizer.json").write_text(json.dumps(
        {"format": "seqvpr-localizer", "version": 1, "calibrations": [entry]}))
    assert stored_threshold(tmp_path / "m", LocalizerSettings())[0] == 0.3
