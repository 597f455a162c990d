"""Progress of long work, one mechanism for the command line and for Python: a progress factory
``(total, label) -> update(n)``. The CLI passes its own (a bar on a terminal, else lines); a Python caller who
passes none gets lines on the ``seqvpr`` logger, silent until logging is turned on
(``logging.basicConfig(level=logging.INFO)``), as a library should be.

Same name as ``seqvpr.cli.progress``: progress as the library reports it; the command line's bars there."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

ProgressFactory = Callable[[int, str], Callable[[int], None]]
LOGGER = logging.getLogger("seqvpr")
LINE_SECONDS = 10.0


def line_progress(total: int, label: str, every: float = LINE_SECONDS, clock=time.monotonic,
                  echo: Callable[[str], None] | None = None, unit: str = "frames") -> Callable[[int], None]:
    """An update function printing ``label: done/total UNIT (p %)`` when ``every`` seconds have passed since the
    last line, and once at the end: long work never looks dead in a log. ``echo`` defaults to the logger."""
    say = echo or LOGGER.info
    state = {"done": 0, "last": clock()}

    def update(n: int = 1) -> None:
        state["done"] += n
        now = clock()
        finished = state["done"] >= total
        if now - state["last"] >= every or (finished and state["done"] - n < total):
            state["last"] = now
            say(f"{label}: {state['done']}/{total} {unit} ({100 * state['done'] / max(total, 1):.0f} %)")

    return update


def logged_progress(total: int, label: str) -> Callable[[int], None]:
    """The progress factory Python entry points use when given none: lines on the ``seqvpr`` logger."""
    return line_progress(total, label)


def progress_or_log(progress: ProgressFactory | None) -> ProgressFactory:
    """``progress``, else lines on the logger."""
    return progress if progress is not None else logged_progress


def silent(total: int, label: str) -> Callable[[int], None]:
    """A progress factory that reports nothing (a process that is not the one reporting)."""
    return lambda n=1: None
