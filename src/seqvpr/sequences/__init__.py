"""Sequence windows, the matching kernel, sequence descriptors, retrieval and hierarchical re-ranking."""

import importlib


def __getattr__(name: str):
    """``_fused``, the compiled kernels, imported on first use (numba takes a third of a second to load). A caller
    that runs every frame reaches them as ``sequences._fused.kernel``: a plain attribute once imported, where an
    import statement costs tens of microseconds after a map's distance pass has flushed the caches."""
    if name == "_fused":
        return importlib.import_module("seqvpr.sequences._fused")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
