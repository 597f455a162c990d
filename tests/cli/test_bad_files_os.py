"""The operating system's no (a full device, a file size limit, a read-only file system, permission denied, a name
too long) is one ``seqvpr: error`` line naming the path, exit status 2, no temporary left, and the previous output
in the target as it was. Real refusals where this process may make them (a small tmpfs as root, ``ulimit -f`` in
a subprocess); injected ones elsewhere."""

from __future__ import annotations

import contextlib
import errno
import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from seqvpr.io import TEMP_TAG
from tests.helpers import run_cli, write_route_files

LONG = "n" * 300  # a file name over the 255 bytes a file system allows


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A small route (a good output fits anywhere) and a larger one (its map and predictions exceed 256 KiB)."""
    folder = tmp_path_factory.mktemp("os")
    write_route_files(folder / _mkdir(folder / "small"), 80, 16, 2)
    write_route_files(folder / _mkdir(folder / "big"), 1500, 64, 3)
    return folder


def _mkdir(path: Path) -> Path:
    path.mkdir()
    return path


def _command(kind: str, inputs: Path, size: str, out: Path) -> list[str]:
    """``map build`` or ``match`` of the ``size`` route into ``out``."""
    if kind == "map":
        return ["map", "build", str(inputs / size / "ref.npz"), "--out", str(out)]
    return ["match", "-r", str(inputs / size / "ref.npz"), "-q", str(inputs / size / "qry.npz"), "--radius", "10m",
            "--out", str(out)]


@contextlib.contextmanager
def tmpfs(folder: Path, size: str = "256k"):
    """Mount a tmpfs of ``size`` on ``folder`` (made here) when this process may; yield whether it did."""
    folder.mkdir()
    mounted = os.geteuid() == 0 and subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                                                   capture_output=True).returncode == 0
    try:
        yield mounted
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(folder)], check=True)


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _good_output(kind: str, inputs: Path, out: Path, monkeypatch, capsys) -> dict[str, bytes]:
    code, _, err = run_cli(monkeypatch, capsys, *_command(kind, inputs, "small", out))
    assert code == 0, err
    return _snapshot(out)


def _assert_refused(code: int, err: str, fragment: str, path: Path, folder: Path, before: dict, out: Path) -> None:
    """Exit 2, one error line holding ``fragment`` and naming ``path``, no temporary (or lock) left in ``folder``,
    and ``out`` as ``before``."""
    lines = [line for line in err.strip().splitlines() if line.startswith("seqvpr: error")]
    assert code == 2, f"exit {code}: {err}"
    assert len(lines) == 1 and "Traceback" not in err, err
    assert fragment in lines[0] and str(path) in lines[0], lines[0]
    assert not [p for p in folder.rglob("*") if TEMP_TAG in p.name], list(folder.rglob("*"))
    assert _snapshot(out) == before


@pytest.mark.parametrize("kind", ["map", "match"])
def test_a_full_device(inputs, tmp_path, monkeypatch, capsys, kind):
    folder, out = tmp_path / "small-disk", tmp_path / "small-disk" / "out"
    with tmpfs(folder) as mounted:
        before = _good_output(kind, inputs, out, monkeypatch, capsys)
        if not mounted:  # not root, or no mount here: the device says no where the output is committed
            _inject(monkeypatch, errno.ENOSPC, named=False)
        code, _, err = run_cli(monkeypatch, capsys, *_command(kind, inputs, "big", out))
        _assert_refused(code, err, "no space left on the device holding", out, folder, before, out)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["map", "match"])
def test_a_file_size_limit_is_a_line_not_a_signal(inputs, tmp_path, monkeypatch, capsys, kind):
    """Past ``ulimit -f`` the kernel sends SIGXFSZ, which would kill seqvpr with no word; it is ignored, so the
    write fails with EFBIG and that is the line."""
    out = tmp_path / "out"
    before = _good_output(kind, inputs, out, monkeypatch, capsys)
    limit = 64 * 1024
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parents[2] / "src"), *sys.path])}
    done = subprocess.run([sys.executable, "-m", "seqvpr.cli", *_command(kind, inputs, "big", out)], env=env,
                          capture_output=True, text=True, timeout=120,
                          preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)))
    assert done.returncode >= 0, f"killed by signal {-done.returncode}"
    _assert_refused(done.returncode, done.stderr, "file size limit reached writing", out, tmp_path, before, out)


def test_a_read_only_file_system(inputs, tmp_path, monkeypatch, capsys):
    folder, out = tmp_path / "ro", tmp_path / "ro" / "out"
    with tmpfs(folder, "4m") as mounted:
        before = _good_output("map", inputs, out, monkeypatch, capsys)
        if mounted and subprocess.run(["mount", "-o", "remount,ro", str(folder)]).returncode == 0:
            code, _, err = run_cli(monkeypatch, capsys, *_command("map", inputs, "small", out))
            _assert_refused(code, err, "Read-only file system", folder, folder, before, out)  # found before any work
            return
        _inject(monkeypatch, errno.EROFS)
        code, _, err = run_cli(monkeypatch, capsys, *_command("map", inputs, "small", out))
        _assert_refused(code, err, "is on a read-only file system: write elsewhere", out, folder, before, out)


def _inject(monkeypatch, code: int, named: bool = True) -> None:
    """``seqvpr.io.rename`` and ``exchange`` (where every output is committed) refused with ``code``, naming both
    paths as the system does (``named``), or none, as a write() does."""
    def refuse(source, target):
        if named:
            raise OSError(code, os.strerror(code), str(source), None, str(target))
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr("seqvpr.io.rename", refuse)
    monkeypatch.setattr("seqvpr.io.exchange", refuse)


@pytest.mark.parametrize("kind", ["map", "match"])
def test_permission_denied(inputs, tmp_path, monkeypatch, capsys, kind):
    """As root a mode of 0o555 does not stop a write, so the refusal is injected where the output is committed."""
    out = tmp_path / "out"
    before = _good_output(kind, inputs, out, monkeypatch, capsys)
    _inject(monkeypatch, errno.EACCES)
    code, _, err = run_cli(monkeypatch, capsys, *_command(kind, inputs, "small", out))
    _assert_refused(code, err, "permission denied: ", out, tmp_path, before, out)
    assert TEMP_TAG not in err  # the output is named as the user gave it, not its temporary


@pytest.mark.parametrize("kind", ["map", "match", "extract"])
def test_an_out_name_over_255_bytes_is_refused_before_any_work(inputs, tmp_path, monkeypatch, capsys, kind):
    out = tmp_path / (LONG + (".npz" if kind == "extract" else ""))
    args = ["extract", str(inputs), "--out", str(out)] if kind == "extract" else _command(kind, inputs, "small", out)
    code, _, err = run_cli(monkeypatch, capsys, *args)
    _assert_refused(code, err, "is longer than the file system allows (255 bytes", out, tmp_path, {}, tmp_path)


def test_an_os_error_it_does_not_know_stays_as_it_was(inputs, tmp_path, monkeypatch, capsys):
    _inject(monkeypatch, errno.EAGAIN)
    with pytest.raises(BlockingIOError):
        run_cli(monkeypatch, capsys, *_command("match", inputs, "small", tmp_path / "out"))


def test_a_device_too_full_for_the_lock(inputs, tmp_path, monkeypatch, capsys):
    """The lock beside the output cannot even hold its process id: one line, and no empty lock left to refuse the
    next run."""
    folder, out = tmp_path / "full", tmp_path / "full" / "out"
    with tmpfs(folder, "64k") as mounted:
        if not mounted:
            pytest.skip("needs a tmpfs mount (root); the lock's refusal is injected in tests/test_os_refusals.py")
        before = _good_output("match", inputs, out, monkeypatch, capsys)
        with contextlib.suppress(OSError), open(folder / "filler", "wb") as filler:
            while True:
                filler.write(b"\0" * 4096)
                filler.flush()
        code, _, err = run_cli(monkeypatch, capsys, *_command("match", inputs, "small", out))
        _assert_refused(code, err, "no space left on the device holding", out, folder, before, out)
