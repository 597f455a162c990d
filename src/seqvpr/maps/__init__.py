"""Saved maps: a reference described once, stored as plain memory-mappable files, matched many times.

    saved = build_map(["summer.npy"], "maps/summer")          # or seqvpr map build summer.npy --out maps/summer
    saved = open_map("maps/summer")                            # memory-mapped, never read whole
    result = match_map(saved, load_traversal("winter.npy", "query"), "matching", MatchSettings(SequenceSpec(5)))
"""

from __future__ import annotations

import importlib
from typing import Any

#: public name -> the module defining it; imported when first used, so ``seqvpr.maps.files`` (what a localiser
#: needs) does not pull in the builder's loaders and descriptors
EXPORTS = {"FrameDescription": "build", "build_map": "build", "build_sharded_map": "build", "describe_frames": "build", "MapInfo": "files",
           "SavedMap": "files", "open_map": "files", "read_map_info": "files", "match_map": "match"}

__all__ = list(EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in EXPORTS:
        raise AttributeError(f"module 'seqvpr.maps' has no attribute {name!r}")
    return getattr(importlib.import_module(f"seqvpr.maps.{EXPORTS[name]}"), name)
