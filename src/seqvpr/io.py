"""Atomic output files and folders: write under a temporary name beside the target, then rename, so no partial
output remains under the final name."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from seqvpr.errors import SeqvprError


def current_umask() -> int:
    """The process's umask (read by setting it and setting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "w", **open_kwargs) -> Iterator[IO]:
    """Open a temporary file next to ``path``; on success rename it over ``path``, on error delete it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.chmod(tmp, 0o666 & ~current_umask())  # what open() would have given, not mkstemp's private 0600
    try:
        with os.fdopen(fd, mode, **open_kwargs) as handle:
            yield handle
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_folder(path: str | Path, marker: str | None = None) -> Iterator[Path]:
    """Yield an empty temporary folder beside ``path``; on success it replaces ``path`` (an old folder is removed),
    on error it is deleted, so an interrupted run never leaves half a folder under the final name. An existing
    folder is replaced only when it is empty or holds ``marker`` (the file that says it is this kind of output):
    a user's other files are never deleted."""
    path = Path(path)
    check_replaceable(path, marker)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent))
    os.chmod(tmp, 0o777 & ~current_umask())  # what mkdir would have given, not mkdtemp's private 0700
    try:
        yield tmp
        _replace_folder(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def check_replaceable(path: Path, marker: str | None) -> None:
    """``path`` may be replaced by a new output folder: absent, or an empty folder, or one holding ``marker``; and not
    the current folder or one above it (a folder in use cannot be swapped)."""
    if path.exists() and not path.is_dir():
        raise SeqvprError(f"{path} exists and is not a folder; not replacing it")
    if not path.is_dir():
        return
    if Path.cwd().resolve().is_relative_to(path.resolve()):
        raise SeqvprError(f"{path} is the current folder (or holds it); give a new folder to write")
    if any(path.iterdir()) and (marker is None or not (path / marker).is_file()):
        mark = f" and no {marker}" if marker else ""
        raise SeqvprError(f"{path} holds other files{mark}, so it is not this command's output: give a new or empty "
                          "folder (the output folder is replaced whole)")


def _replace_folder(new: Path, target: Path) -> None:
    """Put the finished folder ``new`` in place of ``target``; the old one is restored if the swap fails."""
    if not target.exists():
        os.replace(new, target)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".old", dir=target.parent))
    os.replace(target, old / target.name)
    try:
        os.replace(new, target)
    except BaseException:
        os.replace(old / target.name, target)
        raise
    finally:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def output_lock(path: str | Path) -> Iterator[Path]:
    """Hold ``.<name>.seqvpr-lock`` beside an output file or folder for the duration: a second seqvpr writing the
    same output fails with one line naming the first's process, never interleaving with it. A lock left by a
    process that is gone (killed) is taken over."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    lock = target.parent / f".{target.name}.seqvpr-lock"
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            break
        except FileExistsError:
            holder = _lock_holder(lock)
            if holder is not None:
                raise SeqvprError(f"{target} is being written by another seqvpr (process {holder}; lock {lock})") from None
            lock.unlink(missing_ok=True)  # stale: its process is gone
    else:
        raise SeqvprError(f"{target}: cannot take the lock {lock}")
    with os.fdopen(fd, "w") as handle:
        handle.write(str(os.getpid()))
    try:
        yield lock
    finally:
        lock.unlink(missing_ok=True)


def _lock_holder(lock: Path) -> int | None:
    """The live process holding a lock file, or None when it is gone (or the file is unreadable)."""
    try:
        pid = int(lock.read_text().strip() or "0")
        os.kill(pid, 0)
    except (ValueError, OSError):
        return None
    return pid if pid != os.getpid() else None
