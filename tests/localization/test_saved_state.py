"""A localiser's saved files name the map they belong to: a state or a calibration of another map is refused by the
map's identity where the map has one; maps written before identities keep today's check."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from seqvpr.localization import Localizer
from seqvpr.localization.localizer import LocalizerSettings, read_calibrations, store_calibration, stored_threshold
from seqvpr.maps import build_map, load_map
from tests.helpers import raises_one_line, write_route_files

RECORD = {"threshold": 0.3, "calibration": "q", "target_precision": 0.9, "precision": 0.95, "reached": True}


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    folder = write_route_files(tmp_path_factory.mktemp("route"), 60, 8, 4)
    build_map([str(folder / "ref.npz")], folder / "map")
    return folder


def set_identity(folder, identity) -> None:
    path = folder / "map.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "identity": identity}))


def state_of(folder, path, route) -> None:
    localizer = Localizer.open(load_map(folder))
    for row in np.load(route / "qry.npz")["descriptors"][:8]:
        localizer.update(row)
    localizer.save_state(path)


def test_a_map_without_an_identity_keeps_todays_check(route, tmp_path):
    shutil.copytree(route / "map", tmp_path / "copy")
    set_identity(tmp_path / "copy", None)
    state_of(tmp_path / "copy", tmp_path / "state.npz", route)
    shutil.copytree(tmp_path / "copy", tmp_path / "again")  # same count, dimension and creation: accepted
    Localizer.open(load_map(tmp_path / "again")).restore(tmp_path / "state.npz")
    header = json.loads(str(np.load(tmp_path / "state.npz")["header"]))
    assert "identity" not in header["map"] and header["version"] == 1


def test_a_state_names_its_map_by_identity(route, tmp_path):
    for name, fill in (("a", "a"), ("b", "b")):
        shutil.copytree(route / "map", tmp_path / name)
        set_identity(tmp_path / name, "sha256:" + fill * 64)
    state_of(tmp_path / "a", tmp_path / "state.npz", route)
    assert json.loads(str(np.load(tmp_path / "state.npz")["header"]))["map"]["identity"] == "sha256:" + "a" * 64
    Localizer.open(load_map(tmp_path / "a")).restore(tmp_path / "state.npz")
    raises_one_line("a localiser state for another map (identity", Localizer.open(load_map(tmp_path / "b")).restore,
                    tmp_path / "state.npz")


def test_a_calibration_records_its_map_and_is_refused_for_another(route, tmp_path):
    shutil.copytree(route / "map", tmp_path / "m")
    set_identity(tmp_path / "m", "sha256:" + "a" * 64)
    settings = LocalizerSettings()
    store_calibration(tmp_path / "m", settings, RECORD)
    stored = json.loads((tmp_path / "m" / "localizer.json").read_text())
    assert stored["map"] == "sha256:" + "a" * 64 and stored_threshold(tmp_path / "m", settings)[0] == 0.3
    set_identity(tmp_path / "m", "sha256:" + "b" * 64)  # the folder now holds another map
    raises_one_line("localizer.json: calibrated for another map", read_calibrations, tmp_path / "m")
    raises_one_line("calibrated for another map", Localizer.open, tmp_path / "m")
    store_calibration(tmp_path / "m", LocalizerSettings(method="hmm"), {**RECORD, "threshold": 0.6})
    entries = read_calibrations(tmp_path / "m")  # calibrating again replaces the other map's thresholds
    assert [e["threshold"] for e in entries] == [0.6]


def test_a_calibration_file_from_before_map_identities_still_reads(route, tmp_path):
    shutil.copytree(route / "map", tmp_path / "m")
    set_identity(tmp_path / "m", "sha256:" + "a" * 64)
    entry = {"settings": LocalizerSettings().key(), **RECORD}
    (tmp_path / "m" / "localizer.json").write_text(json.dumps(
        {"format": "seqvpr-localizer", "version": 1, "calibrations": [entry]}))
    assert stored_threshold(tmp_path / "m", LocalizerSettings())[0] == 0.3
