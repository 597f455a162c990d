"""Output locks: a second writer of one output is refused with one line naming the first; a stale lock (its
process gone) is taken over; the lock is released after the work, whatever happened."""

from __future__ import annotations

import subprocess

import pytest

from seqvpr.io import output_lock
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


@pytest.mark.parametrize("signum", ["SIGINT", "SIGTERM"])
def test_a_signalled_match_leaves_no_partial_output_and_no_lock(tmp_path, signum):
    """Interrupted mid-work: the folder holds no file under a final name, and the lock is gone."""
    import signal
    import sys
    import time

    import numpy as np

    from seqvpr.data.sources import save_traversal_npz
    from seqvpr.data.traversal import Traversal

    rng = np.random.default_rng(0)
    save_traversal_npz(tmp_path / "ref.npz", Traversal.from_descriptors(rng.random((40000, 64), np.float32), "r"))
    save_traversal_npz(tmp_path / "qry.npz", Traversal.from_descriptors(rng.random((4000, 64), np.float32), "q"))
    command = [sys.executable, "-c", "from seqvpr.cli import main; main()", "match", "-r", str(tmp_path / "ref.npz"),
               "-q", str(tmp_path / "qry.npz"), "--radius", "2f", "-L", "5", "--out", str(tmp_path / "o")]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lock = tmp_path / ".o.seqvpr-lock"
    deadline = time.monotonic() + 60
    while not lock.exists() and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.5)
    process.send_signal(getattr(signal, signum))
    _, err = process.communicate(timeout=60)
    assert process.returncode in (130, 143), err
    assert not lock.exists()
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())
