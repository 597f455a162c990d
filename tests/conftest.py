"""Shared fixtures: where the real datasets live (skip cleanly when ../shared/data is absent), and a cache folder of
the test run's own (``$SEQVPR_CACHE``), so the suite never writes into the user's home."""

import os
import shutil
import tempfile
from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
_CACHE: list[str] = []


def pytest_configure(config) -> None:
    """Point seqvpr's cache (``seqvpr.cache.cache_root``) at a fresh temporary folder for the whole run, before any
    test (or a process one spawns, which inherits the environment) can reach it."""
    _CACHE.append(tempfile.mkdtemp(prefix="seqvpr-test-cache-"))
    os.environ["SEQVPR_CACHE"] = _CACHE[-1]
    os.environ.pop("SEQVPR_BAG_FRAMES", None)


def pytest_unconfigure(config) -> None:
    """Remove the run's cache folder."""
    for folder in _CACHE:
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not DATA.is_dir():
        pytest.skip("../shared/data is not present")
    return DATA
