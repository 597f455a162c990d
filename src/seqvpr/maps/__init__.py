"""Saved maps: a reference described once, stored as plain memory-mappable files, matched many times.

    saved = build_map(["summer.npy"], "maps/summer")          # or seqvpr map build summer.npy --out maps/summer
    saved = load_map("maps/summer")                            # memory-mapped, never read whole
    result = match_map(saved, load_traversal("winter.npy", "query"), "matching", MatchSettings(SequenceSpec(5)))
"""

from seqvpr.maps.build import FrameDescription, build_map, describe_frames
from seqvpr.maps.files import MapInfo, SavedMap, open_map, read_map_info
from seqvpr.maps.match import match_map

load_map = open_map

__all__ = ["FrameDescription", "MapInfo", "SavedMap", "build_map", "describe_frames", "load_map", "match_map",
           "open_map", "read_map_info"]
