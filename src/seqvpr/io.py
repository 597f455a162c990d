"""Atomic output files and folders: write under a temporary name beside the target, then rename, so no partial
output remains under the final name. A folder replaces an old one by one atomic exchange of the two names, so a
reader sees the old output or the new, never a mix; every rename goes through ``rename`` / ``exchange`` (one place
to inject a failure). Files that belong together among other outputs' files are committed as one set
(``atomic_file_set``: links into a folder swapped whole). Temporaries are named ``.NAME.seqvpr-PID-XXXX.KIND``: one
left by a process that is gone (killed) is removed by the next writer in that folder."""

from __future__ import annotations

import contextlib
import ctypes
import errno
import hashlib
import os
import re
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO, NoReturn

from seqvpr.errors import SeqvprError

#: the longest file name most file systems take, in bytes
NAME_MAX = 255
TEMP_TAG = ".seqvpr-"
_LEFTOVER = re.compile(r"^\..*\.seqvpr-(\d+)-\w+\.(part|old)$")  # a temporary: its process id, its kind
_HELD: set[Path] = set()  # the output locks this process holds
_TEMP_TAIL = TEMP_TAG + "0000000-XXXXXXXX.part"  # the longest tail a temporary name adds (a 7-digit process id)
#: the exception a signal raised, kept until it stops a commit: one that lands while CPython runs a callback whose
#: exceptions it ignores (the lock clean-up after an import, a finaliser) is dropped there, and the command would
#: otherwise go on to replace the output that Ctrl-C was meant to keep
_SIGNALLED: list[BaseException] = []


def raise_for_signal(error: BaseException) -> NoReturn:
    """A signal handler's body (the CLI's, for SIGINT and SIGTERM): raise ``error``, remembered in case it is
    dropped before it reaches the command, so the next commit raises it instead (``check_not_signalled``)."""
    _SIGNALLED[:] = [error]
    raise error


def check_not_signalled() -> None:
    """Before an output is committed: raise a signal's exception that was dropped on its way (once)."""
    if _SIGNALLED:
        raise _SIGNALLED.pop()


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
    fd, tmp = tempfile.mkstemp(prefix=temporary_prefix(path), suffix=".part", dir=path.parent)
    os.chmod(tmp, 0o666 & ~current_umask())  # what open() would have given, not mkstemp's private 0600
    try:
        with os.fdopen(fd, mode, **open_kwargs) as handle:
            yield handle
        check_not_signalled()
        rename(tmp, path)
    except BaseException as error:
        name_target(error, Path(tmp), path)
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
    tmp = temporary_folder(path)
    try:
        yield tmp
        _replace_folder(tmp, path)
    except BaseException as error:
        name_target(error, tmp, path)  # before the temporary goes: a full device is still full
        shutil.rmtree(tmp, ignore_errors=True)
        raise


#: errnos of a failed write: one that names no path (a write to an open file) is said of the output being written
_WRITE_ERRNOS = {errno.ENOSPC, errno.EFBIG, errno.EIO, errno.EROFS, getattr(errno, "EDQUOT", errno.ENOSPC)}


def name_target(error: BaseException, tmp: Path, target: Path) -> None:
    """Make an OSError from writing ``target`` (through its temporary ``tmp``) name ``target`` as the user gave it,
    not the temporary, and name it where the system named nothing (ENOSPC from a write): the one-line error then
    tells the user which output failed."""
    if not isinstance(error, OSError):
        return
    for field in ("filename", "filename2"):
        name = getattr(error, field)
        if isinstance(name, (str, bytes, os.PathLike)) and Path(os.fsdecode(name)).is_relative_to(tmp):
            setattr(error, field, str(target / Path(os.fsdecode(name)).relative_to(tmp)))
    if error.errno is None and error.filename is None:
        error.errno = _short_write_errno(str(error), target)
    if error.filename is None and error.errno in _WRITE_ERRNOS:
        error.filename = str(target)


def _short_write_errno(message: str, target: Path) -> int | None:
    """The errno behind a short write reported without one (numpy's ``N requested and M written``): ENOSPC when
    the device holding ``target`` has less room than the N - M bytes left to write (asked while the partial file is
    still there), EFBIG under a file size limit, else None."""
    import resource

    short = re.search(r"(\d+) requested and (\d+) written", message)
    if short is None:
        return None
    folder = target.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    with contextlib.suppress(OSError):
        device = os.statvfs(folder)
        if device.f_bavail * device.f_frsize < int(short.group(1)) - int(short.group(2)):
            return errno.ENOSPC
    if resource.getrlimit(resource.RLIMIT_FSIZE)[0] != resource.RLIM_INFINITY:
        return errno.EFBIG
    return None


