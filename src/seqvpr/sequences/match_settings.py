"""The settings that decide any match (a family's own knobs live with its matcher)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from seqvpr.sequences.windows import SequenceSpec


@dataclass(frozen=True)
class MatchSettings:
    """What decides any match: sequences, K, normalisation, numeric type, device and memory budget (a family's own
    knobs live in its matcher)."""

    sequence: SequenceSpec = field(default_factory=SequenceSpec)
    k: int = 20
    normalize: bool = True
    dtype: str = "float32"
    device: str = "cpu"
    memory_budget: int | None = 2 * 1024**3

    def __post_init__(self) -> None:
        from seqvpr.errors import SettingError

        if isinstance(self.k, bool) or not isinstance(self.k, (int, np.integer)) or self.k < 1:
            raise SettingError(f"{{k}} (matches kept per query) must be a whole number at least 1, got {self.k!r}")

    def as_dict(self) -> dict:
        return asdict(self)
