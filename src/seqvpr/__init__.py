"""seqvpr: sequence-based visual place recognition.

    import seqvpr
    result = seqvpr.match("day.npz", "night.npz", "matching", seq_len=5)   # or a map: seqvpr.open_map(folder)
    print(seqvpr.evaluate(result, radius="2f").recall)

The data flow is: traversals (frames with descriptors and positions) -> descriptors -> matching by a method's
matcher (``seqvpr.matchers``; one record per method in ``seqvpr.methods``) -> predictions -> evaluation. The
public names below are imported when first used, so ``import seqvpr`` stays light.
"""

from __future__ import annotations

import importlib
from typing import Any

from seqvpr.errors import SeqvprError

__version__ = "0.1.0"

#: public name -> the module defining it
EXPORTS = {
    "load_traversal": "seqvpr.data.sources", "Traversal": "seqvpr.data.traversal",
    "match": "seqvpr.api", "evaluate": "seqvpr.api",
    "MatchSettings": "seqvpr.sequences.match_settings", "SequenceSpec": "seqvpr.sequences.windows",
    "build_map": "seqvpr.maps.build", "open_map": "seqvpr.maps.files",
    "Localizer": "seqvpr.localization.localizer",
    "loops": "seqvpr.localization.loops", "LoopSettings": "seqvpr.localization.loops",
    "LoopDetector": "seqvpr.localization.loop_detector", "add_to_map": "seqvpr.maps.grow",
    "view_page": "seqvpr.viewer",
}
__all__ = ["SeqvprError", "__version__", *EXPORTS]


def __getattr__(name: str) -> Any:
    if name not in EXPORTS:
        raise AttributeError(f"module 'seqvpr' has no attribute {name!r}")
    return getattr(importlib.import_module(EXPORTS[name]), name)


def __dir__() -> list[str]:
    return sorted(__all__)
