"""Output locks: a second writer of one output is refused with one line naming the first; a stale lock (its
process gone) is taken over; the lock is released after the work, whatever happened."""

from __future__ import annotations

import os
import subprocess

import pytest

from seqvpr.io import atomic_folder, atomic_write, output_lock, raise_for_signal
from tests.helpers import raises_one_line, run_cli, write_route_files


def test_a_live_holder_is_refused_and_a_dead_one_taken_over(tmp_path):
    holder = subprocess.Popen(["sleep", "30"])
    try:
        (tmp_path / ".out.seqvpr-lock").write_text(str(holder.pid))
        raises_one_line(f"being written by another seqvpr (process {holder.pid}", output_lock(tmp_path / "out").__enter__)
    finally:
        holder.kill()
        holder.wait()
    with output_lock(tmp_path / "out") as lock:  # the holder is gone: its lock is stale
        assert lock.read_text().strip().isdigit()
    assert not (tmp_path / ".out.seqvpr-lock").exists()
    with pytest.raises(RuntimeError), output_lock(tmp_path / "out"):
        raise RuntimeError("the work failed")
    assert not (tmp_path / ".out.seqvpr-lock").exists()


def test_two_matches_into_one_out_do_not_interleave(tmp_path, monkeypatch, capsys):
    write_route_files(tmp_path, 40, 8, 1)
    holder = subprocess.Popen(["sleep", "30"])
    try:
        (tmp_path / ".o.seqvpr-lock").write_text(str(holder.pid))
        code, _, err = run_cli(monkeypatch, capsys, "match", "-r", tmp_path / "ref.npz", "-q", tmp_path / "qry.npz",
                               "--radius", "10m", "--out", tmp_path / "o")
    finally:
        holder.kill()
        holder.wait()
    assert code == 2 and "being written by another seqvpr" in err and not (tmp_path / "o").exists()


def _inputs(folder):
    """Work long enough to be interrupted (a few seconds each), and small inputs for a previous complete output."""
    import numpy as np
    from PIL import Image

    from seqvpr.data.sources import save_traversal_npz
    from seqvpr.data.traversal import Traversal

    rng = np.random.default_rng(0)
    save_traversal_npz(folder / "ref.npz", Traversal.from_descriptors(rng.random((40000, 64), np.float32), "r"))
    save_traversal_npz(folder / "qry.npz", Traversal.from_descriptors(rng.random((4000, 64), np.float32), "q"))
    save_traversal_npz(folder / "big.npz", Traversal.from_descriptors(rng.random((200000, 64), np.float32), "b"))
    for name, count in (("imgs", 3000), ("few", 4)):
        (folder / name).mkdir()
        for i in range(count):
            Image.fromarray(rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)).save(folder / name / f"{i:05d}.png")
    (folder / "route").mkdir()
    write_route_files(folder / "route", 80, 16, 2)


#: a command whose work is interrupted, and the same command on small inputs (its previous complete output)
INTERRUPTED = {
    "match": (("match", "-r", "{d}/ref.npz", "-q", "{d}/qry.npz", "--radius", "2f", "-L", "5", "--out", "{d}/o"),
              ("match", "-r", "{d}/route/ref.npz", "-q", "{d}/route/qry.npz", "--radius", "10m", "--out", "{d}/o")),
    "extract": (("extract", "{d}/imgs", "--out", "{d}/o.npz"), ("extract", "{d}/few", "--out", "{d}/o.npz")),
    "map build": (("map", "build", "{d}/big.npz", "--dtype", "pq:8", "--out", "{d}/o"),
                  ("map", "build", "{d}/route/ref.npz", "--out", "{d}/o")),
    "train": (("train", "seqmatchnet", "-r", "{d}/route/ref.npz", "-q", "{d}/route/qry.npz", "--radius", "10m",
               "--train-frames", "0:50", "--val-frames", "50:80", "-L", "3", "--epochs", "400", "--out", "{d}/o"),
              None),
}


@pytest.fixture(scope="module")
def interrupt_inputs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("interrupt")
    _inputs(folder)
    return folder


def _snapshot(out) -> dict[str, bytes]:
    """Every file under ``out`` (a file or a folder) by relative name, with its bytes."""
    if out.is_file():
        return {out.name: out.read_bytes()}
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


