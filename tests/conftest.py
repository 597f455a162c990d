"""Shared fixtures: where the real datasets live (skip cleanly when ../shared/data is absent), and a cache folder of
the test run's own (``$SEQVPR_CACHE``), so the suite never writes into the user's home; and hypothesis's profiles
(``tests.helpers.examples``): few examples by default, each test's full count under ``CI=true``."""

import os
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import settings

from tests.helpers import DEV_EXAMPLES, hypothesis_profile

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
_CACHE: list[str] = []

settings.register_profile("dev", max_examples=DEV_EXAMPLES, deadline=None)
settings.register_profile("ci", deadline=None)
settings.load_profile(hypothesis_profile())


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


def pytest_collection_modifyitems(session, config, items) -> None:
    """Modules with slow tests first, each module's tests together and in order: under ``-n auto`` each module is
    one worker's (``--dist loadscope``, so its fixtures are made once), and the long ones start early instead of
    leaving one worker busy at the end."""
    modules: dict[str, list] = {}
    for item in items:
        modules.setdefault(item.nodeid.split("::")[0], []).append(item)
    ordered = sorted(modules.values(), key=lambda tests: -sum(t.get_closest_marker("slow") is not None for t in tests))
    items[:] = [item for tests in ordered for item in tests]


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not DATA.is_dir():
        pytest.skip("../shared/data is not present")
    return DATA
