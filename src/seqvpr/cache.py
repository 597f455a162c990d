"""Where seqvpr keeps what it can rebuild (bag frames, ...): one home for the cache folder, so every cache is found,
listed by ``seqvpr doctor`` and redirected (``$SEQVPR_CACHE``) in one place."""

from __future__ import annotations

import os
from pathlib import Path


def cache_root() -> Path:
    """``$SEQVPR_CACHE`` if set and non-empty, else ``$XDG_CACHE_HOME/seqvpr``, else ``~/.cache/seqvpr``."""
    chosen = os.environ.get("SEQVPR_CACHE", "").strip()  # set but empty: as unset, never the current folder
    if chosen:
        return Path(chosen).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    return (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "seqvpr"


def cache_folder(kind: str) -> Path:
    """The cache folder of one kind of entry (``bag-frames``, ...): ``cache_root() / kind`` (not created here)."""
    return cache_root() / kind


def writable_folder(folder: Path, variable: str = "SEQVPR_CACHE") -> Path:
    """``folder`` created if absent; one line naming it (and ``$variable``, the setting that chose it) when it
    cannot be."""
    from seqvpr.errors import SeqvprError

    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise SeqvprError(f"cache folder {folder} cannot be created ({error.strerror}); point ${variable} at a "
                          "writable folder") from None
    return folder