@pytest.mark.slow
@pytest.mark.parametrize("command,signum", [("match", "SIGINT"), ("match", "SIGTERM"), ("extract", "SIGTERM"),
                                            ("map build", "SIGINT"), ("train", "SIGTERM")])
def test_a_signalled_command_leaves_the_previous_output_or_none(interrupt_inputs, tmp_path, command, signum):
    """Interrupted mid-work: the previous complete output is still there byte for byte (or, for training, only
    complete checkpoint files are), no temporary file is left beside it, and the lock is gone."""
    import signal
    import sys
    import time

    work, before = ([a.format(d=tmp_path) if "{d}/o" in a else a.format(d=interrupt_inputs) for a in args]
                    if args else None for args in INTERRUPTED[command])
    out = tmp_path / ("o.npz" if command == "extract" else "o")
    if before:
        assert run_cli(pytest.MonkeyPatch(), _NoCapture(), *before)[0] == 0
    previous = _snapshot(out) if out.exists() else None
    # a shell that starts jobs in the background (CI's, nohup's) hands them SIGINT ignored: restore Ctrl-C's handler
    child = "import signal; signal.signal(signal.SIGINT, signal.default_int_handler); from seqvpr.cli import main; main()"
    process = subprocess.Popen([sys.executable, "-c", child, *work],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lock = tmp_path / f".{out.name}.seqvpr-lock"
    started = out / "history.csv" if command == "train" else lock  # training: once checkpoints are being written
    deadline = time.monotonic() + 60
    while not started.exists() and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.3 if command == "train" else 1.0)
    assert process.poll() is None, "the work ended before the signal; give it more to do"
    process.send_signal(getattr(signal, signum))
    _, err = process.communicate(timeout=60)
    assert process.returncode == {"SIGINT": 130, "SIGTERM": 143}[signum], err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("seqvpr: "), err
    assert not lock.exists()
    assert not [p.name for p in tmp_path.rglob("*") if p.name.endswith((".part", ".old"))]
    if previous is not None:
        assert _snapshot(out) == previous
    else:
        _assert_training_files_complete(out)


def _assert_training_files_complete(out) -> None:
    """Whatever a signalled training left is whole: its JSON parses, its tensors load, its history rows are full."""
    import json

    from safetensors.numpy import load_file

    for path in out.rglob("*") if out.exists() else ():
        if path.suffix == ".json":
            json.loads(path.read_text())
        elif path.suffix == ".safetensors":
            load_file(path)
        elif path.suffix == ".csv":
            rows = path.read_text().splitlines()
            assert len({row.count(",") for row in rows}) == 1, rows


class _NoCapture:
    def readouterr(self):
        return "", ""


def _dead_pid() -> int:
    """A process id that is no longer running (a child that has exited)."""
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


def test_a_folder_replaces_the_old_by_one_exchange_and_leaves_no_temporary(tmp_path):
    from seqvpr.io import atomic_folder

    for text in ("old", "new"):
        with atomic_folder(tmp_path / "out", "m") as tmp:
            (tmp / "m").write_text(text)
    assert (tmp_path / "out" / "m").read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["out"]


def test_without_an_exchange_a_kill_between_the_renames_is_undone_by_the_next_writer(tmp_path, monkeypatch):
    """Where the file system cannot exchange, the old folder is moved aside first: a writer killed right then
    leaves the old output under a temporary name, which the next writer in the folder puts back."""
    import errno
    import os

    import seqvpr.io as io

    with io.atomic_folder(tmp_path / "out", "m") as tmp:
        (tmp / "m").write_text("old")

    def no_exchange(a, b):
        raise OSError(errno.EINVAL, "not here")

    renames = []

    def killed_after_one(source, target):
        if renames:
            raise KeyboardInterrupt  # the kill, between the two renames
        renames.append(target)
        os.replace(source, target)

    monkeypatch.setattr(io, "exchange", no_exchange)
    monkeypatch.setattr(io, "rename", killed_after_one)
    with pytest.raises(KeyboardInterrupt):
        with io.atomic_folder(tmp_path / "out", "m") as tmp:
            (tmp / "m").write_text("new")
    monkeypatch.undo()
    # what the kill leaves: the old output moved aside under this process's temporary name; a dead process's:
    aside = next(p for p in tmp_path.iterdir() if p.name.endswith(".old"))
    assert not (tmp_path / "out").exists() and (aside / "out" / "m").read_text() == "old"
    dead = tmp_path / aside.name.replace(f"seqvpr-{os.getpid()}-", f"seqvpr-{_dead_pid()}-")
    aside.rename(dead)
    (tmp_path / f".out.seqvpr-{_dead_pid()}-abc.part").mkdir()
    assert len(io.sweep_leftovers(tmp_path)) == 2
    assert (tmp_path / "out" / "m").read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["out"]