@contextlib.contextmanager
def atomic_file_set(folder: str | Path, names: Sequence[str], manifest: str) -> Iterator[Path]:
    """Files that belong together, written among others' in ``folder``, committed as one: yield an empty temporary
    folder to write some of ``names`` in (``manifest`` always, and last). Each ``folder/NAME`` is a relative link into
    the set's hidden folder (``file_set_folder``), which ``atomic_folder`` swaps whole: a reader sees the old set or
    the new, never a mix, and a NAME the new set lacks disappears with the swap. On error the old set stays."""
    folder = Path(folder)
    store = file_set_folder(folder, manifest)
    folder.mkdir(parents=True, exist_ok=True)
    _adopt_plain_files(folder, names, manifest)
    try:
        for name in names:  # before the swap: a name the old set lacks is a link to nothing (absent) until then
            _point(folder / name, f"{store.name}/{name}")
        with atomic_folder(store, manifest) as tmp:
            yield tmp
    finally:
        for name in names:
            if is_set_link(folder / name) and not (folder / name).exists():
                (folder / name).unlink(missing_ok=True)


def file_set_folder(folder: Path, manifest: str) -> Path:
    """Where ``atomic_file_set`` keeps a set's committed files: the hidden folder ``.MANIFEST.set`` in ``folder``."""
    return folder / f".{short_name(manifest, '.set')}.set"


def is_set_link(path: Path) -> bool:
    """Whether ``path`` is a link ``atomic_file_set`` made (``NAME -> .MANIFEST.set/NAME``); one to nothing is a name
    the committed set lacks (or a killed first run's), not a fault."""
    if not path.is_symlink():
        return False
    target = os.readlink(path)
    return re.fullmatch(r"\.[^/]+\.set/" + re.escape(path.name), target) is not None


def _point(path: Path, target: str) -> None:
    """Make ``path`` a link to ``target``, replacing what is there by one rename (a folder there is an error)."""
    if path.is_symlink() and os.readlink(path) == target:
        return
    if path.is_dir() and not path.is_symlink():
        raise SeqvprError(f"{path} is a folder; a file goes there")
    link = path.parent / f"{temporary_prefix(path)}{os.urandom(4).hex()}.part"
    os.symlink(target, link)
    try:
        rename(link, path)
    except BaseException:
        link.unlink(missing_ok=True)
        raise


def _adopt_plain_files(folder: Path, names: Sequence[str], manifest: str) -> None:
    """A set written as plain files (before sets were linked) becomes the set's committed folder, each name then a
    link to the same bytes: the old output stays whole throughout, and a failed run keeps it."""
    store = file_set_folder(folder, manifest)
    plain = [n for n in names if (folder / n).is_file() and not (folder / n).is_symlink()]
    if store.exists() or manifest not in plain:
        return
    tmp = temporary_folder(store)
    try:
        for name in plain:
            try:
                os.link(folder / name, tmp / name)
            except OSError:
                shutil.copy2(folder / name, tmp / name)
        rename(tmp, store)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    for name in plain:
        _point(folder / name, f"{store.name}/{name}")


def check_replaceable(path: Path, marker: str | None, keep: Sequence[str | Path | None] = ()) -> None:
    """``path`` may be replaced by a new output folder: absent, or an empty folder, or one holding ``marker``; and not
    the current folder or one above it (a folder in use cannot be swapped), nor one holding a path of ``keep`` (the
    run's inputs and other outputs, which the swap would delete)."""
    inside = [str(k) for k in keep if k and Path(k).resolve().is_relative_to(path.resolve())]
    if inside:
        raise SeqvprError(f"{inside[0]} lies in {path}, which is replaced whole by the new output: keep it elsewhere")
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


