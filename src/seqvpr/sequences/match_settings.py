"""The settings that decide any match (a family's own knobs live with its matcher)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from seqvpr import checks
from seqvpr.sequences.windows import SequenceSpec

#: the numeric types matching computes in
MATCH_DTYPES = ("float32", "float64")
#: bytes a match's distance blocks may take unless told otherwise (the command line's and the API's default)
DEFAULT_BUDGET = 2 * 1024**3


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
        checks.instance(self.sequence, "sequence", SequenceSpec, "a SequenceSpec")
        object.__setattr__(self, "k", checks.whole(self.k, "k", 1))
        checks.flag(self.normalize, "normalize")
        checks.text(self.dtype, "dtype", MATCH_DTYPES)
        checks.device(self.device)
        object.__setattr__(self, "memory_budget", checks.optional_whole(self.memory_budget, "memory_budget", 1))

    def as_dict(self) -> dict:
        return asdict(self)
