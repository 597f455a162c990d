"""A map folder's own files and a user's. A map owns what its ``map.json`` names (its rows, side files, frame table,
names, index) and the calibration beside it while that is still the map's; a command that writes the map anew (a
rebuild, an index) carries everything else over, so a user's files and folders in a map folder outlive it."""

from __future__ import annotations

import json
from pathlib import Path

from seqvpr.io import carry_over
from seqvpr.maps.codes import SIDE_FILES
from seqvpr.maps.files import DESCRIPTORS_FILE, INFO_FILE, PER_FRAME_FILES
from seqvpr.maps.names import NAMES_FILE, OFFSETS_FILE
from seqvpr.progress import LOGGER

CALIBRATION_FILE = "localizer.json"  # the localiser's calibrated thresholds (``seqvpr.localization.saved_state``)
#: the files a map of any version may write (a version-1 map.json names none of them; an index is in its record)
MAP_FILES = (INFO_FILE, DESCRIPTORS_FILE, *SIDE_FILES.values(), *PER_FRAME_FILES, NAMES_FILE, OFFSETS_FILE)


def owned_files(folder: Path) -> set[str]:
    """The names a map folder's ``map.json`` makes the map's own (its files, its index's), and every map file name."""
    try:
        values = json.loads((folder / INFO_FILE).read_text())
    except (OSError, ValueError):
        values = {}
    values = values if isinstance(values, dict) else {}
    index = values.get("index") if isinstance(values.get("index"), dict) else {}
    named = [*(values.get("files") or {}), index.get("file"), index.get("rows_file")]
    return {*MAP_FILES, *(name for name in named if isinstance(name, str))}


def identity_of(folder: Path) -> str | None:
    """The identity a map folder's ``map.json`` records (None without one)."""
    try:
        identity = json.loads((folder / INFO_FILE).read_text()).get("identity")
    except (OSError, ValueError, AttributeError):
        return None
    return identity if isinstance(identity, str) else None


def keep_users_files(old: Path, new: Path) -> None:
    """Everything in the map folder ``old`` that the map does not own, carried into ``new`` (the map that replaces
    it): a user's files and folders as they are, the calibration when ``new`` is the same map (an index leaves the
    identity as it is), else left out with a warning naming it (another map's thresholds mean nothing)."""
    if not (old / INFO_FILE).is_file():
        return
    skip = {*owned_files(old), *(p.name for p in new.iterdir())}
    calibration = old / CALIBRATION_FILE
    if calibration.exists() and CALIBRATION_FILE not in skip and identity_of(old) != identity_of(new):
        skip.add(CALIBRATION_FILE)
        LOGGER.warning(f"{calibration}: calibrated for the map this one replaces, so left out: calibrate again "
                       "(seqvpr localize --calibrate)")
    carry_over(old, new, tuple(skip))
