"""The one place a matcher stack is built, offline and a frame at a time alike: a family's matcher (what a method's
record builds, ``seqvpr.methods.build_matcher``), over shards when the reference is split into them (``Sharded``,
each rank its own), re-ranking only what a nearest-neighbour search proposes when a shortlist is given
(``Shortlisted``). Each wrapper is a ``Matcher`` that checks what it can wrap, so the stack answers ``topk`` and
``stream`` as any matcher does."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from seqvpr.matchers.base import Matcher
from seqvpr.matchers.sharded import Sharded, is_sharded
from seqvpr.matchers.shortlisted import Neighbors, Shortlisted, check_shortlistable


@dataclass(frozen=True)
class Shortlist:
    """A shortlist: how to open the search that proposes candidates (a map's index, a sharded map's indexes merged,
    a brute-force search; opened once the matcher is known to take a shortlist), the ``size`` S nearest reference
    frames a query frame and the ``history`` H frames before each window that place candidates too."""

    open: Callable[[], Neighbors]
    size: int
    history: int = 0


def assemble(matcher: Matcher, reference: Any, shortlist: Shortlist | None = None, ranks: Any = None) -> Matcher:
    """``matcher`` stacked for ``reference``: over its shards when it is sharded (under ``ranks``, the distributed
    run, each rank its shards; None: the current run), then over ``shortlist``'s candidates when one is given."""
    stacked = Sharded(matcher, ranks) if is_sharded(reference) else matcher
    if shortlist is None:
        return stacked
    check_shortlistable(stacked)
    return Shortlisted(stacked, shortlist.open(), shortlist.size, shortlist.history)
