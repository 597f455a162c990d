"""Coordinate systems of positions: latitude/longitude to UTM metres (with the zone they are in) and back, through
the ``utm`` package.

A traversal's ``crs`` names what its ``positions`` are: ``"utm:32N"`` / ``"utm:55S"`` (UTM zone and hemisphere:
they go back to latitude/longitude), ``"local"`` (metres in a frame seqvpr does not know: easting/northing columns
without a zone, odometry), or None (no positions).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from seqvpr.errors import SeqvprError

LOCAL = "local"
_UTM = re.compile(r"utm:([0-9]{1,2})([NS])")


def utm_crs(zone_number: int, northern: bool) -> str:
    """The ``crs`` text of a UTM zone and hemisphere, e.g. ``utm:32N``."""
    return f"utm:{int(zone_number)}{'N' if northern else 'S'}"


def parse_crs(crs: str | None, where: str | Path = "crs") -> tuple[int, bool] | None:
    """``(zone number, northern)`` of a ``utm:ZZH`` text; None for ``local`` or None; anything else is a one-line
    error naming ``where``."""
    if crs is None or crs == LOCAL:
        return None
    found = _UTM.fullmatch(str(crs))
    if found is None or not 1 <= int(found.group(1)) <= 60:
        raise SeqvprError(f"{where}: coordinate system {crs!r} is not 'local' or 'utm:ZONE' + N|S (e.g. utm:32N)")
    return int(found.group(1)), found.group(2) == "N"


def latlon_to_utm(lat: np.ndarray, lon: np.ndarray, where: str | Path) -> tuple[np.ndarray, str]:
    """UTM (easting, northing) [N, 2] in metres of every fix, all in the first fix's zone and hemisphere (a route
    crossing a zone line stays one planar frame), and that ``crs``; a fix out of range is an error naming ``where``
    and the row."""
    import utm

    lat, lon = np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64)
    bad_lat = np.flatnonzero(~((lat >= -80.0) & (lat <= 84.0)))
    if len(bad_lat):
        row = int(bad_lat[0]) + 1
        raise SeqvprError(f"{where}: row {row}, latitude {lat[row - 1]:g} is outside the UTM range [-80, 84]")
    bad_lon = np.flatnonzero(~((lon >= -180.0) & (lon <= 180.0)))
    if len(bad_lon):
        row = int(bad_lon[0]) + 1
        raise SeqvprError(f"{where}: row {row}, longitude {lon[row - 1]:g} is outside [-180, 180]")
    zone = utm.latlon_to_zone_number(float(lat[0]), float(lon[0]))
    northern = bool(lat[0] >= 0.0)
    easting, northing, _, _ = utm.from_latlon(lat, lon, force_zone_number=zone, force_northern=northern)
    return np.column_stack([easting, northing]).astype(np.float64), utm_crs(zone, northern)


def utm_to_latlon(positions: np.ndarray, crs: str | None) -> np.ndarray | None:
    """(latitude, longitude) [N, 2] in degrees of UTM positions in ``crs``; None when ``crs`` is ``local`` or None
    (metres in an unknown frame do not go back)."""
    zone = parse_crs(crs)
    if zone is None:
        return None
    import utm

    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    if not len(positions):
        return np.empty((0, 2))
    lat, lon = utm.to_latlon(positions[:, 0], positions[:, 1], zone[0], northern=zone[1], strict=False)
    return np.column_stack([lat, lon]).astype(np.float64)


def positions_in(positions: np.ndarray, crs: str | None, target: str | None, where: str) -> np.ndarray:
    """UTM ``positions`` in ``crs`` expressed in ``target``'s zone and hemisphere (through latitude and longitude: a
    route that crosses a zone line, or a pair whose sides start on either side of one, compares in one planar
    frame); as they are when the two agree. A local frame and a UTM one cannot be compared: one line naming
    ``where``."""
    crs, target = crs or LOCAL, target or LOCAL
    if crs == target:
        return positions
    zone, goal = parse_crs(crs, where), parse_crs(target, where)
    if zone is None or goal is None:
        raise SeqvprError(f"{where}: positions in {crs} cannot be compared with positions in {target} (a local "
                          "frame has no place on the globe): give both sides in one coordinate system")
    import utm

    latlon = utm_to_latlon(positions, crs)
    easting, northing, _, _ = utm.from_latlon(latlon[:, 0], latlon[:, 1], force_zone_number=goal[0],
                                              force_northern=goal[1])
    return np.column_stack([easting, northing]).astype(np.float64)
