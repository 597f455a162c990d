"""One class per matching family, each with ``topk(reference, query)`` and ``stream(reference)``: frame sequence
matching (``sequence``), retrieval by a sequence descriptor (``retrieval``), hierarchical (``hierarchical``), the
HMM filter (``filter``) and graph matching (``graph``); what they share in ``base``, the one-frame steppers in
``stream``, a matcher written as one window distance in ``windows``. Any matcher that scores windows is wrapped,
not copied, for a shortlist (``shortlisted.Shortlisted``) and for shards (``sharded.Sharded``), offline and a frame
at a time; ``assemble`` (``stack.assemble``) is the one place such stacks are built. ``seqvpr.methods`` names
the class of every method."""

from __future__ import annotations

from typing import Any


def __getattr__(name: str) -> Any:
    """``seqvpr.matchers.assemble`` and ``Shortlist``, imported when first used (``import seqvpr`` stays light)."""
    if name in ("assemble", "Shortlist"):
        from seqvpr.matchers import stack as module

        return getattr(module, name)
    raise AttributeError(f"module 'seqvpr.matchers' has no attribute {name!r}")