def check_output_apart(output: str | Path, inputs: Sequence[str | Path | None], what: str = "the output") -> None:
    """The one rule for what seqvpr writes: an output file or folder is none of the run's ``inputs``, lies inside
    none of them and holds none of them. Paths are compared once symbolic links are resolved, and a file also by
    its inode (a hard link is the same file). An input given as a source text (``x.npz:VAR``, ``run.bag:/topic``,
    ``run.bag?gps=/fix``) counts as its file. One line naming both, before anything is written."""
    out = Path(output).resolve()
    for given in inputs:
        if not given:
            continue
        for path in {Path(given), Path(str(given).split("?")[0].split(":")[0] or str(given))}:
            how = _overlap(out, path.resolve())
            if how:
                raise SeqvprError(f"{what} {output} {how} the input {given}: write it elsewhere")


def check_out_folder(folder: str | Path, marker: str | None, inputs: Sequence[str | Path | None],
                     what: str = "--out") -> None:
    """A command's output folder, before anything is read: apart from every input (``check_output_apart``) and
    replaceable whole (``check_replaceable``)."""
    check_output_apart(folder, inputs, what)
    check_replaceable(Path(folder), marker)


def _overlap(out: Path, source: Path) -> str | None:
    """How an output path meets an input path, in words (None: they are apart)."""
    if out == source or (out.is_file() and source.exists() and os.path.samefile(out, source)):
        return "is"
    if out.is_relative_to(source):
        return "lies inside"
    if source.is_relative_to(out):
        return "holds"
    if out.is_file() and source.is_dir() and _in_folder(out, source):
        return "is a file (a hard link) of"
    return None


def _in_folder(output: Path, folder: Path) -> bool:
    """Whether an existing output file is one of the files of ``folder`` under another name (the same inode)."""
    found = os.stat(output)
    with os.scandir(folder) as entries:
        return any(entry.is_file() and entry.inode() == found.st_ino and entry.stat().st_dev == found.st_dev
                   for entry in entries)


def commit_folder(new: Path, target: Path, marker: str | None = None) -> None:
    """Put a finished temporary folder (``temporary_folder``) in place of ``target`` as ``atomic_folder`` does."""
    check_replaceable(target, marker)
    _replace_folder(new, target)


def _replace_folder(new: Path, target: Path) -> None:
    """Put the finished folder ``new`` in place of ``target`` by one atomic exchange of the two names (the old
    folder then sits under ``new``'s temporary name and is removed). Where the file system cannot exchange, the old
    folder is moved aside first, and restored if the second rename fails or, after a kill, by ``sweep_leftovers``."""
    check_not_signalled()
    if not target.exists():
        rename(new, target)
        return
    try:
        exchange(new, target)
    except OSError as error:
        if error.errno not in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EXDEV):
            raise
        _replace_in_two_steps(new, target)
        return
    shutil.rmtree(new, ignore_errors=True)


def _replace_in_two_steps(new: Path, target: Path) -> None:
    """The fallback of ``_replace_folder``: the old folder to a ``.old`` temporary, then the new one in its place."""
    old = Path(tempfile.mkdtemp(prefix=temporary_prefix(target), suffix=".old", dir=target.parent))
    rename(target, old / target.name)
    try:
        rename(new, target)
    except BaseException:
        rename(old / target.name, target)  # if this fails too, the old output waits aside for sweep_leftovers
        shutil.rmtree(old, ignore_errors=True)
        raise
    shutil.rmtree(old, ignore_errors=True)


def rename(source: str | Path, target: str | Path) -> None:
    """``os.replace``: every rename that commits an output goes through here (tests inject failures here)."""
    os.replace(source, target)


def exchange(first: str | Path, second: str | Path) -> None:
    """Swap two existing paths in one atomic step (Linux ``renameat2(RENAME_EXCHANGE)``); OSError ENOSYS where the
    system or file system has no such call."""
    call = _renameat2()
    if call is None:
        raise OSError(errno.ENOSYS, "no atomic exchange on this system", str(first), None, str(second))
    at_cwd, rename_exchange = -100, 2
    if call(at_cwd, os.fsencode(first), at_cwd, os.fsencode(second), rename_exchange) != 0:
        code = ctypes.get_errno()
        raise OSError(code, os.strerror(code), str(first), None, str(second))


def _renameat2():
    """libc's ``renameat2``, or None where there is none (not Linux, or an old C library)."""
    try:
        call = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return None
    call.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    call.restype = ctypes.c_int
    return call