def test_a_live_process_s_temporaries_are_left_alone(tmp_path):
    import os

    from seqvpr.io import sweep_leftovers

    mine = tmp_path / f".out.seqvpr-{os.getpid()}-abc.part"
    mine.mkdir()
    (tmp_path / ".out.seqvpr-notapid-abc.part").mkdir()
    assert sweep_leftovers(tmp_path) == [] and mine.exists()


def test_names_too_long_for_a_lock_or_a_temporary_are_shortened_alike(tmp_path):
    from seqvpr.io import NAME_MAX, atomic_folder, lock_path, output_lock, temporary_prefix

    target = tmp_path / ("x" * 250)
    assert len(lock_path(target).name.encode()) <= NAME_MAX
    assert lock_path(target) != lock_path(tmp_path / ("x" * 249 + "y"))
    assert len(temporary_prefix(target).encode()) + len("XXXXXXXX.part") <= NAME_MAX
    with output_lock(target), atomic_folder(target) as tmp:
        (tmp / "f").write_text("1")
    assert (target / "f").read_text() == "1"


def test_a_lock_held_by_this_process_is_taken_again_inside_and_released_by_its_holder(tmp_path):
    from seqvpr.io import lock_path, output_lock

    with output_lock(tmp_path / "m"):
        with output_lock(tmp_path / "m"):
            pass
        assert lock_path(tmp_path / "m").exists()
    assert not lock_path(tmp_path / "m").exists()


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the drop this test makes
def test_a_signal_dropped_on_its_way_still_stops_the_next_commit(tmp_path):
    """A signal whose exception CPython drops (raised inside a callback whose exceptions it ignores, as the lock
    clean-up after an import is) still stops the next commit, of a file or a folder: the old output stays, no
    temporary is left, and only that one commit is stopped."""
    import weakref

    class Finalised:
        pass

    target, folder = tmp_path / "out.txt", tmp_path / "out"
    target.write_text("old")
    for commit in ("file", "folder"):
        thing = Finalised()
        keep = weakref.ref(thing, lambda _: raise_for_signal(KeyboardInterrupt()))
        del thing  # the callback runs here and its KeyboardInterrupt is dropped ("Exception ignored in ...")
        assert keep() is None
        with pytest.raises(KeyboardInterrupt):
            if commit == "file":
                with atomic_write(target) as handle:
                    handle.write("new")
            else:
                with atomic_folder(folder) as tmp:
                    (tmp / "f").write_text("new")
        assert target.read_text() == "old" and not folder.exists()
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]
    with atomic_write(target) as handle:
        handle.write("new")
    assert target.read_text() == "new"


def test_an_output_is_none_of_the_inputs_lies_in_none_and_holds_none(tmp_path):
    """The one rule for outputs (``check_output_apart``): the same path, the same file through a symbolic or hard
    link, a path inside an input folder, a folder holding an input, and a source text's file are all refused."""
    from seqvpr.io import check_output_apart
    from tests.helpers import raises_one_line

    (tmp_path / "in").mkdir()
    data = tmp_path / "in" / "x.npz"
    data.write_bytes(b"x")
    (tmp_path / "link.npz").symlink_to(data)
    os.link(data, tmp_path / "hard.npz")
    for output, how in ((data, "is"), (tmp_path / "link.npz", "is"), (tmp_path / "hard.npz", "is"),
                        (tmp_path / "in" / "y.npz", "lies inside"), (tmp_path / "in" / "sub" / "y", "lies inside"),
                        (tmp_path, "holds")):
        raises_one_line(f"{how} the input", check_output_apart, output, [tmp_path / "in"] if how != "is" else [data])
    raises_one_line("is the input", check_output_apart, data, [f"{data}:descriptors"])
    raises_one_line("lies inside the input", check_output_apart, tmp_path / "bag" / "out.npz",
                    [f"{tmp_path / 'bag'}:/camera?gps=/fix"])
    check_output_apart(tmp_path / "out.npz", [data, None, tmp_path / "in"])  # beside them: fine
