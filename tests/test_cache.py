"""seqvpr's cache folder: one home (``seqvpr.cache``), chosen by the environment, never the current folder."""

from __future__ import annotations

import os
from pathlib import Path

from seqvpr.cache import cache_folder, cache_root


def test_the_cache_root_follows_seqvpr_cache_then_xdg_then_home(tmp_path, monkeypatch):
    monkeypatch.setenv("SEQVPR_CACHE", str(tmp_path / "mine"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_root() == tmp_path / "mine" and cache_folder("bag-frames") == tmp_path / "mine" / "bag-frames"
    monkeypatch.setenv("SEQVPR_CACHE", "")  # set but empty: as unset
    assert cache_root() == tmp_path / "xdg" / "seqvpr"
    monkeypatch.delenv("SEQVPR_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", " ")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_root() == tmp_path / "home" / ".cache" / "seqvpr"


def test_the_test_run_has_a_cache_of_its_own():
    root = Path(os.environ["SEQVPR_CACHE"])
    assert root.is_dir() and Path.home() not in root.parents
