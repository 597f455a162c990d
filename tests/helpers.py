"""Small assertions shared by the test modules."""

import os
import re
import sys
from pathlib import Path

import pytest

from seqvpr.errors import SeqvprError

#: hypothesis examples per property test in the default (``dev``) profile: a fast loop, every property still exercised
DEV_EXAMPLES = 10


def hypothesis_profile() -> str:
    """``ci`` (each test's full example count) when the environment has ``CI=true`` or ``HYPOTHESIS_PROFILE=ci``,
    else ``dev`` (at most DEV_EXAMPLES each), so the default run stays fast."""
    if os.environ.get("CI", "").lower() == "true" or os.environ.get("HYPOTHESIS_PROFILE") == "ci":
        return "ci"
    return "dev"


def examples(full: int) -> int:
    """A property test's ``max_examples``: ``full`` under the ci profile, at most DEV_EXAMPLES otherwise (an explicit
    ``@settings(max_examples=...)`` outranks any profile, so the count goes through here)."""
    return full if hypothesis_profile() == "ci" else min(full, DEV_EXAMPLES)


def raises_one_line(match: str, fn, *args, **kwargs) -> str:
    """Call fn, expect a SeqvprError whose message is one line containing ``match``; return the message."""
    with pytest.raises(SeqvprError) as info:
        fn(*args, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    assert match in message
    return message


class QuietCapsys:
    """A stand-in for pytest's capsys where a module-scoped fixture runs the CLI (output left where it went)."""

    def readouterr(self) -> tuple[str, str]:
        return "", ""


def run_cli(monkeypatch, capsys, *args) -> tuple[int, str, str]:
    """Run ``seqvpr ARGS`` in-process as a user would; return (exit status, stdout, stderr)."""
    from seqvpr.cli import main

    monkeypatch.setattr(sys, "argv", ["seqvpr", *map(str, args)])
    code = 0
    try:
        main()
    except SystemExit as exit_:
        code = exit_.code or 0
    out, err = capsys.readouterr()
    return code, out, err


def write_route_files(folder, n_frames: int, dim: int, seed: int):
    """A synthetic route's reference and query as traversal files ``ref.npz`` and ``qry.npz`` in ``folder``."""
    from seqvpr.data.sources import save_traversal_npz
    from seqvpr.synthetic.routes import generate_route

    reference, query = generate_route(n_frames=n_frames, dim=dim, seed=seed)
    save_traversal_npz(folder / "ref.npz", reference)
    save_traversal_npz(folder / "qry.npz", query)
    return folder


def spawn_ranks(function, args: tuple, ranks: int = 2, timeout: float = 120.0) -> None:
    """``torch.multiprocessing.spawn`` of ``ranks`` processes, failing (and stopping them) after ``timeout`` seconds
    rather than waiting forever on a rank that hangs."""
    import time

    import torch.multiprocessing as mp

    context = mp.spawn(function, args=args, nprocs=ranks, join=False)
    deadline = time.monotonic() + timeout
    try:
        while not context.join(timeout=1.0):
            if time.monotonic() > deadline:
                for process in context.processes:
                    process.kill()
                raise AssertionError(f"{ranks} ranks of {function.__name__} still running after {timeout:.0f} s")
    except mp.ProcessRaisedException as first:
        raise _own_failure(context, first) from None


#: what a rank raises when a peer's process ended under it (the peer's own error is the one that matters)
PEER_GONE = ("Connection closed by peer", "Connection reset by peer")


def _own_failure(context, first):
    """The error of the rank that failed by itself, not of a rank that lost its connection to it: which of the two
    ``join`` reports first depends on which process the OS ends first (every rank has ended when it raises)."""
    import os
    import pickle

    import torch.multiprocessing as mp

    for index, path in enumerate(context.error_files):
        if os.access(path, os.R_OK) and os.path.getsize(path):
            with open(path, "rb") as handle:
                text = pickle.load(handle)  # torch's own traceback file from a rank this test spawned
            if not any(mark in text for mark in PEER_GONE):
                return mp.ProcessRaisedException(f"\n\n-- Process {index} terminated with the following error:\n{text}",
                                                 index, context.processes[index].pid)
    return first


def run_bad_case(monkeypatch, capsys, args, fragment: str, world, out) -> str:
    """Run one bad-input table case (``{w}``/``{out}`` in ``args`` filled in) and check the promise: exit 2, one
    ``seqvpr: error`` line containing ``fragment`` and no traceback, nothing under ``out``. The stderr, returned.
    It runs in ``out``'s folder, the test's own: a case without ``--out`` writes (or locks) the default output
    folder there, never in a folder other tests share."""
    monkeypatch.chdir(Path(out).parent)
    code, _, err = run_cli(monkeypatch, capsys, *(a.format(w=world, out=out) for a in args))
    lines = [line for line in err.strip().splitlines() if line.startswith("seqvpr: error")]
    assert code == 2, f"exit {code}: {err}"
    assert len(lines) == 1 and "Traceback" not in err, err  # progress lines and warnings may come before it
    assert fragment in lines[0], lines[0]
    assert not out.exists() or not any(out.rglob("*")), f"partial output: {list(out.rglob('*'))}"
    return err


def match_method(name: str, reference, query, settings, models=None, **conf):
    """``seqvpr.match`` by a method's name with the given settings, as every entry point calls it."""
    from seqvpr.api import match

    return match(reference, query, name, models=models or {}, settings=settings, **conf)


NOT_RUN = re.compile(r"<!-- not run: (.+?) -->\s*$")


def fenced_blocks(text: str, language: str | None = None) -> list[tuple[str, str, str | None]]:
    """Each fenced code block of a Markdown text (of ``language`` when given): its language, its code, and why it
    is not run (the ``<!-- not run: why -->`` line just above it; None: it is run)."""
    found = []
    for match in re.finditer(r"```(\w*)\n(.*?)```", text, re.S):
        if language is not None and match.group(1) != language:
            continue
        before = text[: match.start()].rstrip().splitlines()[-1:] or [""]
        marker = NOT_RUN.search(before[0])
        found.append((match.group(1), match.group(2), marker.group(1) if marker else None))
    return found


def write_image_folder(folder, n: int, pixels: tuple[int, int], size: tuple[int, int], seed: int = 0):
    """``n`` random PNG frames ``000.png``... in ``folder``: noise of ``pixels`` (height, width) blown up to ``size``
    (width, height), so each frame is distinct and small."""
    import numpy as np
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        noise = rng.integers(0, 255, (*pixels, 3), dtype=np.uint8)
        Image.fromarray(noise).resize(size).save(folder / f"{i:03d}.png")
    return folder

