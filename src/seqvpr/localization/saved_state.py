"""What a localiser keeps on disk, checked as it is read: a saved state (``Localizer.save_state``: its format
version, the map it belongs to, counters and the matcher's arrays) and the calibrated thresholds in a map's
``localizer.json`` (each threshold a number, the file recorded for this map). A damaged file, one of another
version or one for another map is one line naming it: a localiser never goes on from one. The map is named by its
identity (a hash of its files' digests) where it has one, else, for maps written before, by count, dimension and
time of creation."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr.errors import SeqvprError
from seqvpr.maps.files import MapInfo
from seqvpr.maps.keep import CALIBRATION_FILE, identity_of

STATE_FORMAT = "seqvpr-localizer-state"
STATE_VERSION = 2  # 2: sequence matching keeps its last L distance rows (``ring``), not running sums
CALIBRATION_FORMAT = "seqvpr-localizer"
CALIBRATION_VERSION = 1
COUNTERS = ("frame", "misses", "since_reset")


def map_record(info: MapInfo) -> dict[str, Any]:
    """How a state names its map: count, dimension, creation time and, where the map has one, its identity."""
    record: dict[str, Any] = {"count": info.count, "dim": info.dim, "created": info.created}
    if info.identity:
        record["identity"] = info.identity
    return record


def check_state_header(path: str | Path, header: Any, info: MapInfo) -> None:
    """A state's header: this format and version, this map (by identity where both record one), whole counters."""
    if not isinstance(header, dict) or header.get("format") != STATE_FORMAT:
        raise SeqvprError(f"{path}: not a localiser state")
    if header.get("version") != STATE_VERSION:
        raise SeqvprError(f"{path}: localiser state version {header.get('version')!r} is not known (this seqvpr reads "
                          f"version {STATE_VERSION})")
    saved, current = header.get("map"), map_record(info)
    ours, theirs = current.get("identity"), saved.get("identity") if isinstance(saved, dict) else None
    if ours and theirs and ours != theirs:
        raise SeqvprError(f"{path}: a localiser state for another map (identity {theirs[:19]}..., this map "
                          f"{ours[:19]}...)")
    if saved != current:
        raise SeqvprError(f"{path}: a localiser state for another map ({saved}, this map {current})")
    for key in COUNTERS:
        value = header.get(key)
        if not (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
            raise SeqvprError(f"{path}: {key} {value!r} is not a count (a whole number >= 0)")


def check_state_arrays(path: str | Path, arrays: dict[str, np.ndarray], dim: int) -> None:
    """A state's arrays: numbers; counts whole and >= 0; beliefs probabilities summing to 1; frames finite and of
    the map's dimension ``dim``; distance rows finite and >= 0; other values free of NaN and -inf."""
    for name, array in arrays.items():
        if name == "header":
            continue
        if array.dtype.kind not in "fiu":
            raise SeqvprError(f"{path}: {name} holds {array.dtype} values, not numbers")
        if name.endswith("count"):
            if array.size != 1 or not np.isfinite(array).all() or array.item() < 0 or array.item() != int(array.item()):
                raise SeqvprError(f"{path}: {name} {array.tolist()!r} is not a count (a whole number >= 0)")
        elif name.endswith("belief"):
            if not np.isfinite(array).all() or (array < 0).any() or (array > 1).any() \
                    or not math.isclose(float(array.sum()), 1.0, rel_tol=1e-6):
                raise SeqvprError(f"{path}: {name} is not a belief (probabilities in [0, 1] summing to 1)")
        elif name.endswith(("frames", "last_kept")):
            if array.ndim not in (1, 2) or array.shape[-1] != dim:
                raise SeqvprError(f"{path}: {name} has shape {array.shape}; the map's frames are {dim}-D")
            if not np.isfinite(array).all():
                raise SeqvprError(f"{path}: {name} holds NaN or infinite values (damaged)")
        elif name.endswith("ring"):
            if not np.isfinite(array).all() or (array < 0).any():
                raise SeqvprError(f"{path}: {name} holds NaN, infinite or negative distances (damaged)")
        elif array.dtype.kind == "f" and (np.isnan(array).any() or np.isneginf(array).any()):
            raise SeqvprError(f"{path}: {name} holds NaN or -inf (damaged)")


def read_calibration_file(folder: str | Path, replacing: bool = False) -> list[dict[str, Any]]:
    """The calibrations in ``folder``'s ``localizer.json`` (none without one), each checked: one line naming the file
    when it is malformed, of another version, or recorded for another map (``replacing``, as a new calibration is
    stored: none, since another map's thresholds mean nothing here)."""
    path = Path(folder) / CALIBRATION_FILE
    if not path.exists():
        return []
    try:
        values = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise SeqvprError(f"{path}: malformed ({type(error).__name__}: {error})") from None
    if not isinstance(values, dict) or not isinstance(values.get("calibrations"), list):
        raise SeqvprError(f"{path}: malformed (no list of calibrations)")
    if values.get("version", CALIBRATION_VERSION) != CALIBRATION_VERSION:
        raise SeqvprError(f"{path}: localizer.json version {values.get('version')!r} is not known (this seqvpr reads "
                          f"version {CALIBRATION_VERSION})")
    recorded, ours = values.get("map"), identity_of(Path(folder))
    if recorded and ours and recorded != ours:
        if replacing:
            return []
        raise SeqvprError(f"{path}: calibrated for another map (identity {str(recorded)[:19]}..., this map "
                          f"{ours[:19]}...): calibrate again (seqvpr localize --calibrate)")
    for number, entry in enumerate(values["calibrations"], start=1):
        check_calibration(path, number, entry)
    return values["calibrations"]


def check_calibration(path: Path, number: int, entry: Any) -> None:
    """One calibration: its settings, a threshold that is a number >= 0, precisions that are numbers in [0, 1]."""
    if not isinstance(entry, dict) or not isinstance(entry.get("settings"), dict):
        raise SeqvprError(f"{path}: calibration {number} is malformed (no settings)")
    if "threshold" not in entry:
        raise SeqvprError(f"{path}: calibration {number} has no threshold")
    if not _number(entry["threshold"]) or entry["threshold"] < 0:
        raise SeqvprError(f"{path}: calibration {number} threshold {entry['threshold']!r} is not a number >= 0")
    for key in ("target_precision", "precision", "recall"):
        if key in entry and not (_number(entry[key]) and 0 <= entry[key] <= 1):
            raise SeqvprError(f"{path}: calibration {number} {key} {entry[key]!r} is not a number in [0, 1]")


def _number(value: Any) -> bool:
    """A finite JSON number (not a boolean, not a string, not NaN or infinity)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def calibration_file(calibrations: list[dict[str, Any]], folder: str | Path) -> dict[str, Any]:
    """What ``localizer.json`` holds: format, version, the map's identity (where it has one), the calibrations."""
    return {"format": CALIBRATION_FORMAT, "version": CALIBRATION_VERSION, "map": identity_of(Path(folder)),
            "calibrations": calibrations}