def short_name(name: str, tail: str) -> str:
    """``name`` (a file name) shortened so that ``.NAME`` + ``tail`` fits in NAME_MAX bytes: a name too long keeps
    its start and gains a hash of the whole, so two long names never collide."""
    room = NAME_MAX - len(tail.encode()) - 1
    if len(name.encode()) <= room:
        return name
    digest = hashlib.sha256(name.encode()).hexdigest()[:16]
    head = name.encode()[: max(0, room - 17)].decode(errors="ignore")
    return f"{head}-{digest}"


def temporary_prefix(target: Path) -> str:
    """The start of every temporary name this process makes for ``target``: ``.NAME.seqvpr-PID-``."""
    return f".{short_name(target.name, _TEMP_TAIL)}{TEMP_TAG}{os.getpid()}-"


def temporary_folder(target: Path) -> Path:
    """A new empty folder beside ``target`` (made with mkdir's usual mode) to build ``target`` in; temporaries of
    ``target`` left by dead processes are removed first."""
    target.parent.mkdir(parents=True, exist_ok=True)
    sweep_leftovers(target.parent)
    tmp = Path(tempfile.mkdtemp(prefix=temporary_prefix(target), suffix=".part", dir=target.parent))
    os.chmod(tmp, 0o777 & ~current_umask())  # what mkdir would have given, not mkdtemp's private 0700
    return tmp


def sweep_leftovers(folder: Path) -> list[Path]:
    """Remove the temporaries in ``folder`` whose process is gone (a killed writer's half-written output); an old
    output a killed writer had moved aside, whose name is now free, is put back. The paths handled, returned."""
    try:
        names = [m for m in map(_LEFTOVER.match, os.listdir(folder)) if m and not _alive(int(m.group(1)))]
    except OSError:
        return []
    handled = []
    for match in names:
        path = folder / match.group(0)
        if match.group(2) == "old":
            for kept in list(path.iterdir()) if path.is_dir() else []:
                if not (folder / kept.name).exists():
                    rename(kept, folder / kept.name)
        shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)
        handled.append(path)
    return handled


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists (this process counts as alive)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # exists, owned by someone else
    return True


def lock_path(target: Path) -> Path:
    """The lock file of an output: ``.NAME.seqvpr-lock`` beside it (NAME shortened to fit a file name)."""
    return target.parent / f".{short_name(target.name, '.seqvpr-lock')}.seqvpr-lock"


@contextlib.contextmanager
def output_lock(path: str | Path) -> Iterator[Path]:
    """Hold ``.<name>.seqvpr-lock`` beside an output file or folder for the duration: a second seqvpr writing the
    same output fails with one line naming the first's process, never interleaving with it. A lock left by a
    process that is gone (killed) is taken over."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    lock = lock_path(target)
    if lock.resolve() in _HELD:  # this process holds it already (a build that indexes its map): nested, not taken
        yield lock
        return
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
    try:
        with os.fdopen(fd, "w") as handle:
            handle.write(str(os.getpid()))
    except OSError as error:  # a full device: no empty lock is left to stop the next run
        lock.unlink(missing_ok=True)
        name_target(error, lock, target)
        raise
    _HELD.add(lock.resolve())
    try:
        yield lock
    finally:
        _HELD.discard(lock.resolve())
        lock.unlink(missing_ok=True)


def _lock_holder(lock: Path) -> int | None:
    """The live process holding a lock file, or None when it is gone (or the file is unreadable)."""
    try:
        pid = int(lock.read_text().strip() or "0")
    except (ValueError, OSError):
        return None
    return pid if pid > 0 and pid != os.getpid() and _alive(pid) else None  # another user's live process counts


def carry_over(old: Path, new: Path, skip: tuple[str, ...]) -> None:
    """Everything in ``old`` but ``skip`` (and temporaries) into ``new``, as hard links (copies where the file
    system has none): files are only ever replaced by renames, never edited, so a link is as good as a copy."""
    if not old.is_dir():
        return
    for entry in old.iterdir():
        if entry.name in skip or TEMP_TAG in entry.name:
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.copytree(entry, new / entry.name, symlinks=True, copy_function=link_or_copy)
        else:
            link_or_copy(entry, new / entry.name)


def link_or_copy(source: str | Path, target: str | Path) -> None:
    """``target`` as a hard link to ``source`` (a copy where the file system has no links)."""
    try:
        os.link(source, target, follow_symlinks=False)
    except OSError:
        shutil.copy2(source, target, follow_symlinks=False)
